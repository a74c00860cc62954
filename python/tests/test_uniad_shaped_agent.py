"""Acceptance of issue #34 (the resident service with a UniAD-shaped agent): examples/uniad_shaped_agent.py (inputs
built by the adapter's img_metas, output 6 xy points at 0.5 s in the lidar frame) drives the six held-out dense
scenarios of tools/closed_loop_table.py through `--planner resident:` with ONE model load, and scores within
0.02 of the same agent run one process per scenario (`cmd:`, six loads). Kept cheap: the groundtruth renderer,
the front camera at 112x200, 10 steps (2 plans) per scenario; docs/planner_protocol.md has the full-length
figures."""
import json
import shlex
import subprocess
import sys
import time

import pytest

from planner_fixture import REPO
from scale_helpers import b2dr_binary

sys.path.insert(0, str(REPO / "tools"))
from closed_loop_table import DEFAULT_SCENARIOS  # noqa: E402

STEPS = 10


def run(mode, out, extra=()):
    loads = out / "loads"
    agent = f"exec {shlex.quote(sys.executable)} {REPO / 'examples' / 'uniad_shaped_agent.py'} --loads {loads}"
    t0 = time.time()
    r = subprocess.run([b2dr_binary(), "run", "--scenario", DEFAULT_SCENARIOS, "--renderer", "groundtruth",
                        "--cameras", "CAM_FRONT", "--steps", str(STEPS), "--agents", "idm", "--no-gif",
                        "--planner", f"{mode}:{agent}", "--planner-timeout", "30", "--out", str(out / "run"), *extra],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((out / "run" / "metrics.json").read_text())
    n_loads = len(loads.read_text().splitlines())
    print(f"{mode}: {time.time() - t0:.1f} s, {n_loads} load(s), CLS {m['cls']:.4f}")
    return m, n_loads


def test_resident_uniad_shaped_agent_scores_as_one_process_per_scenario(tmp_path):
    (tmp_path / "r").mkdir()
    (tmp_path / "c").mkdir()
    res, res_loads = run("resident", tmp_path / "r")
    cmd, cmd_loads = run("cmd", tmp_path / "c")
    assert len(res["scenarios"]) == len(cmd["scenarios"]) == 6
    assert res_loads == 1 and cmd_loads == 6
    for a, b in zip(res["scenarios"], cmd["scenarios"]):
        assert a["failure"] is None and b["failure"] is None, (a["failure"], b["failure"])
        assert a["scenario"] == b["scenario"]
        assert a["planner_process"]["process"] == 1 and not a["planner_process"]["restarted"]
        assert abs(a["score"] - b["score"]) <= 0.02, (a["scenario"], a["score"], b["score"])
        assert a["frames"] == STEPS // 5
    assert abs(res["cls"] - cmd["cls"]) <= 0.02
