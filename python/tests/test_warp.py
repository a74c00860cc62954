"""b2dr_ref.warp: the previous frame's warp grid against closed-form flat-ground geometry (the engine's
tests/render_warp.rs checks src/render/warp.rs the same way), and warp_image against a plain bilinear loop."""

import numpy as np
import pytest
import torch

from b2dr_ref.warp import ground_warp_grid, warp_image

H, W, F, CX, CY, CAM_H = 112, 200, 100.0, 99.5, 55.5, 1.5
K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1.0]])
# x_cam = -y_ego, y_cam = -z_ego, z_cam = x_ego; CAM_H above the ego origin
CAM2EGO = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, CAM_H], [0, 0, 0, 1.0]])


def pose(x, y, z, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1.0]])


def test_same_pose_is_the_identity():
    p = pose(12, -3, 0.4, 0.3)
    g = ground_warp_grid(K, CAM2EGO, p, p, (H, W), 30.0)
    v, u = np.mgrid[0:H, 0:W]
    np.testing.assert_allclose(g[..., 0], u, atol=1e-3)
    np.testing.assert_allclose(g[..., 1], v, atol=1e-3)


def test_forward_motion_matches_flat_ground_geometry():
    dx, d = 5.0, 30.0
    g = ground_warp_grid(K, CAM2EGO, pose(40, 7, 2), pose(40 - dx, 7, 2), (H, W), d)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = u - CX, v - CY
    with np.errstate(divide="ignore"):
        z = np.where(v > 0, np.minimum(CAM_H * F / np.where(v > 0, v, 1), d), d)
    np.testing.assert_allclose(g[..., 0], CX + u * z / (z + dx), atol=1e-3)
    np.testing.assert_allclose(g[..., 1], CY + v * z / (z + dx), atol=1e-3)
    ground = (v > 0) & (CAM_H * F / np.where(v > 0, v, 1) < d)
    assert ground.sum() > 1000 and (~ground).sum() > 1000


def test_sources_outside_or_behind_keep_the_pixel():
    g = ground_warp_grid(K, CAM2EGO, pose(0, 0, 0), pose(20, 0, 0), (H, W), 30.0)
    assert np.isnan(g[H - 1, W // 2]).all()
    ok = np.isfinite(g).all(-1)
    assert ok.any() and (~ok).any()
    assert (g[ok][:, 0] >= -0.5).all() and (g[ok][:, 0] <= W - 0.5).all()
    with pytest.raises(ValueError):
        ground_warp_grid(K, CAM2EGO, pose(0, 0, 0), pose(0, 0, 0), (H, W), 0.0)


def test_warp_image_is_clipped_bilinear_and_nan_keeps_the_pixel():
    rng = np.random.default_rng(0)
    n, c, h, w = 2, 3, 7, 13
    img = torch.from_numpy(rng.random((n, c, h, w))).float()
    grid = np.stack([rng.uniform(-0.5, w - 0.5, (n, h, w)), rng.uniform(-0.5, h - 0.5, (n, h, w))], -1)
    grid[0, 2, 3] = np.nan
    out = warp_image(img, torch.from_numpy(grid).float()).numpy()
    x = img.numpy().astype(np.float64)
    gf = torch.from_numpy(grid).float().double().numpy()   # the grid as the float32 the function sees
    for b in range(n):
        for yy in range(h):
            for xx in range(w):
                sx, sy = gf[b, yy, xx]
                if np.isnan(sx):
                    want = x[b, :, yy, xx]
                else:
                    sx, sy = np.clip(sx, 0, w - 1), np.clip(sy, 0, h - 1)
                    x0, y0 = int(np.floor(sx)), int(np.floor(sy))
                    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
                    ax, ay = sx - x0, sy - y0
                    want = (1 - ay) * ((1 - ax) * x[b, :, y0, x0] + ax * x[b, :, y0, x1]) + \
                        ay * ((1 - ax) * x[b, :, y1, x0] + ax * x[b, :, y1, x1])
                np.testing.assert_allclose(out[b, :, yy, xx], want, atol=1e-5)
    with pytest.raises(ValueError):
        warp_image(img, torch.zeros(n, h, w + 1, 2))
