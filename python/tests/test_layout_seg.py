"""The layout segmenter (b2dr_ref/layout_seg.py) and the colour classifier's port (tools/layout_ceiling.py)."""

import math

import numpy as np
import pytest
import torch
from PIL import Image

from b2dr_ref import layout_seg as L


def test_class_ids_maps_the_display_colours_and_refuses_others():
    img = np.stack([np.array([L.CLASS_COLOURS[11], L.CLASS_COLOURS[5]], np.uint8)])   # (1, 2, 3)
    assert L.class_ids(img).tolist() == [[11, 5]]
    bad = img.copy()
    bad[0, 0] = (1, 2, 3)
    with pytest.raises(ValueError, match="no class"):
        L.class_ids(bad)


def test_gaussian_blur_keeps_constants_and_spreads_a_point_as_its_kernel():
    x = torch.full((2, 3, 9, 11), 77.0)
    y = L.gaussian_blur(x, torch.tensor([0.0, 1.3]))
    assert torch.allclose(y, x, atol=1e-4)
    p = torch.zeros(1, 1, 15, 15)
    p[0, 0, 7, 7] = 1.0
    q = L.gaussian_blur(p, torch.tensor([1.0]))[0, 0]
    # separable Gaussian, sigma 1, radius 5 (normalised): centre weight = (1 / sum_k exp(-k^2 / 2))^2
    s = sum(math.exp(-k * k / 2) for k in range(-5, 6))
    assert q[7, 7].item() == pytest.approx(1 / s ** 2, rel=1e-5)
    assert q[7, 8].item() == pytest.approx(math.exp(-0.5) / s ** 2, rel=1e-5)
    assert q.sum().item() == pytest.approx(1.0, rel=1e-5)


def test_iou_is_summed_over_images():
    t = [np.array([[4, 4, 11, 11]]), np.array([[11, 11, 11, 11]])]
    p = [np.array([[4, 4, 4, 11]]), np.array([[11, 11, 11, 4]])]
    r = L.iou(p, t)
    # vehicle (11): intersections 1 + 3, unions 2 + 4; road (4): intersections 2 + 0, unions 3 + 1
    assert r[11] == pytest.approx(4 / 6)
    assert r[4] == pytest.approx(2 / 4)


def test_the_colour_classifier_port_matches_the_rust_test_case(tool):
    # src/eval/fidelity/metrics.rs classifier_and_iou: red (class 4) left, blue (class 11) right
    h, w = 4, 8
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:, : w // 2] = (200, 20, 20)
    rgb[:, w // 2:] = (20, 20, 200)
    cls = np.zeros((h, w), np.uint8)
    cls[:, : w // 2] = 4
    cls[:, w // 2:] = 11
    k = tool("layout_ceiling").PaletteClassifier([(rgb, cls)])
    assert (k.classify(rgb) == cls).all()
    assert k.classify(np.array([[[30, 40, 180], [180, 50, 40]]], np.uint8)).tolist() == [[11, 4]]


def test_a_segmenter_learns_a_toy_world_and_round_trips_through_its_file(tmp_path):
    # two "frames": a vehicle-coloured square on road, and the reverse; the class images in display colours
    frames = tmp_path / "frames" / "a"
    frames.mkdir(parents=True)
    for n, (fg, bg) in enumerate([(11, 4), (4, 11)]):
        cls = np.full((24, 32), bg, np.uint8)
        cls[6:18, 8:20] = fg
        rgb = np.where(cls[..., None] == 11, np.array([30, 40, 160], np.uint8), np.array([90, 90, 90], np.uint8))
        Image.fromarray(rgb.astype(np.uint8)).save(frames / f"CAM{n}.png")
        Image.fromarray(L.CLASS_COLOURS[cls]).save(frames / f"CAM{n}_class.png")
    rgb, cls = L.load_frames(str(tmp_path / "frames"))
    assert rgb.shape == (2, 24, 32, 3) and sorted(np.unique(cls).tolist()) == [4, 11]
    out = tmp_path / "run"
    L.main(["train", "--frames", str(tmp_path / "frames"), "--out", str(out), "--steps", "300", "--batch", "4",
            "--crop", "16x16", "--width", "8", "--mid", "8", "--lr", "1e-2"])
    net = L.load(str(out / "seg.safetensors"))
    r = L.iou([L.classify(net, x) for x in rgb], list(cls))
    assert r[11] > 0.8 and r[4] > 0.8, r
