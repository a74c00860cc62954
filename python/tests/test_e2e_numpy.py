"""The torch-free numpy forward of the image planner (b2dr_ref.e2e_numpy) against the torch model
(b2dr_ref.e2e_planner) on the committed weights (models/e2e-planner): the same poses, the same protocol-v2
replies, a server that runs with torch unimportable, clear errors for a wrong weights folder."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file, save_file

from b2dr_ref import e2e_common as C
from b2dr_ref import e2e_numpy as N
from b2dr_ref import e2e_planner as P
from planner_fixture import plan_message, start_message, wire

PY = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WEIGHTS = os.path.join(os.path.dirname(PY), "models", "e2e-planner")
ENV = dict(os.environ, PYTHONPATH=PY, OMP_NUM_THREADS="1")
# numpy computes in f64 and equals torch run in f64 to ~1e-13; torch's own f32 rounding, a few ulps of the
# pose, is what separates the two servers: under 1e-5 m for poses within ~20 m, 1.9e-5 at x = 50 m (measured)
ATOL, RTOL = 1e-5, 1e-6

# runs a module with every `import torch` failing (and checks that it does fail)
NO_TORCH = """
import runpy, sys
class NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked in this test")
sys.meta_path.insert(0, NoTorch())
sys.modules.pop("torch", None)
try:
    import torch
    raise SystemExit("the torch blocker does not block")
except ImportError:
    pass
sys.argv = sys.argv[1:]
runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""


@pytest.fixture(scope="module")
def planners():
    return P.load_planner(WEIGHTS), N.load_planner(WEIGHTS)


def scene(r, h=112, w=200):
    """A road-like frame: sky, road, lane markings, one vehicle-sized box, sensor noise."""
    img = np.empty((h, w, 3))
    hz = int(r.integers(40, 60))
    img[:hz] = r.uniform(120, 220, 3)
    img[hz:] = r.uniform(60, 110)
    for x0 in r.integers(0, w - 20, 3):
        img[hz + 10:, x0:x0 + 4] = 230
    bx, by = int(r.integers(60, 140)), int(r.integers(hz, hz + 20))
    img[by:by + 15, bx:bx + 25] = r.uniform(0, 255, 3)
    return np.clip(img + r.normal(0, 5, img.shape), 0, 255).astype(np.uint8)


def cases(n=12, seed=0):
    """Road-like and uniform-noise frames, speeds 0-14 m/s, accelerations, each command."""
    r = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = scene(r) if i % 2 == 0 else r.integers(0, 256, (112, 200, 3), dtype=np.uint8)
        ego = {"vx": [0.0, 3.0, 8.0, 14.0][i % 4], "ax": float(r.uniform(-4, 2))}
        out.append((img, ego, C.COMMANDS[i % 3]))
    return out


def test_numpy_forward_equals_torch(planners):
    tm, nm = planners
    diffs = []
    for img, ego, cmd in cases():
        a = np.array(P.plan_request(tm, img, ego, cmd))
        b = np.array(N.plan_request(nm, img, ego, cmd))
        np.testing.assert_allclose(b, a, rtol=RTOL, atol=ATOL)
        diffs.append(np.abs(a - b).max())
    print(f"max abs difference numpy - torch (f32): {max(diffs):.3g}")
    # the arithmetic itself: torch in f64 on the same (f16 -> f32) weights, batched
    imgs, states = zip(*(C.request_inputs(nm.image_size, *c) for c in cases(seed=1)))
    img, st = np.concatenate(imgs), np.concatenate(states)
    with torch.no_grad():
        ref = P.load_planner(WEIGHTS).double()(torch.from_numpy(img).double(), torch.from_numpy(st).double())
    np.testing.assert_allclose(nm.forward(img, st), ref.numpy(), rtol=0, atol=1e-9)
    # the f32 path is as close to torch's f32 as torch's own rounding allows
    np.testing.assert_allclose(N.load_planner(WEIGHTS, np.float32).forward(img, st), ref.numpy(), atol=1e-4)


def test_the_comparison_can_fail(planners, tmp_path):
    """One first-layer weight moved by 0.01 moves the poses far beyond the tolerance."""
    tm, _ = planners
    shutil.copy(os.path.join(WEIGHTS, C.CONFIG), tmp_path / C.CONFIG)
    sd = load_file(os.path.join(WEIGHTS, C.WEIGHTS))
    sd["convs.0.weight"][5, 1, 2, 2] += np.float16(0.01)
    save_file(sd, str(tmp_path / C.WEIGHTS))
    bad = N.load_planner(str(tmp_path))
    worst = max(np.abs(np.array(P.plan_request(tm, *c)) - np.array(N.plan_request(bad, *c))).max()
                for c in cases(4))
    assert worst > 100 * ATOL, worst


def request(step, img, ego, cmd, camera="CAM_FRONT"):
    """A plan message as b2dr sends it (the recorded fixture) with `img` as `camera`, inline."""
    return wire(*plan_message(step, images={camera: img}, command=cmd, ego=ego, scenario="t"))


def session(argv):
    """start, six plans (the last two: a wrong image size, a missing camera), end -> the reply lines."""
    msgs = [wire(start_message("t"))]
    msgs += [request(5 * i, *c) for i, c in enumerate(cases(4, seed=2))]
    msgs.append(request(20, np.zeros((10, 10, 3), np.uint8), {"vx": 1.0}, "straight"))
    msgs.append(request(25, cases(1)[0][0], {"vx": 1.0}, "straight", camera="CAM_BACK"))
    msgs.append((json.dumps({"type": "end", "version": 2, "scenario": "t"}) + "\n").encode())
    r = subprocess.run([sys.executable] + argv, input=b"".join(msgs), capture_output=True, env=ENV, cwd=PY,
                       timeout=120)
    assert r.returncode == 0, r.stderr.decode()
    return [json.loads(line) for line in r.stdout.decode().splitlines() if line.strip()]


def test_servers_reply_alike_and_numpy_serves_without_torch():
    serve = ["serve", "--weights", WEIGHTS]
    t = session(["-m", "b2dr_ref.e2e_planner"] + serve)
    n = session(["-c", NO_TORCH, "b2dr_ref.e2e_numpy"] + serve)
    assert len(t) == len(n) == 7
    assert t[0] == n[0] == {"images": "inline", "size": [112, 200]}
    for a, b in zip(t[1:5], n[1:5]):
        assert a.keys() == b.keys() == {"poses", "step"} and a["step"] == b["step"]
        np.testing.assert_allclose(np.array(b["poses"]), np.array(a["poses"]), rtol=RTOL, atol=ATOL)
    assert t[5:] == n[5:]
    assert "trained on" in n[5]["error"] and "no camera CAM_FRONT" in n[6]["error"]


def test_numpy_module_imports_only_numpy_and_safetensors():
    code = NO_TORCH.replace('runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)', """
before = set(sys.modules)  # the interpreter's start-up (site, .pth hooks)
import b2dr_ref.e2e_numpy as N
N.load_planner(sys.argv[1])
top = {m.split(".")[0] for m in set(sys.modules) - before}
bad = sorted(top - set(sys.stdlib_module_names) - {"numpy", "safetensors", "b2dr_ref", "__main__"})
assert not bad, bad
assert "b2dr_ref.e2e_planner" not in sys.modules
print("ok")
""")
    r = subprocess.run([sys.executable, "-c", code, "x", WEIGHTS], capture_output=True, env=ENV, cwd=PY,
                       timeout=60)
    assert r.returncode == 0 and r.stdout.decode().strip() == "ok", r.stderr.decode()


def test_a_wrong_weights_folder_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="no config.json"):
        N.load_planner(str(tmp_path))
    (tmp_path / C.CONFIG).write_text(json.dumps({"format": "b2dr-training"}))
    with pytest.raises(ValueError, match="not a b2dr-e2e-planner"):
        N.load_planner(str(tmp_path))
    cfg = json.loads(open(os.path.join(WEIGHTS, C.CONFIG)).read())
    (tmp_path / C.CONFIG).write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="no planner.safetensors"):
        N.load_planner(str(tmp_path))
    shutil.copy(os.path.join(WEIGHTS, C.WEIGHTS), tmp_path / C.WEIGHTS)
    (tmp_path / C.CONFIG).write_text(json.dumps(dict(cfg, width=16)))
    with pytest.raises(ValueError, match=r"convs.0.weight has shape \(32, 3, 5, 5\), expected \(16, 3, 5, 5\)"):
        N.load_planner(str(tmp_path))
    (tmp_path / C.CONFIG).write_text(json.dumps(dict(cfg, image_size=[64, 64])))
    with pytest.raises(ValueError, match="head.0.weight has shape"):
        N.load_planner(str(tmp_path))
    save_file({"w": np.zeros(3, np.float32)}, str(tmp_path / C.WEIGHTS))
    with pytest.raises(ValueError, match="not E2EPlanner"):
        N.load_planner(str(tmp_path))
    # the server says so too, before reading any request
    r = subprocess.run([sys.executable, "-c", NO_TORCH, "b2dr_ref.e2e_numpy", "serve", "--weights",
                        str(tmp_path)], input=b"", capture_output=True, env=ENV, cwd=PY, timeout=60)
    assert r.returncode != 0 and b"not E2EPlanner" in r.stderr


def test_other_sizes_and_widths(tmp_path):
    """Not only the committed model: an untrained E2EPlanner of another image size (odd halves) and width."""
    from safetensors.torch import save_file as save_torch

    torch.manual_seed(0)
    m = P.E2EPlanner((46, 70), width=8).eval()
    save_torch({k: v.contiguous() for k, v in m.state_dict().items()}, str(tmp_path / C.WEIGHTS))
    (tmp_path / C.CONFIG).write_text(json.dumps({"format": C.FORMAT, "version": 1, "image_size": [46, 70],
                                                 "width": 8}))
    nm = N.load_planner(str(tmp_path))
    r = np.random.default_rng(3)
    for i in range(3):
        img = r.integers(0, 256, (46, 70, 3), dtype=np.uint8)
        ego = {"vx": 5.0 * i, "ax": 1.0}
        np.testing.assert_allclose(N.plan_request(nm, img, ego, C.COMMANDS[i]),
                                   P.plan_request(m, img, ego, C.COMMANDS[i]), rtol=RTOL, atol=ATOL)
