"""VAE stage of the built-in model (docs/training.md): a small AutoencoderKL (4 blocks = factor 8, 4 latent channels
in b2dr-nano) trained on the dataset's target images with an L1 reconstruction loss + a small KL term (LDM style);
`--recon-loss l2` uses the squared error instead (L1 erases thin lane markings: docs/training.md "The loss, not
the width, erased the markings").

    python -m b2dr_ref.vae_train --data DIR --out VAE_RUN [--config nano] [--steps N] [--batch B] [--device cpu|cuda]
                                 [--crop HxW] [--init-from VAE_DIR] [--object-weight W] [--marking-weight W]
                                 [--recon-loss l1|l2] [--grad-weight W] [--se-weight W] [--resume]

Loss per step (LDM's autoencoder without the perceptual / GAN terms): the sums over pixels and latent elements
per image, averaged over the batch, divided by 3 H W so the figure reads as a per-pixel L1:
``(sum |x - D(z)| + kl_weight * KL(q(z|x) || N(0, 1))) / (3 H W)``, z sampled from q, kl_weight 1e-6.
At the end (and at every checkpoint) VAE_RUN/vae/ is written (diffusers folder) with ``scaling_factor`` =
1 / std of the latent means over up to 256 training images spread over the data (SD's 0.18215 was found this way); the diffusion stage
reads that folder with ``--vae VAE_RUN/vae``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

from . import nano
from .training.common import CsvLog
from .training.data import open_source
from .training.loss import MARKING_CHANNELS, OBJECT_CHANNELS
from .training.single import CKPT, add_common, load_vae, lr_lambda, save_checkpoint, set_threads


def build_vae(cfg, seed: int = 0):
    from diffusers import AutoencoderKL

    torch.manual_seed(seed)
    return AutoencoderKL(**cfg["vae"])


def images(source, idx, device) -> torch.Tensor:
    x = np.stack([source[i].target for i in idx])
    return torch.from_numpy(x).float().div(255.0).mul(2.0).sub(1.0).to(device)


def object_masks(source, idx, device, channels=OBJECT_CHANNELS) -> torch.Tensor:
    """(B, 1, H, W) float {0,1}: pixels covered by any of the mask ``channels`` (default the objects: vehicles,
    pedestrians, two-wheelers)."""
    m = np.stack([source[i].masks[channels].max(0) for i in idx])
    return torch.from_numpy(m).float()[:, None].to(device)


def pixel_weights(source, idx, device, object_weight: float, marking_weight: float):
    """(B, 1, H, W) L1 weights 1 + object_weight [object pixel] + marking_weight [marking pixel], or None."""
    w = None
    if object_weight > 0:
        w = 1.0 + object_weight * object_masks(source, idx, device)
    if marking_weight > 0:
        m = marking_weight * object_masks(source, idx, device, MARKING_CHANNELS)
        w = 1.0 + m if w is None else w + m
    return w


def parse_crop(text: str):
    h, w = (int(v) for v in text.lower().split("x"))
    if h % 8 or w % 8 or h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"--crop {text}: HxW, multiples of 8")
    return h, w


def random_crop(x: torch.Tensor, hw, gen: torch.Generator, *more: torch.Tensor):
    """One random HxW window (offsets on the 8-pixel grid) of the whole batch; the VAE is convolutional, so
    training on crops is LDM's usual speed-up. Tensors in ``more`` (same H, W) get the same window and are
    returned after x as a tuple."""
    h, w = hw
    H, W = x.shape[-2:]
    if h > H or w > W:
        raise ValueError(f"crop {h}x{w} larger than the images {H}x{W}")
    y0 = 8 * int(torch.randint(0, (H - h) // 8 + 1, (1,), generator=gen))
    x0 = 8 * int(torch.randint(0, (W - w) // 8 + 1, (1,), generator=gen))
    crops = tuple(t[..., y0:y0 + h, x0:x0 + w] for t in (x,) + more)
    return crops if more else crops[0]


def grad_l1(rec: torch.Tensor, x: torch.Tensor, weight: torch.Tensor = None) -> torch.Tensor:
    """Per-sample sum of |d rec - d x| over horizontal and vertical neighbour differences (the gradient-difference
    term of Mathieu et al. 2016): it pays for an edge's missing contrast, which a per-pixel loss does not see as
    such. Measured on the gate frames (docs/training.md): with L1 it did not bring the centre line back in 1,500
    steps; `--recon-loss l2` did.
    rec, x: (B, 3, H, W); weight: (B, 1, H, W) or None, the larger of the two neighbours' weights."""
    dx = ((rec[..., :, 1:] - rec[..., :, :-1]) - (x[..., :, 1:] - x[..., :, :-1])).abs()
    dy = ((rec[..., 1:, :] - rec[..., :-1, :]) - (x[..., 1:, :] - x[..., :-1, :])).abs()
    if weight is not None:
        dx = dx * torch.maximum(weight[..., :, 1:], weight[..., :, :-1])
        dy = dy * torch.maximum(weight[..., 1:, :], weight[..., :-1, :])
    return dx.flatten(1).sum(1) + dy.flatten(1).sum(1)


def half_size(t: torch.Tensor, hw) -> torch.Tensor:
    """t (B, C, H, W) resized to hw with an antialiased bilinear filter (the same filter for images and latents)."""
    return torch.nn.functional.interpolate(t, size=hw, mode="bilinear", antialias=True, align_corners=False)


def scale_equivariance(vae, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Per-sample mean squared error per pixel value between D(down(z)) and down(x), down = half size
    (Skorokhodov et al. 2025, "Improving the Diffusability of Autoencoders"; EQ-VAE, Kouzelis et al. 2025): a
    latent that decodes correctly at half size carries no content in its finest band that the decoder needs, so
    it is smoother and easier to denoise. z: (B, C, h, w) -> (h // 2, w // 2); x: (B, 3, H, W) -> (f (h // 2),
    f (w // 2)) pixels, f = W / w the decoder's factor: the same fraction of each side as the latent keeps."""
    h, w = z.shape[-2] // 2, z.shape[-1] // 2
    f = x.shape[-1] // z.shape[-1]
    small = vae.decode(half_size(z, (h, w))).sample
    return (small - half_size(x, (f * h, f * w))).square().flatten(1).mean(1)


def vae_loss(vae, x, gen: torch.Generator, kl_weight: float, weight: torch.Tensor = None, grad_weight: float = 0.0,
             recon: str = "l1", se_weight: float = 0.0, decoder_only: bool = False, z_given: torch.Tensor = None,
             given: torch.Tensor = None):
    """(loss, plain per-pixel L1, KL). ``weight`` (B, 1, H, W) >= 1 scales the L1 per pixel (--object-weight);
    ``grad_weight`` adds that multiple of grad_l1 (--grad-weight); the loss is still divided by 3 H W, the logged
    L1 is the unweighted one. ``recon`` "l2": squared error per pixel instead of the absolute one (--recon-loss;
    the logged L1 stays the absolute error). ``se_weight`` adds that multiple of the half-size decode's squared
    error per pixel value of the half-size image (scale_equivariance; --se-weight). ``decoder_only``: the encoder is
    fixed (no gradient reaches it) and the decoder is given the posterior mean, the latent the diffusion stage is
    trained on and samples towards (--decoder-only); the KL term is then a constant, reported, not added.
    ``z_given`` (B, C, h, w), unscaled, with ``given`` (B,) bool (--decode-latents, decoder-only): the rows of
    ``given`` decode ``z_given`` (the renderer's own sampled latent of that frame) instead of the posterior mean."""
    if decoder_only:
        with torch.no_grad():
            post = vae.encode(x).latent_dist
        z = post.mean
        if z_given is not None:
            z = torch.where(given.to(z.device).reshape(-1, 1, 1, 1), z_given.to(z.device, z.dtype), z)
    elif z_given is not None:
        raise ValueError("z_given: only with decoder_only (the encoder's latent space must stay fixed)")
    else:
        post = vae.encode(x).latent_dist
        eps = torch.randn(post.mean.shape, generator=gen).to(x.device)
        z = post.mean + post.std * eps
    rec = vae.decode(z).sample
    per_pixel = float(np.prod(x.shape[1:]))
    err = (rec - x).abs()
    l1 = err.flatten(1).sum(1).mean()
    if recon == "l2":
        err = err.square()
    elif recon != "l1":
        raise ValueError(f"recon loss {recon!r}: l1 or l2")
    wl1 = err.flatten(1).sum(1).mean() if weight is None else (err * weight).flatten(1).sum(1).mean()
    if grad_weight:
        wl1 = wl1 + grad_weight * grad_l1(rec, x, weight).mean()
    kl = post.kl().mean()
    loss = (wl1 + (0.0 if decoder_only else kl_weight) * kl) / per_pixel
    if se_weight:
        loss = loss + se_weight * scale_equivariance(vae, z, x).mean()
    return loss, (l1 / per_pixel).detach(), kl.detach()


def spread(source, n: int):
    """Up to n sample indices evenly spread over the source (the export is ordered by scenario: the first n would
    all come from one or two scenarios and palettes)."""
    m = len(source)
    return sorted(set(np.linspace(0, m - 1, min(n, m)).round().astype(int).tolist()))


@torch.no_grad()
def measure_scaling(vae, source, device, n: int = 256, batch: int = 16) -> float:
    zs = []
    idx = spread(source, n)
    for i in range(0, len(idx), batch):
        zs.append(vae.encode(images(source, idx[i:i + batch], device)).latent_dist.mean.float().cpu())
    std = torch.cat(zs).std().item()
    return 1.0 / max(std, 1e-6)


@torch.no_grad()
def latent_channel_stats(vae, source, device, n: int = 256, batch: int = 16):
    """Per-channel mean and std of the posterior means (no scaling) over up to n images spread over the source: (C,), (C,) float64."""
    zs = []
    idx = spread(source, n)
    for i in range(0, len(idx), batch):
        zs.append(vae.encode(images(source, idx[i:i + batch], device)).latent_dist.mean.double().cpu())
    z = torch.cat(zs).transpose(0, 1).reshape(vae.config.latent_channels, -1)
    return z.mean(1), z.std(1)


@torch.no_grad()
def centre_latents(vae, source, device, n: int = 256):
    """Re-parameterise the VAE so that its latent means are zero-mean, unit-std per channel on the data, without
    changing what it computes: the encoder's quant_conv (1x1) maps to (mean - mu) / sigma (its log-variance half
    shifted by -2 log sigma), the decoder's post_quant_conv (1x1) takes sigma z + mu. Same architecture and
    tensor names, so the engine loads it unchanged; decode(encode(x)) is the same function.

    Why: a latent channel with a large mean (b2dr-nano's VAE had channel means up to 2.5 latent stds) leaks
    into x_T through sqrt(abar_999) = 0.069 during training, where the model learns to read the offset from
    the noise; sampling starts from zero-mean noise, so the model's samples lacked the offsets (washed-out
    blobs, docs/training.md). Returns (mu, sigma) that were folded in."""
    if not (vae.config.use_quant_conv and vae.config.use_post_quant_conv):
        raise ValueError("centre_latents needs quant_conv and post_quant_conv (use_quant_conv / use_post_quant_conv)")
    mu, sigma = latent_channel_stats(vae, source, device, n)
    c = vae.config.latent_channels
    q, pq = vae.quant_conv, vae.post_quant_conv
    m64, s64 = mu.to(torch.float64), sigma.clamp_min(1e-6).to(torch.float64)
    w = q.weight.double()
    b = q.bias.double()
    w[:c] /= s64[:, None, None, None]
    b[:c] = (b[:c] - m64) / s64
    b[c:] -= 2 * torch.log(s64)
    q.weight.copy_(w.to(q.weight.dtype))
    q.bias.copy_(b.to(q.bias.dtype))
    w = pq.weight.double()
    pq.bias.copy_((pq.bias.double() + (w[:, :, 0, 0] * m64[None]).sum(1)).to(pq.bias.dtype))
    pq.weight.copy_((w * s64[None, :, None, None]).to(pq.weight.dtype))
    return mu, sigma


def save_vae(vae, source, out: str, device, centre: bool = True, scaling_factor: float = None):
    """Write OUT/vae. centre: a centred copy (centre_latents) with its scaling factor measured on the data;
    scaling_factor given (a --decoder-only run): no centring and that factor, so the latent space is exactly the
    initial VAE's and a denoiser trained on its latents decodes through this VAE unchanged."""
    was = vae.training
    vae.eval()
    if centre and scaling_factor is None:
        # a copy is centred and saved; the training weights stay as they are (resume is unaffected)
        import copy

        vae = copy.deepcopy(vae)
        centre_latents(vae, source, device)
    sf = measure_scaling(vae, source, device) if scaling_factor is None else scaling_factor
    vae.register_to_config(scaling_factor=float(sf))
    vae.save_pretrained(os.path.join(out, "vae"), safe_serialization=True)
    vae.train(was)
    return sf


def centre_command(argv):
    """python -m b2dr_ref.vae_train centre --vae IN_DIR --data DATA --out OUT_DIR: centre an existing VAE folder."""
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.vae_train centre")
    p.add_argument("--vae", required=True, help="a diffusers AutoencoderKL folder (e.g. MODEL/vae)")
    p.add_argument("--data", required=True, help="the exported dataset (256 targets spread over it are measured)")
    p.add_argument("--out", required=True, help="the centred VAE folder to write")
    a = p.parse_args(argv)
    vae = load_vae(a.vae)
    source = open_source(a.data, None)
    mu, sigma = centre_latents(vae, source, "cpu")
    sf = measure_scaling(vae, source, "cpu")
    vae.register_to_config(scaling_factor=float(sf))
    vae.save_pretrained(a.out, safe_serialization=True)
    print(f"centred {a.vae} -> {a.out}: channel means {[round(float(v), 3) for v in mu]}, stds "
          f"{[round(float(v), 3) for v in sigma]} folded in; scaling_factor {sf:.5f}")
    return mu, sigma, sf


# the flags that define the objective: kept in the checkpoint, a resume must repeat them
LOSS_SETTINGS = ("recon_loss", "object_weight", "marking_weight", "grad_weight", "kl_weight", "crop", "se_weight",
                 "decoder_only", "decode_latents", "decode_latents_p")
# settings added later, with the value a run that predates them trained with
LOSS_DEFAULTS = {"se_weight": 0.0, "decoder_only": False, "decode_latents": None, "decode_latents_p": 1.0}


def load_decode_latents(path: str, source, scaling_factor: float):
    """The --decode-latents file (training/sampled_latents.py): {sample index: unscaled latent}, checked against
    the data (sample count, render size) and the VAE's scaling factor (the latents were made in its space)."""
    from .training.sampled_latents import FORMAT

    d = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise SystemExit(f"--decode-latents {path}: not a {FORMAT} file (python -m b2dr_ref.training.sampled_latents)")
    if int(d["samples"]) != len(source) or list(d["render_size"]) != list(source.render_size):
        raise SystemExit(f"--decode-latents {path}: made from {d['samples']} samples at {d['render_size']}, the data "
                         f"has {len(source)} at {list(source.render_size)}")
    if abs(float(d["scaling_factor"]) - float(scaling_factor)) > 1e-6 * abs(float(scaling_factor)):
        raise SystemExit(f"--decode-latents {path}: made with scaling factor {d['scaling_factor']}, this VAE's is "
                         f"{scaling_factor} (another latent space)")
    lat = d["latents"].float() / float(d["scaling_factor"])
    return d["index"].long(), lat


def train_vae(args):
    device = torch.device(args.device)
    set_threads(args.device, args.threads)
    os.makedirs(args.out, exist_ok=True)
    ck_path = os.path.join(args.out, CKPT)
    ck = torch.load(ck_path, map_location="cpu", weights_only=False) if args.resume and os.path.exists(ck_path) \
        else None
    cfg = ck["cfg"] if ck else nano.get_config(args.config)
    nano.check_config(cfg)
    loss_settings = {k: getattr(args, k) for k in LOSS_SETTINGS}
    if ck and "loss" in ck:
        ck["loss"] = {**LOSS_DEFAULTS, **ck["loss"]}
    if ck and "loss" in ck and ck["loss"] != loss_settings:
        # a resume with other loss flags would silently train a different objective from here on
        diff = ", ".join(f"--{k.replace('_', '-')} {loss_settings[k]} (the run: {ck['loss'][k]})"
                         for k in LOSS_SETTINGS if ck["loss"][k] != loss_settings[k])
        raise SystemExit(f"--resume {args.out}: the loss settings differ from the run's: {diff}; pass the run's")
    if args.decoder_only and not (args.init_from or ck):
        raise SystemExit("--decoder-only trains the decoder of an existing VAE: give it with --init-from")
    if args.decoder_only and args.se_weight:
        raise SystemExit("--decoder-only with --se-weight: the scale-equivariance term shapes the encoder's latent, "
                         "which --decoder-only keeps fixed")
    if args.decode_latents and not args.decoder_only:
        raise SystemExit("--decode-latents trains the decoder on the renderer's own latents: give --decoder-only "
                         "(the encoder, whose latent space they were sampled in, must stay fixed)")
    if args.decode_latents and args.crop:
        raise SystemExit("--decode-latents with --crop: the sampled latents are whole frames")
    if not 0.0 <= args.decode_latents_p <= 1.0:
        raise SystemExit(f"--decode-latents-p {args.decode_latents_p}: a probability in [0, 1]")
    source = open_source(args.data, cfg["render_size"])
    vae = build_vae(cfg, args.seed).to(device).train()
    # a --decoder-only run keeps the initial VAE's latent space: its scaling factor, no re-centring
    keep_sf = ck.get("scaling_factor") if ck else None
    if args.init_from and not ck:
        # continue from an existing VAE folder (e.g. a committed package's vae/, centred or not: it is re-centred
        # whenever it is saved); the architecture must be the config's
        init = load_vae(args.init_from)
        if dict(init.config)["block_out_channels"] != list(cfg["vae"]["block_out_channels"]):
            raise SystemExit(f"--init-from {args.init_from}: its blocks differ from config {cfg['name']!r}")
        if init.config.latent_channels == cfg["vae"]["latent_channels"]:
            vae.load_state_dict(init.state_dict())
            keep_sf = float(init.config.scaling_factor) if args.decoder_only else None
            print(f"vae: initialised from {args.init_from}", flush=True)
        elif args.decoder_only:
            raise SystemExit(f"--decoder-only --init-from {args.init_from}: its {init.config.latent_channels} latent "
                             f"channels differ from config {cfg['name']!r}'s {cfg['vae']['latent_channels']}")
        else:
            # another latent width (a design with more latent channels): the body is taken, the tensors that touch
            # the latent (encoder.conv_out, quant_conv, post_quant_conv, decoder.conv_in) start fresh
            own = vae.state_dict()
            fresh = [k for k, v in init.state_dict().items() if own[k].shape != v.shape]
            vae.load_state_dict({k: v for k, v in init.state_dict().items() if k not in fresh}, strict=False)
            print(f"vae: body initialised from {args.init_from} ({init.config.latent_channels} -> "
                  f"{cfg['vae']['latent_channels']} latent channels; fresh: {', '.join(fresh)})", flush=True)
    if args.decoder_only:
        # the encoder side (encoder, quant_conv) is frozen: only the decoder side has parameters to train
        for mod in (vae.encoder, vae.quant_conv):
            mod.requires_grad_(False)
    params = [p for p in vae.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=args.lr, weight_decay=args.weight_decay)
    total = ck["total_steps"] if ck else args.steps
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda(args.warmup, total))
    gen = torch.Generator().manual_seed(args.seed)
    step = 0
    if ck:
        vae.load_state_dict(ck["vae"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["lr_scheduler"])
        gen.set_state(ck["generator"])
        torch.set_rng_state(ck["torch_rng"])
        step = ck["step"]
    steps = max(args.steps, step)
    if args.stop_after:
        steps = min(steps, step + args.stop_after)
    given_idx = given_lat = None
    if args.decode_latents:
        given_idx, given_lat = load_decode_latents(args.decode_latents, source, keep_sf)
        print(f"--decode-latents: {len(given_idx)} sampled latents, decoded for a row with probability "
              f"{args.decode_latents_p}", flush=True)
    log = CsvLog(os.path.join(args.out, "log.csv"), ["step", "loss", "l1", "kl", "lr", "sec"], step)
    losses = []
    try:
        while step < steps:
            t0 = time.perf_counter()
            z_given = given = None
            if given_idx is not None:
                # rows drawn among the samples the file holds; the draw order is fixed (exact resume)
                pos = torch.arange(args.batch) if args.fixed_batch else \
                    torch.randint(0, len(given_idx), (args.batch,), generator=gen)
                idx = given_idx[pos].tolist()
                given = torch.rand((args.batch,), generator=gen) < args.decode_latents_p
                z_given = given_lat[pos]
            else:
                idx = list(range(args.batch)) if args.fixed_batch else \
                    torch.randint(0, len(source), (args.batch,), generator=gen).tolist()
            x = images(source, idx, device)
            w = pixel_weights(source, idx, device, args.object_weight, args.marking_weight)
            if args.crop:
                x, w = random_crop(x, args.crop, gen, w) if w is not None else (random_crop(x, args.crop, gen), None)
            loss, l1, kl = vae_loss(vae, x, gen, args.kl_weight, w, args.grad_weight, args.recon_loss,
                                    args.se_weight, args.decoder_only, z_given, given)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, args.clip)
            opt.step()
            sched.step()
            step += 1
            losses.append(float(loss.detach()))
            log.write(dict(step=step, loss=f"{losses[-1]:.6f}", l1=f"{float(l1):.6f}", kl=f"{float(kl):.3f}",
                           lr=f"{sched.get_last_lr()[0]:.3e}", sec=f"{time.perf_counter() - t0:.3f}"))
            if step % args.log_every == 0:
                print(f"vae step {step} loss {losses[-1]:.4f} kl {float(kl):.1f}", flush=True)
            if step % args.ckpt_every == 0 or step == steps:
                save_checkpoint(ck_path, dict(cfg=cfg, total_steps=total, step=step, vae=vae.state_dict(),
                                              loss=loss_settings, scaling_factor=keep_sf,
                                              optimizer=opt.state_dict(), lr_scheduler=sched.state_dict(),
                                              generator=gen.get_state(), torch_rng=torch.get_rng_state()))
                sf = save_vae(vae, source, args.out, device, scaling_factor=keep_sf)
                print(f"vae step {step}: wrote {os.path.join(args.out, 'vae')} (scaling_factor {sf:.5f})", flush=True)
    finally:
        log.close()
    return losses


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "centre":
        return centre_command(argv[1:])
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.vae_train")
    add_common(p)
    p.set_defaults(lr=2e-4, warmup=200, ckpt_every=500)
    p.add_argument("--kl-weight", type=float, default=1e-6)
    p.add_argument("--crop", type=parse_crop, default=None,
                   help="train on random HxW crops (multiples of 8), e.g. 56x104: ~4x cheaper steps")
    p.add_argument("--init-from", default=None, help="start from this VAE folder (e.g. models/b2dr-nano/vae)")
    p.add_argument("--object-weight", type=float, default=0.0,
                   help="extra L1 weight on pixels of objects (vehicles, pedestrians, two-wheelers; the export's "
                        "masks): the loss weight there is 1 + this (0 = plain L1)")
    p.add_argument("--marking-weight", type=float, default=0.0,
                   help="extra L1 weight on lane-divider and crosswalk pixels (the export's masks), added to the "
                        "object weight")
    p.add_argument("--grad-weight", type=float, default=0.0,
                   help="weight of an L1 term on neighbour-pixel differences (edge contrast; the object / marking "
                        "weights apply to it too); 0 = off")
    p.add_argument("--recon-loss", choices=["l1", "l2"], default="l1",
                   help="per-pixel reconstruction error: absolute (l1, LDM's) or squared (l2: a thin bright line "
                        "whose place the decoder has not learnt yet costs more, so it is learnt sooner)")
    p.add_argument("--se-weight", type=float, default=0.0,
                   help="weight of the scale-equivariance term: the half-size latent must decode to the half-size "
                        "image (smoother, easier-to-denoise latents; docs/training.md); 0 = off")
    p.add_argument("--decoder-only", action="store_true",
                   help="train the decoder of the --init-from VAE only, the encoder frozen: its latent space (and "
                        "scaling factor) stay exactly the initial VAE's, so a denoiser trained on it keeps working "
                        "with the new decoder")
    p.add_argument("--decode-latents", default=None,
                   help="with --decoder-only: a file of the renderer's own one-step latents of the data's frames "
                        "(python -m b2dr_ref.training.sampled_latents); a row decodes its frame's sampled latent "
                        "(probability --decode-latents-p) instead of the encoder's, the true frame the target")
    p.add_argument("--decode-latents-p", type=float, default=1.0,
                   help="the probability that a row decodes the sampled latent (else the encoder's mean)")
    return train_vae(p.parse_args(argv))


if __name__ == "__main__":
    main()
