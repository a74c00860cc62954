"""The renderer's own one-step latents of a dataset's frames, for a decoder trained on what it will decode
(``vae_train --decoder-only --decode-latents FILE``; docs/training.md, session 37).

The VAE's decoder is trained on the encoder's latents of true frames, but in the engine it only ever decodes the
denoiser's one-step sample, whose errors (a blur, a colour offset, a smeared edge) have a shape of their own. A
decoder shown those latents with the true frame as the target learns the image that such a latent most likely
came from. The encoder, and with it the latent space the denoiser works in and the previous-frame path, stay as
they are.

    python -m b2dr_ref.training.sampled_latents --package PKG --data DIR --out FILE [--prev truth|chain]
        [--latents RUN/latents.pt --vae-path PATH] [--guidance G] [--batch B] [--seed S] [--threads T]

Per sample (the engine's one-step UniPC of a package with ``steps`` 1, src/sampling/unipc.rs): x_T ~ N(0, 1); the
previous latent noised to the ControlNet's ``prev_noise_level``; the prediction at t = 999 with the references
(cond) and without (uncond), guided ``u + g (c - u)`` (renderer.md f; g = the package's ``ref_guidance``); its
x_0, plus the previous latent for an ``x0_base`` "prev" package. ``--prev truth``: the previous frame is the log's
(blurred, encoded: the eval-render protocol); ``chain`` (a --prev-chain export): the model's own one-step render
of the previous frame from the frame before it, through the engine's previous-frame path (the closed loop's input,
training/selfprev.py). The file holds the scaled latents (the sampler's units), the sample indices, the VAE
scaling factor and how they were made; vae_train checks the factor and the data size against its own.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Dict

import torch

from .loss import denoise
from .selfprev import ONE_STEP_T, one_step_x0, previous_frame_latent, x0_from

FORMAT = "b2dr-sampled-latents"


@torch.no_grad()
def one_step_with_refs(unet, controlnet, ctx, b: Dict, z_prev: torch.Tensor, x_T, eps_in, abar, prediction: str,
                       x0_base: str, guidance: float) -> torch.Tensor:
    """(N, C, h, w) scaled latents: the package's one-step sample of the batch ``b`` (Batcher.batch) from the
    previous latent ``z_prev``, with reference guidance ``guidance`` (1 = references only, no uncond pass)."""
    dev = x_T.device
    N = x_T.shape[0]
    a = abar.to(dev)
    level = int(controlnet.config.prev_noise_level)
    an = a[level]
    z = an.sqrt() * z_prev + (1 - an).sqrt() * eps_in
    n = torch.full((N,), level, dtype=torch.int64, device=dev)
    t = torch.full((N,), ONE_STEP_T, dtype=torch.int64, device=dev)
    on = torch.ones(N, dtype=torch.bool)
    c = denoise(unet, controlnet, x_T, t, ctx, b["masks"], z, n, b["ref_latents"], b["pe_cur"], b["pe_ref"],
                on).float()
    if guidance != 1.0:
        u = denoise(unet, controlnet, x_T, t, ctx, b["masks"], z, n, None, None, None, ~on).float()
        c = u + guidance * (c - u)
    x0 = x0_from(c, x_T, a[ONE_STEP_T], prediction)
    return x0 + z_prev if x0_base == "prev" else x0


def main(argv=None):
    from ..package import load_package
    from ..train import Batcher, latent_cache_key, make_noise_scheduler
    from .data import open_source
    from .single import save_checkpoint, set_threads

    p = argparse.ArgumentParser(prog="python -m b2dr_ref.training.sampled_latents")
    p.add_argument("--package", required=True, help="the model package whose denoiser samples (f16 weights widen)")
    p.add_argument("--data", required=True, help="the exported dataset (b2dr export-training)")
    p.add_argument("--out", required=True, help="the file to write (torch.save of a dict)")
    p.add_argument("--prev", choices=("truth", "chain"), default="truth",
                   help="the previous frame: the log's (truth) or the model's own render of it (chain; needs a "
                        "--prev-chain export)")
    p.add_argument("--guidance", type=float, default=None, help="reference guidance (default: the package's)")
    p.add_argument("--latents", default=None,
                   help="a training run's latents.pt of this data (skips encoding it); with --vae-path, the VAE "
                        "path that run was given (the file's key)")
    p.add_argument("--vae-path", default=None, help="see --latents")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--limit", type=int, default=0, help="only the first N samples (a smoke run)")
    args = p.parse_args(argv)
    if args.latents and not args.vae_path:
        raise SystemExit("--latents: give --vae-path, the VAE path of the run that wrote it (its key)")
    set_threads("cpu", args.threads)
    pkg = load_package(args.package)
    meta = pkg.meta
    if int(meta.get("steps", 0)) != 1:
        raise SystemExit(f"{args.package}: a {meta.get('steps')}-step package; this samples the one-step sampler")
    source = open_source(args.data, meta["render_size"])
    if list(source.render_size) != list(meta["render_size"]):
        raise SystemExit(f"data render size {source.render_size} != the package's {meta['render_size']}")
    if list(source.cameras) != list(meta["cameras"]):
        raise SystemExit(f"data cameras {source.cameras} != the package's {meta['cameras']} (context rows)")
    chain = args.prev == "chain"
    if chain and not getattr(source, "prev_chain", False):
        raise SystemExit(f"--prev chain: {args.data} is not an export with the previous frame's inputs "
                         "(b2dr export-training --prev-chain)")
    cn = pkg.controlnet
    sigma = float(cn.config.prev_blur_sigma)
    latents = (args.latents, latent_cache_key(args.data, args.vae_path, sigma)) if args.latents else None
    batcher = Batcher(source, pkg.vae, cn, torch.device("cpu"), cache=0, latents=latents, chain=chain)
    prediction = meta.get("prediction_type", "epsilon")
    x0_base = meta.get("x0_base", "none")
    g = float(meta.get("ref_guidance", 1.0) if args.guidance is None else args.guidance)
    abar = make_noise_scheduler().alphas_cumprod.to(torch.float32)
    gen = torch.Generator().manual_seed(args.seed)
    n = len(source) if not args.limit else min(args.limit, len(source))
    out, t0 = [], time.perf_counter()
    for a in range(0, n, args.batch):
        idx = list(range(a, min(n, a + args.batch)))
        b = batcher.batch(idx)
        ctx = pkg.context[b["cams"]]
        x_T = torch.randn(b["x0"].shape, generator=gen)
        eps_in = torch.randn(b["z_prev"].shape, generator=gen)
        z_prev = b["z_prev"]
        if chain:
            x_T2 = torch.randn(b["x0"].shape, generator=gen)
            eps2 = torch.randn(b["z_prev"].shape, generator=gen)
            with torch.no_grad():
                own = one_step_x0(pkg.unet, cn, ctx, b["masks_prev"], b["z_prev2"], x_T2, eps2, abar,
                                  int(cn.config.prev_noise_level), prediction, x0_base)
                z_prev = previous_frame_latent(pkg.vae, own, sigma)
        out.append(one_step_with_refs(pkg.unet, cn, ctx, b, z_prev, x_T, eps_in, abar, prediction, x0_base, g))
        done = idx[-1] + 1
        if (a // args.batch) % 20 == 0 or done == n:
            print(f"sampled {done} / {n} ({time.perf_counter() - t0:.0f} s)", flush=True)
    save_checkpoint(args.out, dict(format=FORMAT, index=torch.arange(n), latents=torch.cat(out),
                                   scaling_factor=float(pkg.vae.config.scaling_factor), samples=len(source),
                                   render_size=list(meta["render_size"]), package=os.path.abspath(args.package),
                                   prev=args.prev, guidance=g, seed=args.seed))
    print(f"wrote {args.out}: {n} latents", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
