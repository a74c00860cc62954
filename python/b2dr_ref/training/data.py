"""The data the renderer trains on, shared by every recipe (b2dr_ref.train, b2dr_ref.training.sd15): one camera
sample (``Sample``), its sources (the exported set through dataset.TrainingSet, or a synthetic one for tests and
smoke runs) and the PETR geometry of a sample (pe.py's formulas, vectorised over pixels and depths)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Protocol, Tuple

import numpy as np

from ..controlnet import MASK_CHANNELS
from ..pe import PeConfig, PixelGrid, cam2cur, depth_bins


@dataclass
class Sample:
    """One camera of one training frame. Images uint8 (3, H, W) at render size; masks {0,1} (15, H, W)."""
    target: np.ndarray
    prev: np.ndarray
    refs: np.ndarray              # (2, 3, H, W): front, rear
    masks: np.ndarray             # (15, H, W), channel order controlnet.MASK_CHANNELS
    k: np.ndarray                 # (3, 3) intrinsics at the render size
    cam2ego: np.ndarray           # (4, 4)
    ego2global: np.ndarray        # (4, 4) current frame
    prev_ego2global: np.ndarray   # (4, 4) (not used by the model: the previous frame has no PE)
    ref_ego2global: np.ndarray    # (2, 4, 4) front, rear
    camera: str
    # a --prev-chain export only: the previous frame's own previous image (3, H, W) and its layout (15, H, W);
    # the pose of that image (4, 4) where the export holds it (written since session 41)
    prev2: Optional[np.ndarray] = None
    prev_masks: Optional[np.ndarray] = None
    prev2_ego2global: Optional[np.ndarray] = None


class SampleSource(Protocol):
    """Item i is one camera of one frame. A source that draws its references per epoch (shards.ShardSource) also
    has ``set_epoch(epoch)``; the trainers call it (through common.CameraSamples) before each epoch."""
    render_size: Tuple[int, int]      # (H, W)
    cameras: List[str]

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Sample: ...


def _rot_z(yaw: float, xyz=(0.0, 0.0, 0.0)) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = xyz
    return m


class SyntheticSource:
    """Random but learnable samples: the target paints the mask classes with fixed colours over a sky/ground
    split; prev / refs are shifted copies. Deterministic per index (seed, i)."""

    def __init__(self, n: int = 16, render_size=(56, 104), cameras=("CAM_FRONT", "CAM_BACK"), seed: int = 0):
        self.n = n
        self.render_size = (int(render_size[0]), int(render_size[1]))
        self.cameras = list(cameras)
        self.seed = seed
        self.palette = np.random.default_rng(1234).integers(0, 256, size=(len(MASK_CHANNELS), 3))

    def __len__(self):
        return self.n

    def _image(self, masks, shift):
        h, w = self.render_size
        img = np.zeros((3, h, w), np.float64)
        img[:, : h // 2] = np.array([120, 170, 230])[:, None, None]
        img[:, h // 2:] = np.array([90, 120, 70])[:, None, None]
        for c in range(masks.shape[0]):
            m = np.roll(masks[c], shift, axis=1) > 0
            img[:, m] = self.palette[c][:, None]
        return img.clip(0, 255).astype(np.uint8)

    def __getitem__(self, i: int) -> Sample:
        rng = np.random.default_rng((self.seed, int(i)))
        h, w = self.render_size
        masks = np.zeros((len(MASK_CHANNELS), h, w), np.uint8)
        masks[10, h // 2:] = 1                                      # drivable area
        for _ in range(3):
            c = int(rng.integers(0, 10))
            y0, x0 = int(rng.integers(h // 3, h - 8)), int(rng.integers(0, w - 12))
            masks[c, y0:y0 + int(rng.integers(4, 12)), x0:x0 + int(rng.integers(6, 24))] = 1
        cam = self.cameras[int(i) % len(self.cameras)]
        f = 0.8 * w
        k = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        yaw = 0.0 if cam.endswith("FRONT") else math.pi
        cam2ego = _rot_z(yaw, (1.5, 0.0, 1.6)) @ np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
        x = float(rng.uniform(-50, 50))
        e2g = _rot_z(float(rng.uniform(-0.3, 0.3)), (x, float(rng.uniform(-5, 5)), 0.0))
        d = rng.choice([rng.uniform(2, 5), rng.uniform(5, 10), rng.uniform(10, 15)], p=[0.1, 0.3, 0.6])
        refs_pose = np.stack([e2g @ _rot_z(0.0, (d, 0, 0)), e2g @ _rot_z(0.0, (-d, 0, 0))])
        return Sample(target=self._image(masks, 0), prev=self._image(masks, 2),
                      refs=np.stack([self._image(masks, 5), self._image(masks, -5)]), masks=masks, k=k,
                      cam2ego=cam2ego, ego2global=e2g, prev_ego2global=e2g @ _rot_z(0.0, (-3.0, 0, 0)),
                      ref_ego2global=refs_pose, camera=cam)


class DatasetSource:
    """The exported training data (world.md 2, docs/training_data.md) read by ``b2dr_ref.dataset.TrainingSet``,
    one Sample per (frame, camera): index ``i = frame * n_cameras + camera``. ``ds``: an opened TrainingSet (or
    anything with its interface: cameras, mask_channels, height, width, __len__, __getitem__ -> the sample dict)."""

    def __init__(self, directory: Optional[str] = None, ds=None):
        if ds is None:
            from ..dataset import TrainingSet      # python/b2dr_ref/dataset.py (the export's reader)

            ds = TrainingSet(directory)
        self.ds = ds
        if list(ds.mask_channels) != list(MASK_CHANNELS):
            raise ValueError(f"{directory}: mask channels {list(ds.mask_channels)} differ from the model's "
                             f"{MASK_CHANNELS}")
        self.render_size = (int(ds.height), int(ds.width))
        self.cameras = list(ds.cameras)
        self.prev_chain = bool(getattr(ds, "prev_chain", False))
        self._frame = (None, None)

    def __len__(self):
        return len(self.ds) * len(self.cameras)

    def __getitem__(self, i: int) -> Sample:
        f, c = divmod(int(i), len(self.cameras))
        if self._frame[0] != f:
            self._frame = (f, self.ds[f])
        s = self._frame[1]
        return Sample(target=s["target"][c], prev=s["prev"][c], refs=s["ref"][c], masks=s["masks"][c],
                      k=np.asarray(s["intrinsics"][c], np.float64), cam2ego=np.asarray(s["cam2ego"][c], np.float64),
                      ego2global=np.asarray(s["ego2global"][c], np.float64),
                      prev_ego2global=np.asarray(s["prev_ego2global"][c], np.float64),
                      ref_ego2global=np.asarray(s["ref_ego2global"][c], np.float64), camera=self.cameras[c],
                      prev2=s["prev2"][c] if "prev2" in s else None,
                      prev_masks=s["prev_masks"][c] if "prev_masks" in s else None,
                      prev2_ego2global=np.asarray(s["prev2_ego2global"][c], np.float64)
                      if "prev2_ego2global" in s else None)


def open_source(data: str, render_size=None, seed: int = 0, reference_bins=None) -> SampleSource:
    """``synthetic[:N]`` -> SyntheticSource (at the config's render size); a shard folder (training/shards.py) ->
    ShardSource (references re-drawn each epoch with ``reference_bins``, default the export's, seeded by ``seed``);
    else the exported dataset folder (references fixed at export time)."""
    if data.startswith("synthetic"):
        n = int(data.split(":")[1]) if ":" in data else 16
        return SyntheticSource(n=n, render_size=render_size or (56, 104))
    from .shards import ShardSource, is_shard_dir

    if is_shard_dir(data):
        src = ShardSource(data, bins=reference_bins, seed=seed)
        if list(src.mask_channels) != list(MASK_CHANNELS):
            raise ValueError(f"{data}: mask channels {src.mask_channels} differ from the model's {MASK_CHANNELS}")
        return src
    return DatasetSource(data)


# ---------------------------------------------------------------------------------------------------------------
# PETR geometry (pe.py's formulas, vectorised over pixels and depths)
# ---------------------------------------------------------------------------------------------------------------


def position_encoding_np(k, img_w: int, img_h: int, m, h: int, w: int, cfg: PeConfig) -> np.ndarray:
    """pe.position_encoding, vectorised: (3 D, h, w) float32, channel d * 3 + axis."""
    k = np.asarray(k, np.float64)
    m = np.asarray(m, np.float64)
    kinv = np.linalg.inv(k)
    sx, sy = img_w / w, img_h / h
    xs, ys = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    if cfg.grid == PixelGrid.CENTRE:
        u, v = (xs + 0.5) * sx - 0.5, (ys + 0.5) * sy - 0.5
    else:
        u, v = xs * sx, ys * sy
    uu, vv = np.meshgrid(u, v)                                           # (h, w)
    pix = np.stack([uu, vv, np.ones_like(uu)], -1)                       # (h, w, 3)
    ray = pix @ kinv.T
    d = np.maximum(np.asarray(depth_bins(cfg)), cfg.eps)
    q = ray[None] * d[:, None, None, None]                               # (D, h, w, 3)
    p = q @ m[:3, :3].T + m[:3, 3]
    r = cfg.position_range
    lo, span = np.array(r[:3]), np.array(r[3:]) - np.array(r[:3])
    x = np.clip((p - lo) / span, 0.0, 1.0)
    x = np.log(np.maximum(x, cfg.eps) / np.maximum(1.0 - x, cfg.eps))
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2).reshape(-1, h, w)).astype(np.float32)


def sample_pe(s: Sample, cfg: PeConfig, sizes, render_hw) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """pe_cur[j] (3D, h_j, w_j), pe_ref[j] (2, 3D, h_j, w_j) of one sample (pe.pe_inputs for one camera)."""
    H, W = render_hw
    m_cur = cam2cur(s.cam2ego, s.ego2global, s.ego2global)
    m_ref = [cam2cur(s.cam2ego, s.ref_ego2global[r], s.ego2global) for r in range(2)]
    cur, ref = [], []
    for (h, w) in sizes:
        cur.append(position_encoding_np(s.k, W, H, m_cur, h, w, cfg))
        ref.append(np.stack([position_encoding_np(s.k, W, H, m, h, w, cfg) for m in m_ref]))
    return cur, ref
