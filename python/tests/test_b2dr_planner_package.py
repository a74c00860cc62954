"""The planner package python/b2dr_planner (issue #34 item 6) on the recorded request fixture
(tests/fixtures/planner_v2_session.json: what `b2dr run` sent): the one parser's typed records and its errors,
the trajectory checks (what b2dr refuses), the command encodings, the Agent base class and the service loop
(hello / start / plan / end, resident and cmd), and that the core imports without numpy."""
import io
import json
import math
import subprocess
import sys

import pytest

import b2dr_planner as bp
from planner_fixture import REPO, plan_message, session, start_message, wire


def parsed(step=5):
    s = bp.parse_message(start_message())
    m, inline = plan_message(step)
    return s, bp.parse_message(m, inline, s)


def test_records_hold_what_b2dr_sent():
    raw = session()
    s, r = parsed()
    assert isinstance(s, bp.StartInfo) and isinstance(r, bp.PlanRequest)
    assert s.scenario == raw["start"]["scenario"] and s.dt_s == 0.1 and len(s.rig) == 6
    assert s.rig[0].width == 1600 and s.rig[0].intrinsic[0][0] == raw["start"]["rig"][0]["intrinsic"][0][0]
    assert s.lidar2ego[2][3] == pytest.approx(1.84019) and s.ego.wheel_base == raw["start"]["ego"]["wheel_base"]
    p = raw["plans"][1]
    assert (r.step, r.time_s, r.version) == (5, 0.5, 2)
    assert r.ego.vx == p["ego"]["vx"] and r.ego.x == p["ego"]["x"] and r.ego_params.length == p["ego"]["length"]
    assert r.command is bp.Command.STRAIGHT and r.command_def == "nuscenes"
    assert [(h.time_s, h.source) for h in r.history] == [(-0.5, "sim"), (-1.0, "pad"), (-1.5, "pad"), (-2.0, "pad")]
    assert r.history[0].x == p["history"][0]["x"]
    assert [c.name for c in r.cameras] == [c["camera"] for c in p["cameras"]]
    assert r.cameras[1].lidar2img[2][0] == p["cameras"][1]["lidar2img"][2][0]  # rows, not columns
    assert r.cameras[0].checksum == int(p["cameras"][0]["fnv1a64"])
    assert r.reply.min_horizon_s == 2.0 and r.lidar2ego == s.lidar2ego
    assert r.route.lane_ids == tuple(p["route"]["lane_ids"]) and r.route.mission_goal is None
    # version 1 (`b2dr sim`): no type, no cameras
    v1 = {k: p[k] for k in ("scenario", "step", "time_s", "ego", "route", "reply")} | {"version": 1}
    r1 = bp.parse_message(v1)
    assert r1.version == 1 and r1.command is None and r1.cameras == ()


@pytest.mark.parametrize("edit,needle", [
    (lambda m: m.pop("ego_in_lidar"), "plan.ego_in_lidar: missing"),
    (lambda m: m["ego"].pop("vx"), "plan.ego.vx: missing"),
    (lambda m: m["cameras"][2].__setitem__("lidar2img", [[1, 0, 0]] * 3), "plan.cameras[2].lidar2img: expected a 4x4"),
    (lambda m: m.__setitem__("command", "up"), "command 'up'"),
    (lambda m: m["history"][1].__setitem__("from", "guess"), "plan.history[1].from"),
    (lambda m: m["ego"].__setitem__("heading", None), "plan.ego.heading: expected a finite number"),
    (lambda m: m.__setitem__("inline_bytes", 12), "plan.inline_bytes: 12, but 0 bytes"),
    (lambda m: m.__setitem__("type", "bye"), "message type 'bye'"),
])
def test_parser_errors_name_the_field(edit, needle):
    m, inline = plan_message()
    edit(m)
    with pytest.raises(bp.ProtocolError) as e:
        bp.parse_message(m, inline, bp.parse_message(start_message()))
    assert needle in str(e.value)


def test_lidar_helpers_agree_with_the_ego_projection():
    # the ego point seen through cam2ego + intrinsic and through ego_in_lidar + lidar2img: one pixel
    _, r = parsed()
    n = 0
    for c in r.cameras:
        for p in ([10.0, 0.0, 0.5], [-8.0, 2.0, 1.0], [3.0, -6.0, 0.2], [2.0, 7.0, 1.5]):
            a, b = c.project(p), c.project_lidar(r.ego_to_lidar(p))
            assert (a is None) == (b is None), (c.name, p)
            if a is not None:
                assert math.dist(a, b) < 1e-6, (c.name, p, a, b)
                n += 1
    assert n >= 6


def test_trajectory_and_reply():
    t = bp.Trajectory([[0.0, 1.0], [0.0, 2.0], [0.5, 3.0], [1.0, 4.0], [1.5, 5.0], [2.0, 6.0]], 0.5, "lidar")
    assert t.xy_only and t.horizon_s == 3.0
    assert t.to_reply(7) == {"poses": [list(p) for p in t.poses], "dt_s": 0.5, "frame": "lidar", "step": 7}
    assert bp.reply([[1, 0, 0]] * 4) == {"poses": [[1.0, 0.0, 0.0]] * 4}
    assert bp.reply([[1, 0, 0.1], [2, 0, 0.2]], dt_s=1, xy_only=True) == {"poses": [[1.0, 0.0], [2.0, 0.0]],
                                                                          "dt_s": 1.0}


@pytest.mark.parametrize("kwargs,needle", [
    ({"poses": [[1, 0]] * 6, "frame": "camera"}, "frame 'camera'"),
    ({"poses": [[1, 0]] * 6, "dt_s": 0}, "dt_s 0"),
    ({"poses": [[1, 0]] * 6, "dt_s": 2.5}, "dt_s 2.5"),
    ({"poses": [[1, 0]] * 6, "dt_s": float("nan")}, "dt_s nan"),
    ({"poses": [[1, 0], [2, 0, 0]] * 3}, "poses[0] has 2 values but poses[1] has 3"),
    ({"poses": [[1, 0]] * 3}, "at least 2 s"),
    ({"poses": [[1, float("inf")]] * 6}, "poses[0]"),
    ({"poses": [[1, 0, 0, 0]] * 6}, "poses[0] has 4 values"),
    ({"poses": [[2e4, 0]] * 6}, "beyond 10000 m"),
    ({"poses": []}, "0 poses"),
])
def test_reply_refuses_what_b2dr_refuses(kwargs, needle):
    with pytest.raises(ValueError) as e:
        bp.reply(**kwargs)
    assert needle in str(e.value)


# Hand-written from the models' sources (cited in b2dr_planner/command.py): UniAD 0 right / 1 left / 2 forward;
# VAD one-hot [right, left, straight]; NAVSIM one-hot [left, straight (forward), right, unknown].
EXPECTED = {
    "left": {"uniad": 1, "vad": [0, 1, 0], "navsim": [1, 0, 0, 0]},
    "right": {"uniad": 0, "vad": [1, 0, 0], "navsim": [0, 0, 1, 0]},
    "straight": {"uniad": 2, "vad": [0, 0, 1], "navsim": [0, 1, 0, 0]},
}


@pytest.mark.parametrize("command", ["left", "right", "straight"])
@pytest.mark.parametrize("family", ["uniad", "vad", "navsim"])
def test_command_encodings(command, family):
    s = bp.parse_message(start_message())
    m, _ = plan_message(command=command)
    r = bp.parse_message(m, b"", s)
    assert r.command_as(family) == EXPECTED[command][family] == bp.Command(command).encode(family)


def test_left_and_right_are_not_swapped():
    # each encoding's "left" slot names a left turn in that model's own label list
    vad_labels = ["Turn Right", "Turn Left", "Go Straight"]
    navsim_labels = ["left", "forward", "right", "unknown"]
    uniad_labels = {0: "RIGHT", 1: "LEFT", 2: "FORWARD"}
    for cmd in bp.Command:
        vad, navsim, uniad = (bp.encode_command(cmd, f) for f in ("vad", "navsim", "uniad"))
        assert sum(vad) == 1 and sum(navsim) == 1
        want = {"straight": ("Go Straight", "forward", "FORWARD")}.get(
            cmd.value, ("Turn " + cmd.value.capitalize(), cmd.value, cmd.value.upper()))
        assert (vad_labels[vad.index(1)], navsim_labels[navsim.index(1)], uniad_labels[uniad]) == want
    # a Command is its wire string, also as a dict key
    assert {"left": 1}.get(bp.Command.LEFT) == 1 and json.dumps(bp.Command.RIGHT) == '"right"'


def test_command_errors_and_navsim_unknown():
    assert bp.encode_command(None, "navsim") == [0, 0, 0, 1]
    with pytest.raises(ValueError, match="no encoding for a missing command"):
        bp.encode_command(None, "vad")
    with pytest.raises(ValueError, match="unknown model family"):
        bp.encode_command("left", "transfuser")
    with pytest.raises(ValueError, match="command 'up'"):
        bp.encode_command("up", "uniad")
    v = bp.encode_command("left", "vad")
    v[0] = 9
    assert bp.encode_command("left", "vad") == [0, 1, 0]


class Straight(bp.Agent):
    """6 lidar-frame xy points at 0.5 s straight ahead; counts its loads; step 10 returns 5 poses (a bug)."""
    images, size, poses, dt_s, frame = "none", (56, 100), 6, 0.5, "lidar"
    loads = 0

    def initialize(self):
        type(self).loads += 1
        if getattr(self, "fail", False):
            raise RuntimeError("no weights here")

    def start(self, session):
        self.scenario = session.scenario

    def step(self, req):
        n = 5 if req.step == 10 else 6
        return bp.Trajectory([[0.0, 4.0 * k] for k in range(1, n + 1)], 0.5, "lidar")


def serve_lines(agent, msgs):
    out = io.StringIO()
    bp.serve_agent(agent, io.BytesIO(b"".join(msgs)), out)
    return [json.loads(x) for x in out.getvalue().splitlines()]


def test_agent_service_resident_sessions():
    Straight.loads = 0
    hello = wire({"type": "hello", "version": 2, "resident": True, "timeout_s": 10.0, "start_timeout_s": 300.0})
    msgs = [hello]
    for name in ("a", "b"):
        msgs += [wire(start_message(name)), wire(*plan_message(5, scenario=name)), wire(*plan_message(10, scenario=name)),
                 wire({"type": "end", "version": 2, "scenario": name})]
    a = Straight()
    replies = serve_lines(a, msgs)
    assert Straight.loads == 1  # one load for the batch
    assert replies[0] == {"ready": True}
    assert replies[1] == {"images": "none", "size": [56, 100]}
    assert replies[2]["step"] == 5 and replies[2]["frame"] == "lidar" and len(replies[2]["poses"]) == 6
    # the base class refuses the 5-pose trajectory: an error reply for that step, and the next session runs
    assert "returned 5 poses, it declares 6" in replies[3]["error"] and replies[3]["step"] == 10
    assert replies[4] == replies[1] and replies[5] == replies[2] and len(replies) == 7
    assert len(a.timings["initialize"]) == 1 and len(a.timings["start"]) == 2 and len(a.timings["end"]) == 2
    # every step is timed, the refused one too
    assert len(a.timings["step"]) == 4 and all(t >= 0 for t in a.timings["step"])


def test_agent_service_cmd_mode_and_failures():
    Straight.loads = 0
    r = serve_lines(Straight(), [wire(start_message()), wire(*plan_message(5)), wire({"type": "end", "version": 2,
                                                                                       "scenario": "x"})])
    assert Straight.loads == 1 and r[0]["images"] == "none" and r[1]["step"] == 5
    broken = Straight()
    broken.fail = True
    hello = wire({"type": "hello", "version": 2, "resident": True, "timeout_s": 1.0, "start_timeout_s": 9.0})
    assert serve_lines(broken, [hello]) == [{"error": "load failed: RuntimeError: no weights here"}]
    # as cmd: the load runs at start, and its failure refuses the scenario
    assert serve_lines(broken, [wire(start_message())]) == [{"error": "load failed: RuntimeError: no weights here"}]
    # a request the parser refuses is an error reply naming the field
    m, _ = plan_message(5)
    del m["cameras"]
    r = serve_lines(Straight(), [wire(start_message()), wire(m)])
    assert "plan.cameras: missing" in r[1]["error"]


def test_function_serve_passes_replies_through():
    # serve(plan): lists and dicts are sent as returned (b2dr's protocol tests rely on it), Trajectories checked
    agent = bp.FunctionAgent(lambda req: {"poses": [[1.0, 0.0]], "dt_s": 0}, images="inline")
    r = serve_lines(agent, [wire(start_message()), wire(*plan_message(5))])
    assert r == [{"images": "inline"}, {"poses": [[1.0, 0.0]], "dt_s": 0, "step": 5}]


def test_core_imports_without_numpy():
    code = ("import sys; sys.modules['numpy'] = None; sys.path.insert(0, sys.argv[1]); import b2dr_planner as b; "
            "print(b.reply([[1, 0, 0]] * 4)['poses'][0])")
    r = subprocess.run([sys.executable, "-c", code, str(REPO / "python")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[1.0, 0.0, 0.0]"
