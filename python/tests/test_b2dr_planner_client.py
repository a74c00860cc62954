"""examples/b2dr_planner.py's reply helper (issue #34): declared pose spacing, lidar frame, xy-only poses, and
the replies b2dr would refuse raised as ValueError before they are sent; the lidar-frame helpers."""
import importlib.util
import math
from pathlib import Path

import pytest

CLIENT = Path(__file__).resolve().parents[2] / "examples" / "b2dr_planner.py"


def client():
    spec = importlib.util.spec_from_file_location("b2dr_planner", CLIENT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_reply_fields():
    c = client()
    assert c.reply([[1, 0, 0]] * 4) == {"poses": [[1.0, 0.0, 0.0]] * 4}
    r = c.reply([[0.0, 1.0], [0.0, 2.0], [0.5, 3.0], [1.0, 4.0], [1.5, 5.0], [2.0, 6.0]], dt_s=0.5, frame="lidar")
    assert r == {"poses": [[0.0, 1.0], [0.0, 2.0], [0.5, 3.0], [1.0, 4.0], [1.5, 5.0], [2.0, 6.0]],
                 "dt_s": 0.5, "frame": "lidar"}
    assert c.reply([[1, 0, 0.1], [2, 0, 0.2]], dt_s=1, xy_only=True) == {"poses": [[1.0, 0.0], [2.0, 0.0]],
                                                                         "dt_s": 1.0}


@pytest.mark.parametrize("kwargs,needle", [
    ({"poses": [[1, 0]] * 6, "frame": "camera"}, "frame 'camera'"),
    ({"poses": [[1, 0]] * 6, "dt_s": 0}, "dt_s 0"),
    ({"poses": [[1, 0]] * 6, "dt_s": 2.5}, "dt_s 2.5"),
    ({"poses": [[1, 0]] * 6, "dt_s": float("nan")}, "dt_s nan"),
    ({"poses": [[1, 0], [2, 0, 0]] * 3}, "mix of [x, y] and [x, y, heading]"),
    ({"poses": [[1, 0]] * 3}, "at least 2 s"),
    ({"poses": [[1, float("inf")]] * 6}, "poses[0]"),
    ({"poses": [[1, 0, 0, 0]] * 6}, "poses[0]"),
])
def test_reply_refuses_what_b2dr_refuses(kwargs, needle):
    c = client()
    with pytest.raises(ValueError) as e:
        c.reply(**kwargs)
    assert needle in str(e.value)


def test_lidar_helpers():
    c = client()
    # lidar 1 m ahead, 1.8 m up, turned -90 degrees: ego (x, y, z) is lidar (-y, x - 1, z - 1.8)
    ego_in_lidar = [[0, -1, 0, 0], [1, 0, 0, -1], [0, 0, 1, -1.8], [0, 0, 0, 1]]
    req = c.Request({"scenario": "s", "step": 0, "time_s": 0.0, "ego": {}, "ego_in_lidar": ego_in_lidar}, b"",
                    {"lidar2ego": [[0, 1, 0, 1], [-1, 0, 0, 0], [0, 0, 1, 1.8], [0, 0, 0, 1]]})
    assert c.ego_to_lidar(req, [10.0, 2.0, 0.0]) == [-2.0, 9.0, -1.8]
    assert req.lidar2ego[0][3] == 1
    cam = c.Camera({"camera": "C", "width": 10, "height": 10, "intrinsic": [[1, 0, 5], [0, 1, 5], [0, 0, 1]],
                    "cam2ego": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                    "ego2global": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                    "lidar2img": [[2, 0, 5, 0], [0, 2, 5, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "fnv1a64": "0"}, b"")
    assert cam.project_lidar([1.0, -1.0, 2.0]) == (6.0, 4.0)
    assert cam.project_lidar([1.0, -1.0, -2.0]) is None
    assert math.isclose(c.transform(ego_in_lidar, [0, 0, 0])[2], -1.8)


# Hand-written from the models' sources (cited in examples/b2dr_planner.py): UniAD 0 right / 1 left / 2 forward;
# VAD one-hot [right, left, straight]; NAVSIM one-hot [left, straight (forward), right, unknown].
EXPECTED = {
    "left": {"uniad": 1, "vad": [0, 1, 0], "navsim": [1, 0, 0, 0]},
    "right": {"uniad": 0, "vad": [1, 0, 0], "navsim": [0, 0, 1, 0]},
    "straight": {"uniad": 2, "vad": [0, 0, 1], "navsim": [0, 1, 0, 0]},
}


@pytest.mark.parametrize("command", ["left", "right", "straight"])
@pytest.mark.parametrize("model", ["uniad", "vad", "navsim"])
def test_command_encodings(command, model):
    c = client()
    req = c.Request({"scenario": "s", "step": 0, "time_s": 0.0, "ego": {}, "command": command,
                     "command_def": "nuscenes"}, b"")
    assert req.command_def == "nuscenes"
    assert req.command_as(model) == EXPECTED[command][model]


def test_left_and_right_are_not_swapped():
    # each encoding's "left" slot names a left turn in that model's own label list
    c = client()
    vad_labels = ["Turn Right", "Turn Left", "Go Straight"]
    navsim_labels = ["left", "forward", "right", "unknown"]
    uniad_labels = {0: "RIGHT", 1: "LEFT", 2: "FORWARD"}
    for cmd, word in [("left", "left"), ("right", "right"), ("straight", "straight")]:
        vad = c.encode_command(cmd, "vad")
        navsim = c.encode_command(cmd, "navsim")
        uniad = c.encode_command(cmd, "uniad")
        assert sum(vad) == 1 and sum(navsim) == 1
        want = {"straight": ("Go Straight", "forward", "FORWARD")}.get(
            word, ("Turn " + word.capitalize(), word, word.upper()))
        assert vad_labels[vad.index(1)] == want[0]
        assert navsim_labels[navsim.index(1)] == want[1]
        assert uniad_labels[uniad] == want[2]


def test_command_errors_and_navsim_unknown():
    c = client()
    assert c.encode_command(None, "navsim") == [0, 0, 0, 1]
    with pytest.raises(ValueError, match="expected one of"):
        c.encode_command(None, "vad")
    with pytest.raises(ValueError, match="unknown model"):
        c.encode_command("left", "transfuser")
    with pytest.raises(ValueError, match="command 'up'"):
        c.encode_command("up", "uniad")
    # the encodings are copies: a caller editing one does not change the next
    v = c.encode_command("left", "vad")
    v[0] = 9
    assert c.encode_command("left", "vad") == [0, 1, 0]


def test_history_is_typed():
    c = client()
    h = [{"time_s": -0.5, "x": -5.0, "y": 0.0, "heading": 0.0, "vx": 10.0, "vy": 0.0, "ax": 0.0, "ay": 0.0,
          "from": "sim"},
         {"time_s": -1.0, "x": -10.0, "y": 0.0, "heading": 0.0, "vx": 10.0, "vy": 0.0, "ax": 0.0, "ay": 0.0,
          "from": "pad"}]
    req = c.Request({"scenario": "s", "step": 5, "time_s": 0.5, "ego": {}, "history": h}, b"")
    assert [(p.time_s, p.x, p.source) for p in req.history] == [(-0.5, -5.0, "sim"), (-1.0, -10.0, "pad")]
    assert c.Request({"scenario": "s", "step": 0, "time_s": 0.0, "ego": {}}, b"").history == []
