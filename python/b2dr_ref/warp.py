"""The previous frame warped to the current pose (b2dr.json ``prev_warp_max_depth`` D > 0; the engine's
src/render/warp.rs and kernels/warp.wgsl compute the same).

Every pixel of the current camera is taken to the flat ground (the plane z = the current ego origin's global z:
nuScenes' ego frame sits on the ground) along its ray, or to depth D
(metres along the camera's optical axis) where the ray meets the ground beyond D or not at all (sky, and
buildings: a vertical plane D ahead), and projected into the previous frame's camera. The previous image is
sampled there bilinearly; a pixel whose source falls outside the previous image or behind its camera keeps the
previous image's own pixel (no warp). Static scenery on the ground (lane markings, crosswalks, kerbs) then
lands where the current frame shows it, whatever the ego did in between (0.5 s of driving, a lateral
displacement off the log); vehicles and tall structures do not (the model corrects them from the layout).

Pixel convention (the projection's, src/projection/geometry.rs): K maps a camera point to pixel-index units,
the centre of pixel i at i (the image spans [-0.5, W - 0.5]). The grid holds source coordinates in those
units, NaN where the pixel keeps its own value.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

# rays this close to parallel with the ground never meet it (metres of height per metre of depth)
MIN_DOWN = 1e-6
# a projected point nearer than this (metres, along the previous camera's axis) is behind it: no warp
MIN_Z = 0.1


def ground_warp_grid(k: np.ndarray, cam2ego: np.ndarray, ego2global: np.ndarray, prev_ego2global: np.ndarray,
                     size, max_depth: float) -> np.ndarray:
    """(H, W, 2) float32 source pixel coordinates (x, y) in the previous image of every current pixel (NaN: keep
    the pixel). ``k`` (3, 3) intrinsics at the render size; ``cam2ego`` (4, 4) shared by both frames;
    ``ego2global`` / ``prev_ego2global`` (4, 4) the current and previous ego poses."""
    if not max_depth > 0:
        raise ValueError(f"ground_warp_grid: max_depth {max_depth} must be > 0")
    H, W = size
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], -1)                              # (H, W, 3) pixel centres
    ray = pix @ np.linalg.inv(np.asarray(k, np.float64)).T                   # camera frame, depth 1
    c2g = np.asarray(ego2global, np.float64) @ np.asarray(cam2ego, np.float64)
    d = ray @ c2g[:3, :3].T                                                  # global direction per unit depth
    o = c2g[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(d[..., 2] < -MIN_DOWN, (float(ego2global[2][3]) - o[2]) / d[..., 2], np.inf)
    depth = np.minimum(depth, float(max_depth))
    p = o + d * depth[..., None]                                             # (H, W, 3) global
    pc2g = np.asarray(prev_ego2global, np.float64) @ np.asarray(cam2ego, np.float64)
    q = (p - pc2g[:3, 3]) @ pc2g[:3, :3]                                     # previous camera frame
    z = q[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (q @ np.asarray(k, np.float64).T)[..., :2] / z[..., None]
    ok = (z > MIN_Z) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5) & (uv[..., 1] >= -0.5) & \
        (uv[..., 1] <= H - 0.5)
    return np.where(ok[..., None], uv, np.nan).astype(np.float32)


def warp_image(img: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) images, (N, H, W, 2) source coordinates (ground_warp_grid) -> (N, C, H, W): bilinear samples
    (taps clamped to the image), the image's own pixel where the grid is NaN."""
    N, C, H, W = img.shape
    if tuple(grid.shape) != (N, H, W, 2):
        raise ValueError(f"warp_image: grid {tuple(grid.shape)} for images {tuple(img.shape)}")
    g = grid.to(img.device, torch.float32)
    ok = torch.isfinite(g).all(-1)                                           # (N, H, W)
    g = torch.nan_to_num(g, nan=0.0)
    norm = torch.stack([(g[..., 0] + 0.5) / W * 2 - 1, (g[..., 1] + 0.5) / H * 2 - 1], -1)
    out = F.grid_sample(img.float(), norm, mode="bilinear", padding_mode="border", align_corners=False)
    return torch.where(ok[:, None], out, img.float()).to(img.dtype)
