"""The model's own previous frame (``train --self-prev P``): in the closed loop the renderer's previous frame is its
own earlier output, not a blurred true frame, and errors it learned never to meet in training (a lead vehicle
smeared into the road) are carried forward and grow. With probability P a row's previous latent is replaced by
the model's own one-step render of the row's frame (the current weights, no gradient) taken through the
engine's previous-frame path: decode, clamp, 8-bit, blur, encode. The row then teaches the model to correct its
own output against the layout rather than to copy it. The own render is of the target's pose (the data holds no
layout of the frame before the previous one); the rows with the true previous frame keep teaching the motion.
"""

from __future__ import annotations

from typing import Dict

import torch

from ..fastpath import PLAIN, FastPath
from ..frame import gaussian_blur
from .loss import denoise

# diffusers' UniPCMultistepScheduler, linspace spacing, one step: timesteps [999]; its last update goes to sigma 0
# and returns the model's x_0 prediction (the engine's one-step UniPC: src/sampling/unipc.rs)
ONE_STEP_T = 999


def draw_self(b, gen: torch.Generator, p: float) -> Dict:
    """The self-prev draws of one batch, after draw_noise's, from ``gen`` (on the CPU): the rows (probability
    ``p``), the one-step sample's starting noise and the noise of its previous-frame input."""
    B = b["x0"].shape[0]
    rows = torch.rand((B,), generator=gen) < p
    x_T = torch.randn(b["x0"].shape, generator=gen)
    eps_in = torch.randn(b["z_prev"].shape, generator=gen)
    return dict(rows=rows, x_T=x_T, eps_in=eps_in)


def one_step_x0(unet, controlnet, ctx, masks, z_prev, x_T, eps_in, abar, level: int, prediction: str,
                x0_base: str, fast: FastPath = PLAIN) -> torch.Tensor:
    """The package's one-step sample without references: the previous latent ``z_prev`` (N, C, h, w) noised to
    ``level`` (the ControlNet config's prev_noise_level), the prediction at t = 999 from ``x_T``, its x_0 (plus
    ``z_prev`` for an ``x0_base`` "prev" model)."""
    dev = x_T.device
    N = x_T.shape[0]
    a = abar.to(dev)
    an = a[int(level)]
    z = an.sqrt() * z_prev + (1 - an).sqrt() * eps_in
    n = torch.full((N,), int(level), dtype=torch.int64, device=dev)
    t = torch.full((N,), ONE_STEP_T, dtype=torch.int64, device=dev)
    pred = denoise(unet, controlnet, x_T, t, ctx, masks, z, n, None, None, None,
                   torch.zeros(N, dtype=torch.bool), fast=fast).float()
    at = a[ONE_STEP_T]
    if prediction == "v_prediction":
        x0 = at.sqrt() * x_T - (1 - at).sqrt() * pred
    elif prediction == "epsilon":
        x0 = (x_T - (1 - at).sqrt() * pred) / at.sqrt()
    else:
        raise ValueError(f"prediction {prediction!r}")
    return x0 + z_prev if x0_base == "prev" else x0


def previous_frame_latent(vae, x0: torch.Tensor, sigma: float) -> torch.Tensor:
    """(N, C, h, w) sampled latent -> the frame the engine shows (decode, clamp, 8-bit) -> the previous-frame path
    (Gaussian blur ``sigma`` pixels, 2x - 1, encoder mean x scaling): the latent the next frame is given."""
    sf = vae.config.scaling_factor
    img = vae.decode(x0 / sf).sample.float()
    img = torch.round((img.clamp(-1, 1) + 1) * 127.5) / 255.0
    if sigma > 0:
        img = gaussian_blur(img.cpu(), sigma).to(x0.device)     # frame.gaussian_blur builds its taps on the CPU
    return vae.encode(2.0 * img - 1.0).latent_dist.mean * sf


@torch.no_grad()
def own_previous(unet, controlnet, vae, ctx, b, s: Dict, rows: torch.Tensor, abar, prediction: str, x0_base: str,
                 fast: FastPath = PLAIN) -> torch.Tensor:
    """``b["z_prev"]`` with the ``rows`` (bool, (B,)) replaced by the previous-frame latent of the model's own
    one-step render of their frame (``s``: draw_self's draws; ``ctx``: the batch's context rows)."""
    if not bool(rows.any()):
        return b["z_prev"]
    cfg = controlnet.config
    dev = b["z_prev"].device
    r = rows.to(dev)
    x0 = one_step_x0(unet, controlnet, ctx[r], b["masks"][r], b["z_prev"][r], s["x_T"].to(dev)[r],
                     s["eps_in"].to(dev)[r], abar, int(cfg.prev_noise_level), prediction, x0_base, fast)
    z = b["z_prev"].clone()
    z[r] = previous_frame_latent(vae, x0, float(cfg.prev_blur_sigma)).to(z.dtype)
    return z
