"""The ceiling a VAE (or any image source) puts on eval-render's layout score (vehicle and lane-marking IoU), and
how that score reacts to small degradations of the ground truth.

    ~/.cache/b2dr-venv/bin/python tools/layout_ceiling.py --scenario builtin:town:0[,builtin:cross:0] --steps 50,150 \
        [--vae VAE_DIR ...] [--degrade noise:4 shift:6 blur:1 ...] [--vae-degraded] \
        [--strip EVAL/strips/single_lateral_0_m.png:1] \
        [--seg models/layout-seg/seg.safetensors] [--b2dr target/release/b2dr] [--camera CAM_FRONT] \
        [--size 112x200] [--json out.json] [--png DIR]

The ground truth (RGB and class image) comes from `b2dr world` at the given log steps (10 Hz; eval-render's
recorded frame k is step 5k: frames 10, 30 = steps 50, 150). The colour classifier is a port of
src/eval/fidelity/metrics.rs `PaletteClassifier`: every 32^3 colour bin takes the class most of its ground-truth
pixels have (ties: the lower class id), an empty bin takes the class of the nearest filled bin (Euclidean on the
bin centres; ties: the lower bin); fitted on the ground truth of this run, as eval-render fits it on its own.
`--seg` scores with a layout segmenter as well (python/b2dr_ref/layout_seg.py). IoU = summed intersections /
summed unions over the images. The "ground truth" row is the colour classifier's own ceiling (eval-render prints
the same number on the same frames); a VAE row is decode(encode(truth)) with the posterior mean, as the engine
encodes the previous frame and references (`--vae-degraded`: also decode(encode(degraded truth)) per --degrade,
e.g. blur:1, what a model whose previous frame is blurred before encoding starts from); a strip row is one column
of an eval-render strip (its first case). Several scenarios: every step of each, one classifier fitted on all.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))

from b2dr_ref import layout_seg  # noqa: E402
from b2dr_ref.layout_seg import CLASS_NAMES, class_ids, iou  # noqa: E402
from b2dr_ref.train import load_vae  # noqa: E402

LEVELS = 32
VEHICLE, LANE_MARKING = 11, 5


def bins(rgb: np.ndarray) -> np.ndarray:
    q = rgb.astype(np.int64) * LEVELS // 256
    return (q[..., 0] * LEVELS + q[..., 1]) * LEVELS + q[..., 2]


def bin_centres(b: np.ndarray) -> np.ndarray:
    c = lambda q: (q + 0.5) * 256.0 / LEVELS  # noqa: E731
    return np.stack([c(b // (LEVELS * LEVELS)), c((b // LEVELS) % LEVELS), c(b % LEVELS)], -1)


class PaletteClassifier:
    def __init__(self, samples):
        votes = np.zeros((LEVELS ** 3, 256), np.int64)
        for rgb, cls in samples:
            np.add.at(votes, (bins(rgb).ravel(), cls.ravel().astype(np.int64)), 1)
        filled = votes.sum(1) > 0
        if not filled.any():
            raise SystemExit("classifier: no ground-truth pixels")
        self.table = np.where(filled, votes.argmax(1), -1)   # argmax: ties go to the lower class id
        fb = np.nonzero(filled)[0]
        fc = bin_centres(fb)
        empty = np.nonzero(~filled)[0]
        for a in range(0, len(empty), 4096):                # nearest filled bin; ties: the lower bin
            e = empty[a:a + 4096]
            d = ((bin_centres(e)[:, None, :] - fc[None]) ** 2).sum(-1)
            self.table[e] = self.table[fb[d.argmin(1)]]

    def classify(self, rgb: np.ndarray) -> np.ndarray:
        return self.table[bins(rgb)].astype(np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def truth(b2dr: str, scenario: str, step: int, camera: str, size: str, tmp: str):
    out = os.path.join(tmp, f"s{step}")
    r = subprocess.run([b2dr, "world", "--scenario", scenario, "--step", str(step), "--size", size,
                        "--cameras", camera, "--out", out], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"b2dr world failed (step {step}):\n{r.stderr}")
    rgb = np.array(Image.open(os.path.join(out, f"{camera}.png")).convert("RGB"))
    cls = class_ids(np.array(Image.open(os.path.join(out, f"{camera}_class.png")).convert("RGB")))
    return rgb, cls


@torch.no_grad()
def roundtrip(vae, rgb: np.ndarray) -> np.ndarray:
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 127.5 - 1
    y = vae.decode(vae.encode(x).latent_dist.mean).sample.clamp(-1, 1)
    return ((y[0].permute(1, 2, 0) + 1) * 127.5).round().byte().numpy()


def degraded(rgb: np.ndarray, kind: str, amount: float, seed: int) -> np.ndarray:
    """The ground truth under one degradation: noise (i.i.d. Gaussian, sigma levels), shift (+levels on every
    channel) or blur (Gaussian, sigma pixels)."""
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()
    if kind == "noise":
        g = torch.Generator().manual_seed(seed)
        x = x + torch.randn(x.shape, generator=g) * amount
    elif kind == "shift":
        x = x + amount
    elif kind == "blur":
        x = layout_seg.gaussian_blur(x, torch.tensor([amount]))
    else:
        raise SystemExit(f"--degrade {kind}: noise, shift or blur")
    return x.clamp(0, 255).round()[0].permute(1, 2, 0).byte().numpy()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", required=True, help="comma-separated scenarios")
    ap.add_argument("--steps", required=True, help="comma-separated log steps (10 Hz)")
    ap.add_argument("--vae", nargs="*", default=[])
    ap.add_argument("--degrade", nargs="*", default=[],
                    help="KIND:AMOUNT rows of the degraded ground truth: noise:4 (sigma, levels), shift:6 (levels), "
                         "blur:1 (sigma, pixels)")
    ap.add_argument("--vae-degraded", action="store_true",
                    help="a row per VAE and --degrade: decode(encode(the degraded ground truth))")
    ap.add_argument("--strip", nargs="*", default=[],
                    help="PNG:COLUMN rows: column COLUMN (0 = the ground truth) of an eval-render strip "
                         "(strips/single_lateral_0_m.png, 4-px gaps), scored against the FIRST step only; its "
                         "frame must be that step (eval-render frame k = step 5k)")
    ap.add_argument("--seg", help="a layout segmenter (python -m b2dr_ref.layout_seg train): score with it too")
    ap.add_argument("--b2dr", default=os.path.join(os.path.dirname(__file__), "..", "target", "release", "b2dr"))
    ap.add_argument("--camera", default="CAM_FRONT")
    ap.add_argument("--size", default="112x200")
    ap.add_argument("--json")
    ap.add_argument("--png", help="folder for side-by-side strips (truth | each VAE)")
    a = ap.parse_args(argv)
    steps = [int(s) for s in a.steps.split(",") if s]
    torch.set_num_threads(1)
    scenarios = [s for s in a.scenario.split(",") if s]
    cases = [(sc, s) for sc in scenarios for s in steps]
    with tempfile.TemporaryDirectory() as tmp:
        gts = [truth(a.b2dr, sc, s, a.camera, a.size, tmp) for sc, s in cases]
    scorers = {"colour": PaletteClassifier(gts).classify}
    if a.seg:
        net = layout_seg.load(a.seg)
        scorers["segmenter"] = lambda rgb: layout_seg.classify(net, rgb)
    rows = {"ground truth": [g[0] for g in gts]}
    for d in a.degrade:
        kind, amount = d.split(":")
        rows[f"ground truth, {kind} {amount}"] = [degraded(g[0], kind, float(amount), k) for k, g in enumerate(gts)]
    for v in a.vae:
        vae = load_vae(v)
        rows[f"VAE {v}"] = [roundtrip(vae, g[0]) for g in gts]
        for d in a.degrade if a.vae_degraded else []:
            kind, amount = d.split(":")
            rows[f"VAE {v} of {kind} {amount}"] = [roundtrip(vae, degraded(g[0], kind, float(amount), k))
                                                    for k, g in enumerate(gts)]
    for st in a.strip:
        path, col = st.rsplit(":", 1)
        im = np.array(Image.open(path).convert("RGB"))
        h, w = gts[0][0].shape[:2]
        c0 = int(col) * (w + 4)
        if im.shape[0] < h or im.shape[1] < c0 + w:
            raise SystemExit(f"--strip {st}: {im.shape[1]} x {im.shape[0]} px has no column {col} of {w} x {h}")
        rows[f"strip {st}"] = [im[:h, c0:c0 + w]]
    res = {}
    print(f"{a.scenario} steps {steps} {a.camera} {a.size} ({len(gts)} images)")
    head = "".join(f" {n[:5] + ' veh':>10} {n[:5] + ' mark':>10}" for n in scorers)
    print(f"{'images':<56} {'PSNR dB':>8}{head}")
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for name, imgs in rows.items():
        truths = [g[1] for g in gts][:len(imgs)]
        p = float(np.mean([psnr(i, g[0]) for i, g in zip(imgs, gts)]))
        res[name] = {"psnr_db": p}
        line = f"{name[-56:]:<56} {p:8.2f}"
        for sn, sc in scorers.items():
            r = iou([sc(i) for i in imgs], truths)
            res[name][sn] = {CLASS_NAMES[c]: v for c, v in r.items()}
            line += f" {f(r.get(VEHICLE)):>10} {f(r.get(LANE_MARKING)):>10}"
        print(line)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)
    if a.png:
        os.makedirs(a.png, exist_ok=True)
        full = [v for v in rows.values() if len(v) == len(cases)]
        for k, (sc, s) in enumerate(cases):
            name = f"step_{s}.png" if len(scenarios) == 1 else f"{sc.replace(':', '_')}_step_{s}.png"
            Image.fromarray(np.concatenate([imgs[k] for imgs in full], 1)).save(os.path.join(a.png, name))


if __name__ == "__main__":
    main()
