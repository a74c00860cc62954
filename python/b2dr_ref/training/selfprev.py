"""The model's own previous frame (``train --self-prev P``): in the closed loop the renderer's previous frame is its
own earlier output, not a blurred true frame, and errors it learned never to meet in training (a lead vehicle
smeared into the road) are carried forward and grow. With probability P a row's previous latent is replaced by
the model's own one-step render of the row's frame (the current weights, no gradient) taken through the
engine's previous-frame path: decode, clamp, 8-bit, blur, encode. The row then teaches the model to correct its
own output against the layout rather than to copy it. ``--self-prev-pose same`` renders the target's own pose
(aligned with the target: only the correction is taught); ``other`` renders the same frame at another of the
data's ego offsets (1.5 m or 3 m sideways, 8 deg of yaw, or both), so that the own frame is displaced against the target as a
previous frame is in the loop. Both renders start from the row's true previous frame: every offset of a frame
shares it (the previous frame is recorded at the logged pose). ``chain`` (data exported with ``--prev-chain``)
renders the previous frame ITSELF, as the closed loop does one step earlier: the previous frame's own layout
(``masks_prev``, at its logged pose and step) from the frame before it (``z_prev2``, the log's image 0.5 s before
the previous frame, blurred and encoded); the target's previous frame is then the model's own, displaced by the
ego's 0.5 s of motion and showing the agents where they were, the input the loop gives it.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Dict, List, Optional

import torch

from ..fastpath import PLAIN, FastPath
from ..frame import gaussian_blur
from ..warp import warp_image
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


def x0_from(pred: torch.Tensor, x_T: torch.Tensor, at: torch.Tensor, prediction: str) -> torch.Tensor:
    """x_0 from the model's prediction at the noise level whose alpha-bar is ``at`` (v or epsilon)."""
    if prediction == "v_prediction":
        return at.sqrt() * x_T - (1 - at).sqrt() * pred
    if prediction == "epsilon":
        return (x_T - (1 - at).sqrt() * pred) / at.sqrt()
    raise ValueError(f"prediction {prediction!r}")


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
    x0 = x0_from(pred, x_T, a[ONE_STEP_T], prediction)
    return x0 + z_prev if x0_base == "prev" else x0


def previous_frame_latent(vae, x0: torch.Tensor, sigma: float, grid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(N, C, h, w) sampled latent -> the frame the engine shows (decode, clamp, 8-bit) -> the previous-frame path
    (with ``grid`` (N, H, W, 2) the warp to the next frame's pose (b2dr_ref/warp.py), Gaussian blur ``sigma``
    pixels, 2x - 1, encoder mean x scaling): the latent the next frame is given."""
    sf = vae.config.scaling_factor
    img = vae.decode(x0 / sf).sample.float()
    img = torch.round((img.clamp(-1, 1) + 1) * 127.5) / 255.0
    if grid is not None:
        img = warp_image(img, grid)
    if sigma > 0:
        img = gaussian_blur(img.cpu(), sigma).to(x0.device)     # frame.gaussian_blur builds its taps on the CPU
    return vae.encode(2.0 * img - 1.0).latent_dist.mean * sf


@torch.no_grad()
def own_previous(unet, controlnet, vae, ctx, b, s: Dict, rows: torch.Tensor, abar, prediction: str, x0_base: str,
                 fast: FastPath = PLAIN) -> torch.Tensor:
    """``b["z_prev"]`` with the ``rows`` (bool, (B,)) replaced by the previous-frame latent of the model's own
    one-step render of their frame (``s``: draw_self's draws; ``ctx``: the batch's context rows), at the pose of
    ``b["masks_other"]`` when the batch has it (--self-prev-pose other); with ``b["masks_prev"]`` and
    ``b["z_prev2"]`` (--self-prev-pose chain) the render of the previous frame from its own previous frame."""
    if not bool(rows.any()):
        return b["z_prev"]
    cfg = controlnet.config
    dev = b["z_prev"].device
    r = rows.to(dev)
    if "masks_prev" in b:
        masks, z_in = b["masks_prev"], b["z_prev2"]
    else:
        masks, z_in = (b["masks_other"] if "masks_other" in b else b["masks"]), b["z_prev"]
    x0 = one_step_x0(unet, controlnet, ctx[r], masks[r], z_in[r], s["x_T"].to(dev)[r],
                     s["eps_in"].to(dev)[r], abar, int(cfg.prev_noise_level), prediction, x0_base, fast)
    z = b["z_prev"].clone()
    grid = b.get("prev_grid")
    if float(getattr(cfg, "prev_warp_max_depth", 0.0) or 0.0) > 0 and grid is None:
        raise ValueError("own_previous: a warped previous frame needs the batch's prev_grid")
    z[r] = previous_frame_latent(vae, x0, float(cfg.prev_blur_sigma),
                                 None if grid is None else grid[r.cpu()]).to(z.dtype)
    return z


def pose_partners(source) -> Optional[List[List[int]]]:
    """Per sample index of an exported dataset (training.data.DatasetSource: index = frame row x cameras + camera),
    the indices of the same scenario, step and camera at the other ego offsets; None for a source without that
    index (synthetic, shards) or when a sample has no partner. Partners share the previous frame (checked)."""
    ds = getattr(source, "ds", None)
    rows = getattr(ds, "samples", None)
    if rows is None:
        return None
    nc = len(source.cameras)
    groups: Dict[tuple, List[int]] = defaultdict(list)
    for f, s in enumerate(rows):
        groups[(s["scenario"], int(s["step"]))].append(f)
    out: List[List[int]] = []
    for f, s in enumerate(rows):
        g = [o for o in groups[(s["scenario"], int(s["step"]))] if o != f]
        if not g:
            return None
        if any(int(rows[o]["prev_step"]) != int(s["prev_step"]) for o in g):
            raise ValueError(f"sample {f}: the offsets of {s['scenario']} step {s['step']} have other previous frames")
        for c in range(nc):
            out.append([o * nc + c for o in g])
    return out
