"""The torch-free parts of the image-reading planner (docs/e2e_planner.md), shared by the torch model
(`b2dr_ref.e2e_planner`) and the numpy forward (`b2dr_ref.e2e_numpy`): the constants, the input encoding
(`pool2`, `state_vector`), the exported folder's config, one protocol-v2 request's pre- and post-processing
and the serve loop. Imports numpy and the standard library only.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, List, Tuple

import numpy as np

POSES = 8
COMMANDS = ["left", "straight", "right"]
# Target normalisation (x m, y m, heading rad): the loss is L1 in these units.
POSE_SCALE = (10.0, 1.0, 0.1)
WEIGHTS = "planner.safetensors"
CONFIG = "config.json"
FORMAT = "b2dr-e2e-planner"


def pool2(img: np.ndarray) -> np.ndarray:
    """(..., H, W) uint8 -> (..., H // 2, W // 2) uint8: the rounded mean of each 2 x 2 block."""
    h, w = img.shape[-2] // 2 * 2, img.shape[-1] // 2 * 2
    x = img[..., :h, :w].astype(np.uint16)
    s = x[..., 0::2, 0::2] + x[..., 1::2, 0::2] + x[..., 0::2, 1::2] + x[..., 1::2, 1::2]
    return ((s + 2) // 4).astype(np.uint8)


def state_vector(speed: np.ndarray, accel: np.ndarray, command: np.ndarray) -> np.ndarray:
    """(N,) speed m/s, accel m/s^2, command code (0 left, 1 straight, 2 right) -> (N, 5) float32."""
    s = np.zeros((len(speed), 5), np.float32)
    s[:, 0] = speed / 10.0
    s[:, 1] = np.clip(accel, -6.0, 6.0) / 3.0
    s[np.arange(len(speed)), 2 + command.astype(np.int64)] = 1.0
    return s


def read_config(folder: str) -> dict:
    """An exported planner folder's config.json (checked: format, and that the weights file is there)."""
    p = Path(folder)
    if not (p / CONFIG).is_file():
        raise ValueError(f"{folder}: no {CONFIG}; expected an exported planner folder (e.g. models/e2e-planner)")
    cfg = json.loads((p / CONFIG).read_text())
    if not isinstance(cfg, dict) or cfg.get("format") != FORMAT:
        fmt = cfg.get("format") if isinstance(cfg, dict) else None
        raise ValueError(f"{folder}/{CONFIG}: not a {FORMAT} (format {fmt!r})")
    if not (p / WEIGHTS).is_file():
        raise ValueError(f"{folder}: no {WEIGHTS}")
    return cfg


def request_inputs(image_size: Tuple[int, int], image_hwc: np.ndarray, ego: dict,
                   command: str) -> Tuple[np.ndarray, np.ndarray]:
    """One protocol-v2 request -> the model's inputs: (1, 3, H/2, W/2) pooled uint8 image, (1, 5) float32
    state. The image must be the model's size."""
    h, w = image_size
    if image_hwc.shape != (h, w, 3):
        raise ValueError(f"image {image_hwc.shape}, the planner was trained on {(h, w, 3)}")
    img = pool2(image_hwc.transpose(2, 0, 1))[None]
    st = state_vector(np.array([ego["vx"]], np.float32), np.array([ego.get("ax", 0.0)], np.float32),
                      np.array([COMMANDS.index(command)]))
    return img, st


def reply_poses(p: np.ndarray) -> List[List[float]]:
    """(8, 3) de-normalised poses -> the reply's list (an error when any is not finite)."""
    p = np.asarray(p, np.float64)
    if not np.isfinite(p).all():
        raise ValueError("the planner produced a non-finite pose")
    return [[float(x), float(y), float(t)] for x, y, t in p]


def serve_planner(plan_request: Callable[[np.ndarray, dict, str], List[List[float]]],
                  image_size: Tuple[int, int], camera: str) -> None:
    """Serves protocol v2 on stdin/stdout (the planner package `b2dr_planner`, which parses the requests):
    `plan_request(image_hwc, ego, command) -> 8 poses` with `ego` {"vx", "ax"}; a missing camera or a bad
    request (KeyError / ValueError) is an `{"error": ...}` reply."""
    from b2dr_planner import serve

    def plan(req):
        try:
            ego = {"vx": req.ego.vx, "ax": req.ego.ax}
            return plan_request(req.camera(camera).array(), ego, req.command.value)
        except (KeyError, ValueError) as e:
            return {"error": str(e)}

    serve(plan, images="inline", size=tuple(image_size))
