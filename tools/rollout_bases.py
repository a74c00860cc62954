"""A rollout of a warping package on one logged scenario, in PyTorch, with five previous-frame bases
(docs/training.md, session 42): the model's own previous frame (the engine's `prev_source` "previous") with or
without its vehicle ghosts removed, and a retrieved reference instead (`prev_source` "reference").

The engine warps the previous frame to the current pose as if everything were flat ground (b2dr.json
``prev_warp_max_depth``; b2dr_ref/warp.py). This script runs the one-step sampler over N consecutive 2 Hz frames
of an export (CAM_FRONT, one ego offset), with the package's references and reference guidance, the same noise
per frame in every variant; only the previous-frame input differs:

- ``warp``: the model's own render of the frame before (decode, clamp, 8-bit, warp, blur, encode:
  training/selfprev.py's path), as the engine's loop carries it (frame 1: the logged previous frame);
- ``ghosts inpainted``: the same, where the current pixel is not a vehicle but its warp source is a vehicle of
  the previous frame's layout, the warped pixel replaced by the Gaussian-weighted mean of the non-ghost pixels
  around it (normalised convolution, ``--sigma``) before the blur;
- ``ghosts kept``: those pixels keep the previous image's own (unwarped) pixel;
- ``rear ref warped`` / ``front ref warped``: nothing carried; every frame starts from the sample's rear / front
  reference (a logged image) warped from its pose to the current one (the engine's ``prev_source`` "reference"
  picks the rear one for CAM_FRONT: src/render/warp.rs reference_base_choice).

The export's references are drawn from the training intervals (2-15 m away, mostly 10-15 m), farther than the
engine's nearest-image retrieval: a harder case for the reference bases. Prints per-frame PSNR against the
logged (or displaced) ground truth and the means (all / vehicle / lane-marking pixels) over frames 2-10 and the
last ten; ``--png`` writes a strip (rows: truth, then each variant; columns: frames 1, 2, 5, 10, 20, 30, N).

    b2dr export-training --scenario builtin:town:100:60 --cameras CAM_FRONT --offsets "0,0,0;0,2,0" \
        --samples-per-scenario 400 --prev-chain --size 112x200 --seed 0 --out DIR
    python tools/rollout_bases.py --package models/b2dr-res-z16-warp --data DIR [--offset 0,2,0] [--frames 36]
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))
from b2dr_ref.controlnet import MASK_CHANNELS  # noqa: E402
from b2dr_ref.frame import gaussian_blur  # noqa: E402
from b2dr_ref.warp import ground_warp_grid, warp_image  # noqa: E402
from measure_warp_base import at_source, inpaint  # noqa: E402  (this folder, on sys.path as the script's own)

VEHICLES = ["car", "truck", "bus", "trailer", "construction_vehicle"]
MARKINGS = ["crosswalk", "lane_divider"]


def channel_any(masks, names):
    """(15, H, W) {0,1} layout -> (H, W) bool: any of the named channels."""
    return np.asarray(masks)[[MASK_CHANNELS.index(n) for n in names]].max(0) > 0


def psnr(a, b, m=None):
    d = ((a - b) ** 2).mean(0)
    if m is not None:
        if m.sum() < 1:
            return float("nan")
        d = d[torch.from_numpy(m)]
    return float(10 * torch.log10(1 / d.mean()))


def main():
    from b2dr_ref.package import load_package
    from b2dr_ref.train import Batcher, make_noise_scheduler
    from b2dr_ref.training.data import open_source
    from b2dr_ref.training.sampled_latents import one_step_with_refs

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--package", required=True)
    p.add_argument("--data", required=True, help="an export of one scenario, CAM_FRONT, offset 0, --prev-chain")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--start-step", type=int, default=10, help="the log step of the first frame")
    p.add_argument("--sigma", type=float, default=2.0, help="the inpainting's Gaussian sigma, pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--offset", default="0,0,0", help="the export's ego offset of the rollout (dx,dy,dyaw_deg)")
    p.add_argument("--png", default=None)
    a = p.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    pkg = load_package(a.package)
    meta, cn, vae = pkg.meta, pkg.controlnet, pkg.vae
    depth, sigma = float(cn.config.prev_warp_max_depth), float(cn.config.prev_blur_sigma)
    if not depth > 0:
        raise SystemExit(f"{a.package}: prev_warp_max_depth is 0 (a package that does not warp)")
    src = open_source(a.data, meta["render_size"])
    if list(src.cameras) != ["CAM_FRONT"]:
        raise SystemExit(f"{a.data}: cameras {src.cameras}; export CAM_FRONT only")
    rows = src.ds.samples
    if len({r["scenario"] for r in rows}) != 1:
        raise SystemExit(f"{a.data}: holds several scenarios; export one")
    want = [float(x) for x in a.offset.split(",")]
    by_step = {int(r["step"]): i for i, r in enumerate(rows) if np.allclose(r["offset"], want)}
    steps = [a.start_step + 5 * k for k in range(a.frames)]
    missing = [s for s in steps if s not in by_step]
    if missing:
        raise SystemExit(f"{a.data}: no logged sample at steps {missing[:5]}... (export more samples or fewer frames)")
    cam = list(meta["cameras"]).index("CAM_FRONT")
    ctx = pkg.context[[cam]]
    batcher = Batcher(src, vae, cn, torch.device("cpu"), cache=0)
    abar = make_noise_scheduler().alphas_cumprod.to(torch.float32)
    pred, base = meta.get("prediction_type", "epsilon"), meta.get("x0_base", "none")
    g = float(meta.get("ref_guidance", 1.0))
    sf = vae.config.scaling_factor
    variants = ["warp", "ghosts inpainted", "ghosts kept", "rear ref warped", "front ref warped"]
    own = {v: None for v in variants}            # the previous frame's own render, (1, 3, H, W) in [0, 1]
    res = {v: [] for v in variants}
    shots = {v: {} for v in variants + ["truth"]}
    show = {1, 2, 5, 10, 20, 30, a.frames}
    for f, step in enumerate(steps, 1):
        i = by_step[step]
        s = src[i]
        b = batcher.batch([i])
        gen = torch.Generator().manual_seed(a.seed * 100003 + f)
        x_T = torch.randn(b["x0"].shape, generator=gen)
        eps_in = torch.randn(b["z_prev"].shape, generator=gen)
        tgt = torch.from_numpy(s.target).float() / 255
        cur_v, cur_m = channel_any(s.masks, VEHICLES), channel_any(s.masks, MARKINGS)
        grid = ground_warp_grid(s.k, s.cam2ego, s.ego2global, s.prev_ego2global, tgt.shape[1:], depth)
        hole = at_source(grid, channel_any(s.prev_masks, VEHICLES)) & ~cur_v
        shots["truth"][f] = tgt
        for v in variants:
            prev = own[v] if own[v] is not None else torch.from_numpy(s.prev).float()[None] / 255
            if v.endswith("ref warped"):
                j = 1 if v.startswith("rear") else 0
                prev = torch.from_numpy(s.refs[j]).float()[None] / 255
                rg = ground_warp_grid(s.k, s.cam2ego, s.ego2global, s.ref_ego2global[j], tgt.shape[1:], depth)
                w = warp_image(prev, torch.from_numpy(rg)[None])
            else:
                w = warp_image(prev, torch.from_numpy(grid)[None])
            if v == "ghosts inpainted":
                w = inpaint(w, hole, a.sigma)
            elif v == "ghosts kept":
                w = torch.where(torch.from_numpy(hole)[None, None], prev, w)
            with torch.no_grad():
                z_prev = vae.encode(2.0 * gaussian_blur(w, sigma) - 1.0).latent_dist.mean * sf
                x0 = one_step_with_refs(pkg.unet, cn, ctx, b, z_prev, x_T, eps_in, abar, pred, base, g)
                img = vae.decode(x0 / sf).sample.float()
            img = torch.round((img.clamp(-1, 1) + 1) * 127.5) / 255.0
            own[v] = img
            r = (psnr(tgt, img[0]), psnr(tgt, img[0], cur_v), psnr(tgt, img[0], cur_m), int(hole.sum()))
            res[v].append(r)
            if f in show:
                shots[v][f] = img[0]
        print(f"frame {f:2d} (step {step}): " + "; ".join(f"{v} {res[v][-1][0]:.2f}" for v in variants) +
              f"  (ghost px {int(hole.sum())})", flush=True)
    print(f"\n| variant | frames 2-10 all / vehicle / marking dB | frames {a.frames - 9}-{a.frames} all / vehicle / "
          "marking dB | fall (all) |")
    print("|---|---|---|---|")
    for v in variants:
        r = np.array([x[:3] for x in res[v]])
        e, l_ = np.nanmean(r[1:10], 0), np.nanmean(r[-10:], 0)
        print(f"| {v} | " + " / ".join(f"{x:.2f}" for x in e) + " | " + " / ".join(f"{x:.2f}" for x in l_) +
              f" | {l_[0] - e[0]:+.2f} |")
    if a.png:
        from PIL import Image
        cols = sorted(shots["truth"].keys() & show)
        grid_rows = [torch.cat([shots[k][f] for f in cols], -1) for k in ["truth"] + variants]
        im = (torch.cat(grid_rows, -2).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        Image.fromarray(im).save(a.png)
        print(f"wrote {a.png}: rows truth, {', '.join(variants)}; columns frames {cols}")


if __name__ == "__main__":
    main()
