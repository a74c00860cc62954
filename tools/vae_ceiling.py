"""The ceiling a VAE puts on a renderer (docs/training.md "Designs"): PSNR of decode(encode(target)) over the
whole image and inside the pixels of the structures a renderer must draw, on an export of held-out frames.

    ~/.cache/b2dr-venv/bin/python tools/vae_ceiling.py --data HELD_OUT_EXPORT --vae VAE_DIR [VAE_DIR ...] \
        [--samples 48] [--json out.json]

Regions (the export's layout masks, docs/training_data.md): `vehicle` = mask channels car .. bicycle (every
object that moves), `lane divider` = the lane_divider channel (the painted dividers' projected polylines, a few
pixels wide: the markings and the asphalt right beside them), `crosswalk`. PSNR inside a region = 10 log10(255^2
/ MSE over the region's pixels, RGB), pooled over all images. The encode uses the posterior mean, as the trainer
and the engine do; the first --samples camera samples of the export in index order.

Beside the ceiling, how hard the latent is for the diffusion model that must produce it ("diffusability"): the
latents' lag-1 spatial autocorrelation (each channel centred over the samples, neighbours along x and along y)
and the share of their variance a 2 x 2 average pool keeps. A latent close to spatially white (low
figures) carries its content cell by cell: the denoiser cannot tell it from the noise it removes, and a sampler's
errors decode as blotches (docs/training.md, session 22).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))

from b2dr_ref.controlnet import MASK_CHANNELS  # noqa: E402
from b2dr_ref.train import DatasetSource, load_vae  # noqa: E402

REGIONS = {
    "vehicle": list(range(0, 8)),
    "lane divider": [MASK_CHANNELS.index("lane_divider")],
    "crosswalk": [MASK_CHANNELS.index("crosswalk")],
}


def psnr_of(se: float, n: int):
    if n == 0:
        return None
    mse = se / n
    return math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def latent_smoothness(z: torch.Tensor) -> dict:
    """z (N, C, h, w) latents -> lag-1 spatial autocorrelation along x, along y (each channel centred over the
    whole set; correlations pooled over channels) and the share of the variance a 2 x 2 average pool keeps (the
    even-sized top-left part)."""
    z = z.double()
    z = z - z.mean((0, 2, 3), keepdim=True)
    var = (z ** 2).mean()
    h, w = z.shape[-2] // 2 * 2, z.shape[-1] // 2 * 2
    e = z[..., :h, :w]
    pooled = torch.nn.functional.avg_pool2d(e, 2)
    return {"lag1_x": float((z[..., 1:] * z[..., :-1]).mean() / var),
            "lag1_y": float((z[..., 1:, :] * z[..., :-1, :]).mean() / var),
            "pool2_kept": float((pooled ** 2).mean() / (e ** 2).mean())}


@torch.no_grad()
def ceiling(vae, src, n: int, batch: int = 8):
    acc = {k: [0.0, 0] for k in ["image", *REGIONS]}
    zs = []
    idx = list(range(min(n, len(src))))
    for a in range(0, len(idx), batch):
        ss = [src[i] for i in idx[a:a + batch]]
        x = torch.from_numpy(np.stack([s.target for s in ss])).float() / 255.0
        z = vae.encode(2 * x - 1).latent_dist.mean
        zs.append(z)
        y = ((vae.decode(z).sample.clamp(-1, 1) + 1) * 127.5).round()
        err = ((y - x * 255.0) ** 2).sum(1).numpy()            # (B, H, W), summed over RGB
        acc["image"][0] += float(err.sum())
        acc["image"][1] += err.size * 3
        m = np.stack([s.masks for s in ss])                   # (B, 15, H, W)
        for k, ch in REGIONS.items():
            sel = m[:, ch].max(1) > 0
            acc[k][0] += float(err[sel].sum())
            acc[k][1] += int(sel.sum()) * 3
    return {k: psnr_of(*v) for k, v in acc.items()} | {"pixels": {k: v[1] // 3 for k, v in acc.items()},
                                                      "samples": len(idx),
                                                      "latent": latent_smoothness(torch.cat(zs))}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--vae", nargs="+", required=True)
    p.add_argument("--samples", type=int, default=48)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    src = DatasetSource(a.data)
    rows = {}
    print("| VAE | latent channels | image dB | vehicle dB | lane divider dB | crosswalk dB | latent lag-1 corr x / y "
          "| variance kept by 2x2 pool |\n|---|---|---|---|---|---|---|---|")
    for v in a.vae:
        vae = load_vae(v).eval()
        r = ceiling(vae, src, a.samples)
        r["latent_channels"] = int(vae.config.latent_channels)
        rows[v] = r
        f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        print(f"| {v} | {r['latent_channels']} | {f(r['image'])} | {f(r['vehicle'])} | {f(r['lane divider'])} | "
              f"{f(r['crosswalk'])} | {r['latent']['lag1_x']:.3f} / {r['latent']['lag1_y']:.3f} | "
              f"{r['latent']['pool2_kept']:.3f} |", flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return rows


if __name__ == "__main__":
    main()
