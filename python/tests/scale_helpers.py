"""The b2dr binary for the scale-out tests (python/tests/test_ray_driver.py, test_scale_out_examples.py)."""
import json
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# six short built-in scenarios, out of name order (as tests/scale_out.rs)
SCENARIOS = "builtin:town:0,builtin:cross:0,builtin:straight:1,builtin:curve:0,builtin:town:1,builtin:tjunction:0"
SIM_ARGS = ["sim", "--scenario", SCENARIOS, "--steps", "150", "--bev-every", "0"]


def b2dr_binary() -> str:
    """B2DR_BIN, else the debug build of `cargo test` (CARGO_TARGET_DIR or target/); skips when absent."""
    candidates = [os.environ.get("B2DR_BIN")]
    for t in (os.environ.get("CARGO_TARGET_DIR"), REPO / "target"):
        if t:
            candidates += [Path(t) / "debug" / "b2dr", Path(t) / "release" / "b2dr"]
    for c in candidates:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return str(Path(c).resolve())
    pytest.skip("no b2dr binary: build it (cargo build) or set B2DR_BIN")


def deterministic(summary: dict) -> dict:
    """A metrics.json without what differs between two runs of one configuration (timings, merge list)."""
    s = {k: v for k, v in summary.items() if k not in ("timing_ms", "merged_from", "device_bytes")}
    s["scenarios"] = [{k: v for k, v in sc.items() if k not in ("wall_ms", "timing_ms", "timing_per_frame")}
                      for sc in summary["scenarios"]]
    return s


def load(p) -> dict:
    with open(p) as f:
        return json.load(f)
