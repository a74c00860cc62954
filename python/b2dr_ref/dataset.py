"""Reader of b2dr's training export (``b2dr export-training``; format: docs/training_data.md).

numpy + safetensors only; torch is optional (``to_torch``). One sample is a dict::

    target, prev        uint8   (C, 3, H, W)      images of the C cameras (current / 0.5 s earlier, from the log)
    ref                 uint8   (C, 2, 3, H, W)   two references per camera: slot 0 ahead, slot 1 behind
                                                  (where the log allows; see ``ref_side``)
    masks               uint8   (C, 15, H, W)     layout masks in {0, 1}, channel order ``mask_channels``
    intrinsics          float64 (C, 3, 3)         at render size
    cam2ego             float64 (C, 4, 4)
    ego2global          float64 (C, 4, 4)         current (displaced, for a perturbed sample) ego pose
    prev_ego2global     float64 (C, 4, 4)
    ref_ego2global      float64 (C, 2, 4, 4)
    cam2cur_ref         float64 (C, 2, 4, 4)      inv(ego2global) @ ref_ego2global @ cam2ego: the PE's cam2cur
                                                  of each reference (src/projection/pe.rs); the current
                                                  camera's is ``cam2ego``
    ref_distance        float32 (C, 2)            signed distance along the logged heading (m)
    ref_step            int32   (C, 2)
    step, prev_step     int
    prev2               uint8   (C, 3, H, W)      only in a --prev-chain export: the log's image 0.5 s before
                                                  ``prev`` (the previous frame's own previous frame)
    prev_masks          uint8   (C, 15, H, W)     only in a --prev-chain export: the previous frame's layout at
                                                  its logged pose and step
    prev2_step          int                       only in a --prev-chain export
    prev2_ego2global    float64 (C, 4, 4)         only in a --prev-chain export written since session 41: the
                                                  pose of ``prev2`` (absent from older chain exports)
    offset              float64 (3,)              (dx m, dy m, dyaw degrees) in the ego frame
    perturbed           bool
    scenario            str
    cameras             list[str]
"""
from __future__ import annotations

import json
import os
from typing import Any, Dict, List

import numpy as np
from safetensors import safe_open

FORMAT = "b2dr-training"
VERSION = 1
_CHAIN = ["prev2", "prev_masks_packed", "prev2_step"]     # --prev-chain exports only
_CHAIN_POSE = "prev2_ego2global"                          # --prev-chain exports written since session 41
_PER_ROW = [
    "target",
    "prev",
    "ref",
    "masks_packed",
    "intrinsics",
    "cam2ego",
    "ego2global",
    "prev_ego2global",
    "ref_ego2global",
    "ref_distance",
    "ref_step",
    "step",
    "prev_step",
    "scenario_index",
    "offset",
]


def unpack_masks(packed: np.ndarray, channels: int = 15) -> np.ndarray:
    """``(..., H, W)`` uint16 bit-packed masks -> ``(..., channels, H, W)`` uint8 in {0, 1}."""
    bits = np.arange(channels, dtype=np.uint16).reshape((channels, 1, 1))
    return ((packed[..., None, :, :] >> bits) & 1).astype(np.uint8)


class TrainingSet:
    """Random access to the samples of one export folder (``index.json`` + ``shard_*.safetensors``)."""

    def __init__(self, root: str):
        self.root = root
        with open(os.path.join(root, "index.json"), "r", encoding="utf-8") as f:
            self.index: Dict[str, Any] = json.load(f)
        if self.index.get("format") != FORMAT or self.index.get("version") != VERSION:
            raise ValueError(
                f"{root}: not a {FORMAT} v{VERSION} export "
                f"(format {self.index.get('format')!r}, version {self.index.get('version')!r})"
            )
        self.cameras: List[str] = list(self.index["cameras"])
        self.mask_channels: List[str] = list(self.index["mask_channels"])
        self.height: int = int(self.index["height"])
        self.width: int = int(self.index["width"])
        self.samples: List[Dict[str, Any]] = self.index["samples"]
        self.prev_chain: bool = bool(self.index.get("prev_chain", False))
        self._open: Dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.samples)

    def _shard(self, i: int):
        if i not in self._open:
            name = self.index["shards"][i]["file"]
            self._open[i] = safe_open(os.path.join(self.root, name), framework="np")
        return self._open[i]

    def raw(self, i: int) -> Dict[str, np.ndarray]:
        """The stored tensors of sample ``i`` (row of its shard), without unpacking."""
        s = self.samples[i]
        f = self._shard(int(s["shard"]))
        r = int(s["row"])
        keys = _PER_ROW + (_CHAIN if self.prev_chain else [])
        if self.prev_chain and _CHAIN_POSE in f.keys():
            keys = keys + [_CHAIN_POSE]
        return {k: f.get_slice(k)[r : r + 1][0] for k in keys}

    def __getitem__(self, i: int) -> Dict[str, Any]:
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} of {len(self)}")
        t = self.raw(i)
        s = self.samples[i]
        e2g_inv = np.linalg.inv(t["ego2global"])  # (C, 4, 4)
        cam2cur_ref = e2g_inv[:, None] @ t["ref_ego2global"] @ t["cam2ego"][:, None]
        chain = {}
        if self.prev_chain:
            chain = {"prev2": t["prev2"], "prev_masks": unpack_masks(t["prev_masks_packed"], len(self.mask_channels)),
                     "prev2_step": int(t["prev2_step"])}
            if _CHAIN_POSE in t:
                chain[_CHAIN_POSE] = t[_CHAIN_POSE]
        return {
            **chain,
            "target": t["target"],
            "prev": t["prev"],
            "ref": t["ref"],
            "masks": unpack_masks(t["masks_packed"], len(self.mask_channels)),
            "intrinsics": t["intrinsics"],
            "cam2ego": t["cam2ego"],
            "ego2global": t["ego2global"],
            "prev_ego2global": t["prev_ego2global"],
            "ref_ego2global": t["ref_ego2global"],
            "cam2cur_ref": cam2cur_ref,
            "ref_distance": t["ref_distance"],
            "ref_step": t["ref_step"],
            "ref_side": [[r["side"] for r in cam] for cam in s["refs"]],
            "step": int(t["step"]),
            "prev_step": int(t["prev_step"]),
            "offset": t["offset"],
            "perturbed": bool(s["perturbed"]),
            "scenario": s["scenario"],
            "cameras": self.cameras,
        }

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


def to_torch(sample: Dict[str, Any]):
    """The sample with arrays as torch tensors (images as float in [0, 1]); needs torch."""
    import torch  # optional dependency

    out: Dict[str, Any] = {}
    for k, v in sample.items():
        if isinstance(v, np.ndarray):
            t = torch.from_numpy(np.ascontiguousarray(v))
            if k in ("target", "prev", "ref", "prev2"):
                t = t.float() / 255.0
            out[k] = t
        else:
            out[k] = v
    return out
