"""A small segmentation network for a layout score that is not a colour lookup.

eval-render's layout score classifies each pixel by its colour bin alone (src/eval/fidelity/metrics.rs). That
classifier is exact on the ground truth but measures colour exactness, not whether a vehicle is drawn: the
ground truth plus an invisible change (i.i.d. noise of 4 levels, 36 dB; or +6 levels on every channel) already
scores vehicle IoU 0.27-0.30 instead of 0.97 (docs/training.md, "The gate's layout score measured colour
exactness"). This network classifies a pixel from its neighbourhood (about 70 px), trained on the world's ground truth under the degradations a renderer may
make without failing to draw (blur, noise, colour shifts), so that a soft but correct vehicle counts.

Net (shapes for one image, H x W any; every conv 3x3 with zero padding, then ReLU, unless said otherwise):
x (3, H, W) in [-1, 1] -> stem 3->C (C, H, W) = f -> down, stride 2, C->M (M, ceil(H/2), ceil(W/2)) -> four convs
M->M with dilations 1, 2, 4, 8 -> nearest upsampling x2 cropped to (M, H, W) -> concat [f, that] (C+M, H, W)
-> fuse C+M->C -> head conv1x1 C->17 (no ReLU): logits (17, H, W). Receptive field about 70 px (a near car's
whole body). Classes: src/world/palette.rs SemanticClass ids 0..16.

    py -m b2dr_ref.layout_seg train --frames DIR --out RUN [--steps 3000]   # DIR: `b2dr world --out` folders

Scoring: `b2dr eval-render` (the Rust port, src/eval/fidelity/segmenter.rs, with the committed weights) or
`tools/layout_ceiling.py --seg RUN/seg.safetensors`. How the committed model was trained: models/layout-seg/README.md.
"""

from __future__ import annotations

import argparse
import glob
import math
import os
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from PIL import Image

N_CLASSES = 17
DILATIONS = (1, 2, 4, 8)
# src/world/palette.rs SemanticClass::display_colour, in class-id order
CLASS_COLOURS = np.array([
    (70, 130, 180), (107, 142, 35), (244, 35, 232), (200, 200, 200), (128, 64, 128), (255, 255, 255),
    (250, 170, 30), (255, 0, 0), (70, 70, 70), (0, 190, 0), (153, 153, 153), (0, 0, 142), (220, 20, 60),
    (119, 11, 32), (255, 120, 0), (190, 153, 153), (100, 100, 100)], np.uint8)
CLASS_NAMES = ["sky", "grass", "sidewalk", "kerb", "road", "lane_marking", "crosswalk", "stop_line", "building",
               "vegetation", "pole", "vehicle", "pedestrian", "bicycle", "traffic_cone", "barrier", "other_object"]


class LayoutSeg(nn.Module):
    def __init__(self, width: int = 16, mid: int = 32):
        super().__init__()
        self.stem = nn.Conv2d(3, width, 3, padding=1)
        self.down = nn.Conv2d(width, mid, 3, stride=2, padding=1)
        self.convs = nn.ModuleList(nn.Conv2d(mid, mid, 3, padding=d, dilation=d) for d in DILATIONS)
        self.fuse = nn.Conv2d(width + mid, width, 3, padding=1)
        self.head = nn.Conv2d(width, N_CLASSES, 1)

    def forward(self, x):                      # x (B, 3, H, W) in [-1, 1] -> logits (B, 17, H, W)
        h, w = x.shape[-2:]
        f = F.relu(self.stem(x))               # (B, width, H, W)
        y = F.relu(self.down(f))               # (B, mid, ceil(H/2), ceil(W/2))
        for c in self.convs:
            y = F.relu(c(y))
        y = y.repeat_interleave(2, -2).repeat_interleave(2, -1)[..., :h, :w]   # nearest x2, cropped to (H, W)
        return self.head(F.relu(self.fuse(torch.cat([f, y], 1))))


def class_ids(class_rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) display colours -> (H, W) class ids; an unknown colour is an error."""
    out = np.full(class_rgb.shape[:2], 255, np.uint8)
    for c, col in enumerate(CLASS_COLOURS):
        out[(class_rgb == col).all(-1)] = c
    if (out == 255).any():
        raise ValueError("class image holds a colour that is no class (palette changed?)")
    return out


def load_frames(root: str):
    """Every `<CAM>.png` with its `<CAM>_class.png` under root (the layout of `b2dr world --out`)."""
    rgb, cls = [], []
    for p in sorted(glob.glob(os.path.join(root, "**", "*_class.png"), recursive=True)):
        img = p[:-len("_class.png")] + ".png"
        rgb.append(np.array(Image.open(img).convert("RGB")))
        cls.append(class_ids(np.array(Image.open(p).convert("RGB"))))
    if not rgb:
        raise SystemExit(f"no <CAM>.png + <CAM>_class.png pairs under {root}")
    return np.stack(rgb), np.stack(cls)


def gaussian_blur(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Per-image Gaussian blur of x (B, 3, H, W), sigma (B,) pixels (0: unchanged); replicate padding."""
    r = 5
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    s = sigma.clamp_min(1e-3)[:, None]
    k = torch.exp(-t[None] ** 2 / (2 * s * s))
    k = k / k.sum(1, keepdim=True)                              # (B, 2r+1)
    b, c, h, w = x.shape
    y = F.pad(x.reshape(1, b * c, h, w), (r, r, r, r), mode="replicate")
    kk = k.repeat_interleave(c, 0)                               # (B*C, 2r+1)
    y = F.conv2d(y, kk[:, None, None, :], groups=b * c)
    y = F.conv2d(y, kk[:, None, :, None], groups=b * c)
    return y.reshape(b, c, h, w)


def degrade(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """The degradations a renderer may make without failing to draw; x (B, 3, H, W) in [0, 255]."""
    b = x.shape[0]
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    sigma = u(b) * 1.5 * (u(b) < 0.7)
    x = gaussian_blur(x, sigma)
    x = (x - 128) * (0.9 + 0.2 * u(b, 1, 1, 1)) + 128             # contrast +-10 %
    x = x + (u(b, 3, 1, 1) * 2 - 1) * 10                          # per-channel shift +-10 levels
    x = x + torch.randn(x.shape, generator=g) * (u(b, 1, 1, 1) * 6)
    return x.clamp(0, 255)


def to_input(rgb_u8: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) uint8 or float [0, 255] -> (B, 3, H, W) in [-1, 1]."""
    return rgb_u8.permute(0, 3, 1, 2).float() / 127.5 - 1


def train(a):
    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    rgb, cls = load_frames(a.frames)
    n, h, w, _ = rgb.shape
    freq = np.bincount(cls.ravel(), minlength=N_CLASSES).astype(np.float64)
    weight = torch.tensor(np.where(freq > 0, 1 / np.sqrt(np.maximum(freq, 1) / freq.sum()), 0), dtype=torch.float32)
    weight = weight / weight[freq > 0].mean()
    print(f"{n} images {h}x{w}; class pixel fractions "
          + ", ".join(f"{CLASS_NAMES[c]} {freq[c] / freq.sum():.4f}" for c in range(N_CLASSES) if freq[c]))
    net = LayoutSeg(a.width, a.mid)
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=1e-4)
    warm = max(1, a.steps // 20)
    sched = torch.optim.lr_scheduler.LambdaLR(   # linear warm-up, cosine decay to 0
        opt, lambda s: min(1.0, (s + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(s, a.steps) / a.steps)))
    g = torch.Generator().manual_seed(a.seed)
    ch, cw = a.crop
    rgb_t, cls_t = torch.from_numpy(rgb), torch.from_numpy(cls).long()
    os.makedirs(a.out, exist_ok=True)
    t0 = time.time()
    for step in range(1, a.steps + 1):
        idx = torch.randint(0, n, (a.batch,), generator=g)
        ys = torch.randint(0, h - ch + 1, (a.batch,), generator=g)
        xs = torch.randint(0, w - cw + 1, (a.batch,), generator=g)
        x = torch.stack([rgb_t[i, y:y + ch, xx:xx + cw] for i, y, xx in zip(idx, ys, xs)]).permute(0, 3, 1, 2)
        t = torch.stack([cls_t[i, y:y + ch, xx:xx + cw] for i, y, xx in zip(idx, ys, xs)])
        x = degrade(x.float(), g) / 127.5 - 1
        loss = F.cross_entropy(net(x), t, weight=weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 50 == 0 or step == a.steps:
            print(f"seg step {step} loss {loss.item():.4f} ({(time.time() - t0) / step:.2f} s/step)", flush=True)
    save(net, os.path.join(a.out, "seg.safetensors"))
    print(f"wrote {a.out}/seg.safetensors")


def save(net: LayoutSeg, path: str):
    from safetensors.torch import save_file

    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, path,
              metadata={"arch": "layout-seg-v2", "dilations": ",".join(map(str, DILATIONS)),
                        "classes": ",".join(CLASS_NAMES)})


def load(path: str) -> LayoutSeg:
    from safetensors.torch import load_file

    sd = load_file(path)
    net = LayoutSeg(sd["stem.weight"].shape[0], sd["down.weight"].shape[0])
    net.load_state_dict(sd)
    return net.eval()


@torch.no_grad()
def classify(net: LayoutSeg, rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (H, W) class ids."""
    return net(to_input(torch.from_numpy(rgb)[None]))[0].argmax(0).numpy().astype(np.uint8)


def iou(preds, truths) -> dict:
    """Summed intersections / summed unions per class over the images."""
    acc = {}
    for p, t in zip(preds, truths):
        for c in np.union1d(np.unique(p), np.unique(t)):
            a = acc.setdefault(int(c), [0, 0])
            a[0] += int(((p == c) & (t == c)).sum())
            a[1] += int(((p == c) | (t == c)).sum())
    return {c: (i / u if u else math.nan) for c, (i, u) in acc.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description="layout segmenter (see the module docstring)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--frames", required=True, help="folder of `b2dr world` outputs (<CAM>.png + <CAM>_class.png)")
    t.add_argument("--out", required=True)
    t.add_argument("--steps", type=int, default=3000)
    t.add_argument("--batch", type=int, default=32)
    t.add_argument("--crop", type=lambda s: tuple(int(v) for v in s.split("x")), default=(64, 96))
    t.add_argument("--lr", type=float, default=3e-3)
    t.add_argument("--width", type=int, default=16, help="full-resolution channels")
    t.add_argument("--mid", type=int, default=32, help="half-resolution channels")
    t.add_argument("--threads", type=int, default=1)
    t.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.cmd == "train":
        train(a)


if __name__ == "__main__":
    main()
