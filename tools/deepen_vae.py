"""Grow a trained AutoencoderKL one resnet deeper per level, keeping its function (docs/training.md, session 25).

    ~/.cache/b2dr-venv/bin/python tools/deepen_vae.py --vae models/b2dr-z16-vae --out DEEP_VAE [--layers 2]

Every tensor of the source VAE keeps its name and value; the resnets a larger ``layers_per_block`` adds (encoder
``down_blocks.i.resnets.j`` and decoder ``up_blocks.i.resnets.j+1`` for j >= the source's layers_per_block) are
initialised by diffusers and then have their ``conv2`` weight and bias set to zero. A ResnetBlock2D whose input and
output widths agree has no shortcut conv and returns ``x + conv2(...)``, so a zeroed conv2 makes it the identity
(the same trick as ControlNet's zero convolutions): the deeper VAE reproduces the source exactly (checked here on a
random image, encode mean and decode) and training continues from there (``vae_train --config nano-z16-g4-d2
--init-from DEEP_VAE``). The added blocks sit after the level's existing resnets, before its down / up sampler.
"""

from __future__ import annotations

import argparse
import sys

import torch


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--vae", required=True, help="source diffusers AutoencoderKL folder")
    p.add_argument("--out", required=True, help="where to write the deeper VAE folder")
    p.add_argument("--layers", type=int, default=2, help="layers_per_block of the result (default 2)")
    args = p.parse_args(argv)
    from diffusers import AutoencoderKL

    src = AutoencoderKL.from_pretrained(args.vae, torch_dtype=torch.float32).eval()
    old = src.config.layers_per_block
    if args.layers <= old:
        print(f"--layers {args.layers}: the source already has layers_per_block {old}", file=sys.stderr)
        return 2
    cfg = {k: v for k, v in dict(src.config).items() if not k.startswith("_")}
    cfg["layers_per_block"] = args.layers
    torch.manual_seed(0)
    dst = AutoencoderKL(**cfg).eval()
    sd = dst.state_dict()
    src_sd = src.state_dict()
    missing = [k for k in src_sd if k not in sd]
    if missing:
        print(f"source tensors without a place in the deeper VAE: {missing[:5]}", file=sys.stderr)
        return 1
    for k, v in src_sd.items():
        if sd[k].shape != v.shape:
            print(f"{k}: shape {tuple(v.shape)} vs {tuple(sd[k].shape)}", file=sys.stderr)
            return 1
        sd[k] = v.clone()
    added = set()
    for k in sd:
        if k in src_sd:
            continue
        parts = k.split(".")
        # encoder.down_blocks.i.resnets.j.* / decoder.up_blocks.i.resnets.j.*
        if "resnets" not in parts:
            print(f"unexpected new tensor {k}", file=sys.stderr)
            return 1
        block = ".".join(parts[: parts.index("resnets") + 2])
        added.add(block)
        if parts[-2] == "conv2":
            sd[k] = torch.zeros_like(sd[k])
        if parts[-2] == "conv_shortcut":
            print(f"{k}: an added resnet changes width; it cannot start as the identity", file=sys.stderr)
            return 1
    dst.load_state_dict(sd)
    x = torch.rand(2, 3, 64, 96) * 2 - 1
    with torch.no_grad():
        z0, z1 = src.encode(x).latent_dist.mean, dst.encode(x).latent_dist.mean
        y0, y1 = src.decode(z0).sample, dst.decode(z0).sample
    dz, dy = (z0 - z1).abs().max().item(), (y0 - y1).abs().max().item()
    if dz > 1e-5 or dy > 1e-5:
        print(f"the deeper VAE differs from the source: latent {dz:.2e}, image {dy:.2e}", file=sys.stderr)
        return 1
    dst.save_pretrained(args.out, safe_serialization=True)
    print(f"{args.out}: layers_per_block {old} -> {args.layers}, {len(added)} resnets added as identities "
          f"({sum(v.numel() for v in src_sd.values())} -> {sum(v.numel() for v in sd.values())} parameters); "
          f"max difference to the source: latent {dz:.1e}, image {dy:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
