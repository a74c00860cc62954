"""PETR-style 3D position encodings: an exact port of ``src/projection/pe.rs`` (f64 math, f32 output).

Conventions (see pe.rs for the full description):
- LID depth bins ``d_i = depth_start + (d_max - depth_start) / (D (D + 1)) * i (i + 1)``, ``d_max = position_range[3]``;
- a feature cell at image coordinate ``(u, v)`` (``PixelGrid.CENTRE``: ``u = (x + 0.5) W / w - 0.5``;
  ``PixelGrid.PETR_CORNER``: ``u = x W / w``) at depth ``d`` is ``p = cam2cur * (max(d, eps) K^-1 [u v 1])``;
- normalised ``(p - lo) / (hi - lo)``, mmdet ``inverse_sigmoid(x, eps)``;
- layout ``(D * 3, h, w)`` with channel ``d * 3 + axis``.

``cam2cur = cur_ego2global^-1 * image_ego2global * cam2ego`` puts current and reference images in the CURRENT ego
frame.  ``intrinsic_scaled`` is ``Camera::intrinsic_scaled`` (pixel-centre rescaling of K to a new image size).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import List, Sequence, Tuple

import numpy as np


class PixelGrid(enum.Enum):
    CENTRE = "centre"
    PETR_CORNER = "petr_corner"


@dataclass
class PeConfig:
    depth_num: int = 64
    depth_start: float = 1.0
    position_range: Tuple[float, ...] = (-61.2, -61.2, -10.0, 61.2, 61.2, 10.0)
    eps: float = 1e-5
    grid: PixelGrid = PixelGrid.CENTRE

    @classmethod
    def from_controlnet_config(cls, cfg) -> "PeConfig":
        """The PE settings of a B2D-R ControlNet config (``pe_depth_num``, ``pe_depth_start``, ``pe_position_range``)."""
        return cls(depth_num=int(cfg["pe_depth_num"]), depth_start=float(cfg["pe_depth_start"]),
                   position_range=tuple(float(v) for v in cfg["pe_position_range"]))


LATENT_BLOCK_SIZES = [(28, 50), (14, 25), (7, 13), (4, 7)]


def depth_bins(cfg: PeConfig) -> List[float]:
    n = float(cfg.depth_num)
    bin_ = (cfg.position_range[3] - cfg.depth_start) / (n * (n + 1.0))
    return [cfg.depth_start + bin_ * float(i) * (float(i) + 1.0) for i in range(cfg.depth_num)]


def inverse_sigmoid(x: float, eps: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return math.log(max(x, eps) / max(1.0 - x, eps))


def intrinsic_scaled(k: np.ndarray, width: int, height: int, new_width: int, new_height: int) -> np.ndarray:
    """``Camera::intrinsic_scaled``: K (3x3, row-major maths convention) of an image resized to new_width x new_height."""
    k = np.asarray(k, dtype=np.float64)
    sx = new_width / max(width, 1)
    sy = new_height / max(height, 1)
    out = k.copy()
    out[0, 0] = k[0, 0] * sx
    out[1, 0] = k[1, 0] * sy
    out[0, 1] = k[0, 1] * sx
    out[1, 1] = k[1, 1] * sy
    out[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return out


def cam2cur(cam2ego: np.ndarray, image_ego2global: np.ndarray, cur_ego2global: np.ndarray) -> np.ndarray:
    """Camera -> current ego (4x4, f64) for an image taken at ego pose ``image_ego2global``."""
    return np.linalg.inv(np.asarray(cur_ego2global, np.float64)) @ np.asarray(image_ego2global, np.float64) \
        @ np.asarray(cam2ego, np.float64)


def position_encoding(k: np.ndarray, img_w: int, img_h: int, cam2cur_m: np.ndarray, h: int, w: int,
                      cfg: PeConfig = PeConfig()) -> np.ndarray:
    """PE of one feature map: ``(D*3, h, w)`` float32, channel ``d * 3 + axis`` (pe.rs ``position_encoding``)."""
    if not (h > 0 and w > 0 and img_w > 0 and img_h > 0):
        raise ValueError(f"position_encoding: empty size img {img_w}x{img_h} feat {h}x{w}")
    k = np.asarray(k, dtype=np.float64)
    if abs(np.linalg.det(k)) <= 1e-12:
        raise ValueError("position_encoding: singular intrinsics")
    r = cfg.position_range
    if not (r[3] > r[0] and r[4] > r[1] and r[5] > r[2]):
        raise ValueError(f"position_encoding: empty position range {r}")
    kinv = np.linalg.inv(k)
    m = np.asarray(cam2cur_m, dtype=np.float64)
    depths = depth_bins(cfg)
    sx, sy = img_w / w, img_h / h
    lo = [r[0], r[1], r[2]]
    span = [r[3] - r[0], r[4] - r[1], r[5] - r[2]]
    out = np.zeros((len(depths) * 3, h, w), dtype=np.float32)
    for y in range(h):
        v = (y + 0.5) * sy - 0.5 if cfg.grid == PixelGrid.CENTRE else y * sy
        for x in range(w):
            u = (x + 0.5) * sx - 0.5 if cfg.grid == PixelGrid.CENTRE else x * sx
            ray = kinv @ np.array([u, v, 1.0])
            for di, d in enumerate(depths):
                q = ray * max(d, cfg.eps)
                # glam DMat4::transform_point3: affine (x_axis*x + y_axis*y + z_axis*z + w_axis), no divide
                p = m[:3, :3] @ q + m[:3, 3]
                for a in range(3):
                    out[di * 3 + a, y, x] = np.float32(inverse_sigmoid((p[a] - lo[a]) / span[a], cfg.eps))
    return out


def latent_block_sizes(render_w: int, render_h: int, n_blocks: int = 4) -> List[Tuple[int, int]]:
    """Latent ``(H/8, W/8)`` then ``n_blocks - 1`` stride-2 reductions ``n -> ceil(n / 2)`` (pe.rs: n_blocks = 4)."""
    s = (render_h // 8, render_w // 8)
    v = [s]
    for _ in range(n_blocks - 1):
        s = ((s[0] + 1) // 2, (s[1] + 1) // 2)
        v.append(s)
    return v


def position_encodings_for_blocks(k_native: np.ndarray, native_w: int, native_h: int, render_w: int, render_h: int,
                                  cam2cur_m: np.ndarray, cfg: PeConfig = PeConfig()):
    """pe.rs ``position_encodings_for_blocks``: the PE at the four latent block sizes of a render (finest first),
    intrinsics rescaled from the camera's native size. Returns [(h, w, pe (D*3, h, w))]. NB: a Ref-Attn location
    ``down.i`` uses block size ``min(i + 1, B - 1)`` (see ``location_sizes``), so the finest entry is not used."""
    k = intrinsic_scaled(k_native, native_w, native_h, render_w, render_h)
    return [(h, w, position_encoding(k, render_w, render_h, cam2cur_m, h, w, cfg))
            for (h, w) in latent_block_sizes(render_w, render_h)]


def block_sizes_from_latent(h0: int, w0: int, n_blocks: int) -> List[Tuple[int, int]]:
    """``h_i x w_i`` for i = 0..n_blocks-1 starting from the latent size."""
    s = (h0, w0)
    v = [s]
    for _ in range(n_blocks - 1):
        s = ((s[0] + 1) // 2, (s[1] + 1) // 2)
        v.append(s)
    return v


def location_sizes(ref_attn: Sequence[str], n_blocks: int, latent_hw: Tuple[int, int]) -> List[Tuple[int, int]]:
    """Feature size of each Ref-Attn location (contract 2b/2d): ``down.i`` -> ``h_{min(i+1, B-1)}``, ``mid`` ->
    ``h_{B-1}``."""
    sizes = block_sizes_from_latent(latent_hw[0], latent_hw[1], n_blocks)
    out = []
    for loc in ref_attn:
        if loc == "mid":
            out.append(sizes[n_blocks - 1])
        else:
            i = int(loc.split(".")[1])
            out.append(sizes[min(i + 1, n_blocks - 1)])
    return out


@dataclass
class CameraGeometry:
    """One camera of one frame: intrinsics at the render size (3x3), camera -> ego (4x4)."""
    k_render: np.ndarray
    cam2ego: np.ndarray


def pe_inputs(cams: Sequence[CameraGeometry], render_hw: Tuple[int, int], cur_ego2global: np.ndarray,
              ref_ego2global: Sequence[Tuple[np.ndarray, np.ndarray]], ref_attn: Sequence[str], n_blocks: int,
              cfg: PeConfig, latent_factor: int = 8):
    """PE inputs of every Ref-Attn location for a frame of ``N = len(cams)`` cameras.

    ``ref_ego2global[c] = (front_pose, rear_pose)``: the ego poses at which camera c's two reference images were
    recorded.  The latent size is ``render // latent_factor`` (floor, as pe.rs ``latent_block_sizes``).
    Returns ``(pe_cur, pe_ref)``: lists over locations of float32 arrays ``(N, 3D, h, w)`` and ``(N, 2, 3D, h, w)``.
    """
    H, W = render_hw
    sizes = location_sizes(ref_attn, n_blocks, (H // latent_factor, W // latent_factor))
    pe_cur, pe_ref = [], []
    for (h, w) in sizes:
        cur = []
        ref = []
        for c, cam in enumerate(cams):
            m = cam2cur(cam.cam2ego, cur_ego2global, cur_ego2global)
            cur.append(position_encoding(cam.k_render, W, H, m, h, w, cfg))
            ref.append(np.stack([position_encoding(cam.k_render, W, H, cam2cur(cam.cam2ego, pose, cur_ego2global),
                                                   h, w, cfg) for pose in ref_ego2global[c]]))
        pe_cur.append(np.stack(cur))
        pe_ref.append(np.stack(ref))
    return pe_cur, pe_ref
