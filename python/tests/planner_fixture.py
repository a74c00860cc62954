"""The JSON fixture of what b2dr sends a protocol-v2 planner (tests/fixtures/planner_v2_session.json: one
`b2dr run --scenario builtin:town --renderer groundtruth --steps 6 --command-def nuscenes --history 4` recorded by
python/tests/fixtures/record_planner.py), and wire messages built from it for tests that serve a planner."""
import copy
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIXTURE = REPO / "tests" / "fixtures" / "planner_v2_session.json"


def session():
    """{"start": <start message>, "plans": [<plan message at step 0>, <at step 5>]}."""
    return json.loads(FIXTURE.read_text())


def start_message(scenario=None):
    m = copy.deepcopy(session()["start"])
    if scenario is not None:
        m["scenario"] = scenario
    return m


def plan_message(step=5, images=None, command=None, ego=None, scenario=None):
    """The recorded plan message of `step` (0 or 5; another step: the step-5 message relabelled), with `images` {camera: (H, W, 3) uint8} sent inline (those cameras only, their
    width and height set; the calibration stays the recorded one), `command` / `ego` fields overridden.
    Returns (message dict, inline bytes)."""
    plans = {p["step"]: p for p in session()["plans"]}
    m = copy.deepcopy(plans.get(step, plans[5]))
    m["step"], m["time_s"] = step, step / 10
    if scenario is not None:
        m["scenario"] = scenario
    if command is not None:
        m["command"] = command
    m["ego"].update(ego or {})
    inline = b""
    if images is not None:
        cams = {c["camera"]: c for c in m["cameras"]}
        m["cameras"] = []
        for name, img in images.items():
            c = dict(cams.get(name, cams["CAM_FRONT"]), camera=name, height=img.shape[0], width=img.shape[1])
            c.update(offset=len(inline), bytes=img.nbytes)
            inline += img.tobytes()
            m["cameras"].append(c)
    m["inline_bytes"] = len(inline)
    return m, inline


def wire(msg, inline=b""):
    """One message as b2dr writes it: the JSON line, then the inline bytes."""
    return (json.dumps(msg) + "\n").encode() + inline
