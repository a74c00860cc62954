"""`b2dr export-training` on a nuPlan log (issue #33 item 5): the fixture writer's DB, map and sensor_blobs
(b2dr_ref.nuplan_fixture: the devkit's layout, eight cameras with pickled calibration and lens distortion, PNG
images whose red channel names the camera and whose green ramp moves with the step).

- the eight cameras, each with the fixture's cam2ego (its pickled rotation and translation) and intrinsics (its K
  rescaled to the render size with pixel centres at integer coordinates: Camera::intrinsic_scaled);
- each camera's ego2global is the fixture's ego pose at the target's step; references and the previous frame at
  theirs;
- the targets, previous frames and references are the fixture's recorded images of that camera and step,
  undistorted (OpenCV's model, here in numpy: ``undistort``) and resized to the render size (Pillow's bilinear
  filter here, the image crate's triangle filter in b2dr: within MAX_MEAN_ABS / MAX_ABS); the same images resized
  WITHOUT undistortion, or those of the next step, are further apart than that;
- two sd15 steps (a tiny SD1.5-shaped folder, in this process) train on the export.

Skipped (printed) without a b2dr binary (cargo build, or B2DR_BIN).
"""
import functools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from b2dr_ref import nuplan_fixture as nf  # noqa: E402
from b2dr_ref.dataset import TrainingSet  # noqa: E402

SIZE = (32, 56)
# b2dr's image against undistort + Pillow's bilinear resize here (levels): measured mean |difference| at most 0.09
# per image, largest 1 (rounding); the fixture's images resized without undistortion are 3.2 or more apart (mean),
# the next step's image undistorted 7.6 or more
MAX_MEAN_ABS = 0.5
MAX_ABS = 2


def b2dr_binary():
    from scale_helpers import b2dr_binary as find

    return find()                       # skips (printed reason) without a binary


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    exe = b2dr_binary()
    root = tmp_path_factory.mktemp("nuplan")
    summary = nf.write_fixture(root, seconds=4.0, png=True)
    out = str(tmp_path_factory.mktemp("export"))
    r = subprocess.run([exe, "export-training", "--scenario", f"nuplan:{summary['db']}", "--out", out,
                        "--size", f"{SIZE[0]}x{SIZE[1]}", "--samples-per-scenario", "4", "--seed", "3", "--quiet"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return summary, out


def quat_matrix(q):
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def fixture_ego2global(step: int) -> np.ndarray:
    """The fixture's ego pose at log step ``step`` (10 Hz; the DB's poses are those of ego_at)."""
    x, y, yaw, _ = nf.ego_at(step * 0.1)
    m = np.eye(4)
    m[:3, :3] = quat_matrix(nf.quat_z(yaw))
    m[:2, 3] = (x, y)
    return m


@functools.lru_cache(maxsize=None)
def fixture_image(cam: int, step: int) -> np.ndarray:
    """The recorded image of camera ``cam`` (fixture order) at log step ``step``: (H, W, 3) uint8."""
    rgb = (30 * cam % 256, (7 * 2 * step) % 256, 200)
    return np.array([[nf.pixel(rgb, x, y) for x in range(nf.CAM_W)] for y in range(nf.CAM_H)], np.uint8)


def undistort(img: np.ndarray, k: np.ndarray, d) -> np.ndarray:
    """What cv2.undistort(img, K, D) computes (OpenCV's pinhole + (k1, k2, p1, p2, k3) model): each output pixel
    centre through the distortion into the recorded image, sampled bilinearly (edges clamped), black outside."""
    h, w = img.shape[:2]
    k1, k2, p1, p2, k3 = d
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    y = (v - k[1, 2]) / k[1, 1]
    x = (u - k[0, 2] - k[0, 1] * y) / k[0, 0]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    ud, vd = k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]
    inside = (ud > -1) & (vd > -1) & (ud < w) & (vd < h)
    u0, v0 = np.floor(ud), np.floor(vd)
    a, b = (ud - u0)[..., None], (vd - v0)[..., None]
    f = img.astype(np.float64)

    def px(uu, vv):
        return f[np.clip(vv, 0, h - 1).astype(int), np.clip(uu, 0, w - 1).astype(int)]

    out = (1 - b) * ((1 - a) * px(u0, v0) + a * px(u0 + 1, v0)) \
        + b * ((1 - a) * px(u0, v0 + 1) + a * px(u0 + 1, v0 + 1))
    out[~inside] = 0
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def resized(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> (3, SIZE) with Pillow's bilinear filter (a triangle filter widened when shrinking)."""
    from PIL import Image

    return np.asarray(Image.fromarray(img).resize((SIZE[1], SIZE[0]), Image.BILINEAR)).transpose(2, 0, 1)


def mean_abs(a, b) -> float:
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def test_eight_cameras_with_the_fixtures_calibration_and_poses(exported):
    summary, out = exported
    ds = TrainingSet(out)
    assert sorted(ds.cameras) == sorted(nf.CAMERAS) and len(ds.cameras) == 8
    assert (ds.height, ds.width) == SIZE and len(ds) == 4
    cal = {c["channel"]: c for c in summary["cameras"]}
    sx, sy = SIZE[1] / nf.CAM_W, SIZE[0] / nf.CAM_H
    for s in ds:
        for c, name in enumerate(ds.cameras):
            fx = cal[name]
            want = np.eye(4)
            want[:3, :3] = quat_matrix(fx["rotation"])
            want[:3, 3] = fx["translation"]
            np.testing.assert_allclose(s["cam2ego"][c], want, atol=1e-12, err_msg=name)
            k = np.array(fx["intrinsic"])
            k_want = np.array([[k[0, 0] * sx, k[0, 1] * sx, (k[0, 2] + 0.5) * sx - 0.5],
                               [0.0, k[1, 1] * sy, (k[1, 2] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])
            np.testing.assert_allclose(s["intrinsics"][c], k_want, atol=1e-12, err_msg=name)
            np.testing.assert_allclose(s["ego2global"][c], fixture_ego2global(s["step"]), atol=1e-6)
            np.testing.assert_allclose(s["prev_ego2global"][c], fixture_ego2global(s["prev_step"]), atol=1e-6)
            for r in range(2):
                np.testing.assert_allclose(s["ref_ego2global"][c, r], fixture_ego2global(int(s["ref_step"][c, r])),
                                           atol=1e-6)
        assert not s["perturbed"] and s["prev_step"] == s["step"] - 5
        assert s["masks"][ds.cameras.index("CAM_F0"), ds.mask_channels.index("drivable_area")].mean() > 0.1


def test_targets_are_the_recorded_images_undistorted_and_resized(exported):
    summary, out = exported
    ds = TrainingSet(out)
    cal = {c["channel"]: c for c in summary["cameras"]}
    worst, largest, plain_best, other_best = 0.0, 0.0, math.inf, math.inf
    for s in ds:
        for c, name in enumerate(ds.cameras):
            i = nf.CAMERAS.index(name)
            k, d = np.array(cal[name]["intrinsic"]), cal[name]["distortion"]
            assert any(d), "the fixture's lenses are distorted"
            checks = [(s["target"][c], s["step"]), (s["prev"][c], s["prev_step"])]
            checks += [(s["ref"][c, r], int(s["ref_step"][c, r])) for r in range(2)]
            for got, step in checks:
                want = resized(undistort(fixture_image(i, step), k, d))
                worst = max(worst, mean_abs(got, want))
                largest = max(largest, float(np.abs(got.astype(np.float64) - want).max()))
                plain_best = min(plain_best, mean_abs(got, resized(fixture_image(i, step))))
                other_best = min(other_best, mean_abs(got, resized(undistort(fixture_image(i, step + 1), k, d))))
    print(f"nuPlan export vs undistorted + resized fixture images: worst mean |diff| {worst:.2f}, largest "
          f"{largest:.0f}; not undistorted >= {plain_best:.1f}; the next step's >= {other_best:.1f}")
    assert worst <= MAX_MEAN_ABS < min(plain_best, other_best) and largest <= MAX_ABS


def test_a_few_sd15_steps_train_on_the_nuplan_export(exported, tmp_path):
    from accelerate.state import AcceleratorState, GradientState

    from b2dr_ref.training import sd15
    from b2dr_ref.training.tiny_sd15 import write_tiny_sd15

    _, out = exported
    pretrained = write_tiny_sd15(str(tmp_path / "sd15"))
    run = str(tmp_path / "run")
    args = ["--pretrained", pretrained, "--data", out, "--output_dir", run, "--resolution", f"{SIZE[0]}x{SIZE[1]}",
            "--pe_depth_num", "4", "--conditioning_embedding_out_channels", "8,16,16,32", "--train_batch_size", "4",
            "--max_train_steps", "2", "--lr_warmup_steps", "1", "--validation_steps", "0", "--report_to", "none"]
    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    old = os.environ.get("ACCELERATE_USE_CPU")
    os.environ["ACCELERATE_USE_CPU"] = "true"
    try:
        assert sd15.main(sd15.parse_args(args)) == 2
    finally:
        AcceleratorState._reset_state(True)
        GradientState._reset_state()
        if old is None:
            os.environ.pop("ACCELERATE_USE_CPU")
        else:
            os.environ["ACCELERATE_USE_CPU"] = old
    rows = [line.split(",") for line in open(os.path.join(run, "log.csv")).read().split()[1:]]
    assert [int(r[0]) for r in rows] == [1, 2] and all(math.isfinite(float(r[1])) for r in rows)
    with open(os.path.join(run, "run.json")) as f:
        assert json.load(f)["cameras"] == TrainingSet(out).cameras
