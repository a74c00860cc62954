"""The image-reading planner (b2dr_ref.e2e_planner): it learns a pose that only the image tells, its export
round-trips, and it serves protocol v2 (start -> size, plan -> 8 finite poses echoing the step)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from safetensors.numpy import save_file

from b2dr_ref import e2e_planner as P
from planner_fixture import plan_message, start_message, wire

H, W = 32, 48


def make_data(folder, n=96, seed=0):
    """A toy export-planner folder: a bright bar on the left or right of the image says where to steer; speed
    and command carry nothing about it, so only a planner that reads the image can fit the target."""
    r = np.random.default_rng(seed)
    side = r.integers(0, 2, n)
    img = np.full((n, 1, H, W, 3), 60, np.uint8)
    for i, s in enumerate(side):
        x0 = 4 if s == 0 else W - 12
        img[i, 0, :, x0:x0 + 8] = 230
    y = np.where(side == 0, 2.0, -2.0).astype(np.float32)
    k = np.arange(1, 9, dtype=np.float32)
    target = np.stack([np.broadcast_to(4 * k, (n, 8)), y[:, None] * k / 8, np.zeros((n, 8), np.float32)], -1)
    os.makedirs(folder, exist_ok=True)
    save_file({"image": img, "speed": np.full(n, 8, np.float32), "accel": np.zeros(n, np.float32),
               "command": np.ones(n, np.uint8), "target": target.astype(np.float32),
               "step": np.arange(n, dtype=np.int32), "offset": np.zeros((n, 2), np.float32)},
              os.path.join(folder, "0000_toy.safetensors"))
    with open(os.path.join(folder, "index.json"), "w") as f:
        json.dump({"format": "b2dr-planner-data", "version": 1, "size": [H, W],
                   "files": [{"file": "0000_toy.safetensors", "samples": n}]}, f)
    return img[:, 0], target


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("planner")
    img, target = make_data(str(root / "data"))
    run, model_dir = str(root / "run"), str(root / "model")
    P.main(["train", "--data", str(root / "data"), "--val", str(root / "data"), "--out", run, "--epochs", "25",
            "--batch", "16", "--width", "8", "--threads", "1", "--lr", "3e-3"])
    P.main(["export", "--run", run, "--out", model_dir, "--dtype", "f32"])
    return run, model_dir, img, target


def test_planner_learns_what_only_the_image_says(trained):
    run, model_dir, img, target = trained
    m = P.load_planner(model_dir)
    ego = {"vx": 8.0, "ax": 0.0}
    errs = [abs(P.plan_request(m, img[i], ego, "straight")[7][1] - target[i, 7, 1]) for i in range(16)]
    # the two classes sit 4 m apart at the last pose; a planner blind to the image would err by ~2 m
    assert np.mean(errs) < 0.5, errs
    rows = open(os.path.join(run, "log.csv")).read().splitlines()
    assert len(rows) == 26


def test_resume_continues_from_the_checkpoint(tmp_path):
    make_data(str(tmp_path / "d"), n=32)
    args = ["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "r"), "--batch", "16", "--width", "8",
            "--threads", "1"]
    P.main(args + ["--epochs", "2"])
    P.main(args + ["--epochs", "3", "--resume"])
    rows = open(tmp_path / "r" / "log.csv").read().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["1", "2", "3"]


def test_bad_inputs_are_clear_errors(trained, tmp_path):
    _, model_dir, img, _ = trained
    m = P.load_planner(model_dir)
    with pytest.raises(ValueError, match="trained on"):
        P.plan_request(m, np.zeros((10, 10, 3), np.uint8), {"vx": 1.0}, "straight")
    (tmp_path / "index.json").write_text(json.dumps({"format": "b2dr-training"}))
    with pytest.raises(ValueError, match="b2dr-planner-data"):
        P.load_data(str(tmp_path))


def test_serves_protocol_v2(trained):
    _, model_dir, img, _ = trained
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    p = subprocess.Popen([sys.executable, "-m", "b2dr_ref.e2e_planner", "serve", "--weights", model_dir],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
    p.stdin.write(wire(start_message("toy")))
    p.stdin.flush()
    reply = json.loads(p.stdout.readline())
    assert reply == {"images": "inline", "size": [H, W]}
    msg, px = plan_message(5, images={"CAM_FRONT": img[0]}, command="straight", ego={"vx": 8.0, "ax": 0.0})
    p.stdin.write(wire(msg, px))
    p.stdin.flush()
    r = json.loads(p.stdout.readline())
    p.stdin.close()
    p.wait(timeout=30)
    assert r["step"] == 5 and len(r["poses"]) == 8
    assert all(np.isfinite(v) for pose in r["poses"] for v in pose)
    assert r["poses"][7][0] > 10  # it drives forward
