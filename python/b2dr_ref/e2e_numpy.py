"""The image-reading planner's forward in numpy (docs/e2e_planner.md, "Serving without torch"): the same
network as `b2dr_ref.e2e_planner.E2EPlanner` in eval mode (convolutions, GroupNorm, SiLU, the MLP head, the
POSE_SCALE de-normalisation), read from an exported folder (`config.json`, `planner.safetensors`) with
safetensors.numpy. Imports numpy, safetensors and the standard library only, so a machine without torch can
serve `models/e2e-planner` over protocol v2:

    python -m b2dr_ref.e2e_numpy serve --weights ../models/e2e-planner    (b2dr run --planner cmd:...)

The request parsing, the input encoding and the reply are `b2dr_ref.e2e_common`'s, shared with the torch
server, so both answer a request alike (python/tests/test_e2e_numpy.py: within 1e-5 of torch's poses).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from .e2e_common import POSE_SCALE, POSES, WEIGHTS, read_config, reply_poses, request_inputs, serve_planner

GROUPS = 8          # nn.GroupNorm(8, c)
GN_EPS = 1e-5       # its default eps
# (weight index in `convs`, out channels as a multiple of the width (0: 16 fixed), kernel, stride, padding,
# followed by GroupNorm + SiLU): E2EPlanner.convs, layer by layer
CONVS = [(0, 1, 5, 2, 2, True), (3, 1, 3, 2, 1, True), (6, 2, 3, 2, 1, True), (9, 2, 3, 1, 1, True),
         (12, 0, 1, 1, 0, False)]
HEAD = [0, 2, 4]    # E2EPlanner.head's Linear layers (SiLU between them)


def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """(B, C, H, W) * (O, C, k, k) -> (B, O, Ho, Wo), as torch's Conv2d (cross-correlation, zero padding)."""
    k = w.shape[-1]
    if pad:
        x = np.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)))
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(2, 3))[:, :, ::stride, ::stride]
    y = np.tensordot(win, w, axes=([1, 4, 5], [1, 2, 3]))          # (B, Ho, Wo, O)
    return np.ascontiguousarray(y.transpose(0, 3, 1, 2)) + b[None, :, None, None]


def group_norm(x: np.ndarray, gamma: np.ndarray, beta: np.ndarray, groups: int = GROUPS,
               eps: float = GN_EPS) -> np.ndarray:
    """torch's GroupNorm: per sample and group, the biased mean and variance over (C / G, H, W)."""
    n, c = x.shape[:2]
    g = x.reshape(n, groups, -1)
    mean = g.mean(-1, keepdims=True)
    var = ((g - mean) ** 2).mean(-1, keepdims=True)
    g = (g - mean) / np.sqrt(var + eps)
    return g.reshape(x.shape) * gamma[None, :, None, None] + beta[None, :, None, None]


def silu(x: np.ndarray) -> np.ndarray:
    """x * sigmoid(x), written with tanh so that no exp overflows."""
    return x * (0.5 + 0.5 * np.tanh(0.5 * x))


class NumpyPlanner:
    """E2EPlanner's forward (eval) in numpy. `dtype`: float64 (default; the reference arithmetic) or float32."""

    def __init__(self, folder: str, dtype=np.float64):
        from safetensors.numpy import load_file

        cfg = read_config(folder)
        self.image_size: Tuple[int, int] = tuple(int(v) for v in cfg["image_size"])
        self.width = int(cfg["width"])
        self.dtype = np.dtype(dtype)
        sd = load_file(str(Path(folder) / WEIGHTS))
        c = self.width
        h, w = self.image_size[0] // 2, self.image_size[1] // 2
        want: Dict[str, tuple] = {}
        cin = 3
        for i, mult, k, _, _, norm in CONVS:
            cout = mult * c if mult else 16
            want[f"convs.{i}.weight"] = (cout, cin, k, k)
            want[f"convs.{i}.bias"] = (cout,)
            if norm:
                want[f"convs.{i + 1}.weight"] = (cout,)
                want[f"convs.{i + 1}.bias"] = (cout,)
            cin = cout
        for _ in range(3):
            h, w = (h + 1) // 2, (w + 1) // 2
        dims = [16 * h * w + 5, 256, 256, POSES * 3]
        for j, i in enumerate(HEAD):
            want[f"head.{i}.weight"] = (dims[j + 1], dims[j])
            want[f"head.{i}.bias"] = (dims[j + 1],)
        missing = sorted(set(want) - set(sd))
        extra = sorted(set(sd) - set(want))
        if missing or extra:
            raise ValueError(f"{folder}/{WEIGHTS}: not E2EPlanner(width {c}) weights: missing {missing[:4]}, "
                             f"unexpected {extra[:4]}")
        for k, shape in want.items():
            if tuple(sd[k].shape) != shape:
                raise ValueError(f"{folder}/{WEIGHTS}: {k} has shape {tuple(sd[k].shape)}, expected {shape} "
                                 f"(config: image_size {list(self.image_size)}, width {c})")
        # as load_planner: f16 -> f32 (torch computes in f32), then the arithmetic dtype
        self.p = {k: v.astype(np.float32).astype(self.dtype) for k, v in sd.items()}
        self.scale = np.array(POSE_SCALE, np.float32).astype(self.dtype)

    def forward(self, image: np.ndarray, state: np.ndarray) -> np.ndarray:
        """(B, 3, H/2, W/2) pooled uint8-range image, (B, 5) state -> (B, 8, 3) poses (x, y, heading)."""
        p = self.p
        x = np.asarray(image, np.float32).astype(self.dtype) / 127.5 - 1.0
        for i, _, _, stride, pad, norm in CONVS:
            x = conv2d(x, p[f"convs.{i}.weight"], p[f"convs.{i}.bias"], stride, pad)
            if norm:
                x = silu(group_norm(x, p[f"convs.{i + 1}.weight"], p[f"convs.{i + 1}.bias"]))
        x = np.concatenate([x.reshape(len(x), -1), np.asarray(state, np.float32).astype(self.dtype)], 1)
        for j, i in enumerate(HEAD):
            x = x @ p[f"head.{i}.weight"].T + p[f"head.{i}.bias"]
            if j < len(HEAD) - 1:
                x = silu(x)
        return x.reshape(-1, POSES, 3) * self.scale

    __call__ = forward


def load_planner(folder: str, dtype=np.float64) -> NumpyPlanner:
    return NumpyPlanner(folder, dtype)


def plan_request(model: NumpyPlanner, image_hwc: np.ndarray, ego: dict, command: str) -> List[List[float]]:
    """One protocol-v2 request -> 8 poses (the image must be the model's size): as e2e_planner.plan_request."""
    img, st = request_inputs(model.image_size, image_hwc, ego, command)
    return reply_poses(model.forward(img, st)[0])


def serve(a) -> None:
    model = load_planner(a.weights, np.float32 if a.dtype == "f32" else np.float64)
    serve_planner(lambda img, ego, command: plan_request(model, img, ego, command), model.image_size, a.camera)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.e2e_numpy")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve")
    s.add_argument("--weights", required=True, help="exported planner folder (e.g. ../models/e2e-planner)")
    s.add_argument("--camera", default="CAM_FRONT")
    s.add_argument("--dtype", default="f64", choices=["f64", "f32"], help="arithmetic (default f64)")
    a = p.parse_args(argv)
    {"serve": serve}[a.cmd](a)


if __name__ == "__main__":
    main()
