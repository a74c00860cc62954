"""The diffusion loss of the B2D-R renderer in pieces, shared by every recipe (b2dr_ref.train's diffusion_loss,
b2dr_ref.training.sd15): the random draws of a batch, the noised inputs (DDPM add_noise on the target, noise
modulation of the previous frame, 'no previous frame'), the model's prediction (references, ControlNet, UNet) and
the weighted MSE to its target (epsilon or v)."""

from __future__ import annotations

from typing import Dict

import torch
import torch.nn.functional as F

from ..fastpath import PLAIN, FastPath

NO_PREV_NOISE_LEVEL = 999     # src/render/frame.rs NO_PREV_NOISE_LEVEL: zero latent input, n = 999


LOSS_WEIGHTS = ("eps", "v", "min-snr")


def loss_weight(kind: str, abar_t: torch.Tensor, max_weight: float = 0.0, gamma: float = 5.0) -> torch.Tensor:
    """Per-sample weight of the epsilon MSE at noise levels with alpha-bar ``abar_t`` (SNR = abar / (1 - abar)):
    - ``eps``: 1 (the plain epsilon loss);
    - ``v``: 1 + 1 / SNR, which makes the epsilon-parameterised loss equal to the v-prediction loss
      ||v - v_hat||^2 (v_hat from the predicted epsilon): the x_0 error at high noise levels is no longer weighted
      by SNR ~ 0.005, so the model learns the global layout that the first sampling steps decide;
    - ``min-snr``: min(SNR, gamma) / SNR (Min-SNR-gamma, Hang et al. 2023): down-weights the lowest noise levels.
    ``max_weight`` > 0 caps the weight."""
    snr = abar_t / (1 - abar_t)
    if kind == "eps":
        w = torch.ones_like(snr)
    elif kind == "v":
        w = 1 + 1 / snr
    elif kind == "min-snr":
        w = torch.clamp(snr, max=gamma) / snr
    else:
        raise ValueError(f"loss weight {kind!r} (one of {', '.join(LOSS_WEIGHTS)})")
    return torch.clamp(w, max=max_weight) if max_weight > 0 else w


PREDICTIONS = ("epsilon", "v_prediction")


def draw_noise(b, gen: torch.Generator, prev_noise_max: int, p_noprev: float, ref_dropout: float) -> Dict:
    """The random draws of one batch, in this order from ``gen`` (on the CPU): t, eps, n, eps_p, noprev, ref_mask."""
    B = b["x0"].shape[0]
    t = torch.randint(0, 1000, (B,), generator=gen)
    eps = torch.randn(b["x0"].shape, generator=gen)
    n = torch.randint(0, int(prev_noise_max) + 1, (B,), generator=gen)
    eps_p = torch.randn(b["z_prev"].shape, generator=gen)
    noprev = torch.rand((B,), generator=gen) < p_noprev
    ref_mask = torch.rand((B,), generator=gen) >= ref_dropout
    return dict(t=t, eps=eps, n=n, eps_p=eps_p, noprev=noprev, ref_mask=ref_mask)


def noised_inputs(b, d: Dict, abar: torch.Tensor):
    """x_t (DDPMScheduler.add_noise), the noised previous latent z (zero and n = 999 for 'no previous frame'), the
    noise levels n and sqrt-able alpha-bar at t, all on the batch's device."""
    dev = b["x0"].device
    B = b["x0"].shape[0]
    a = abar.to(dev)
    at = a[d["t"].to(dev)].reshape(B, 1, 1, 1)
    x_t = at.sqrt() * b["x0"] + (1 - at).sqrt() * d["eps"].to(dev)
    an = a[d["n"].to(dev)].reshape(B, 1, 1, 1)
    z = an.sqrt() * b["z_prev"] + (1 - an).sqrt() * d["eps_p"].to(dev)
    keep = (~d["noprev"]).to(dev).float().reshape(B, 1, 1, 1)
    z = z * keep
    n = torch.where(d["noprev"], torch.full_like(d["n"], NO_PREV_NOISE_LEVEL), d["n"])
    return x_t, z, n.to(dev), at


def denoise(unet, controlnet, x_t, t, ctx, masks, z, n, ref_latents, pe_cur, pe_ref, ref_mask, fast: FastPath = PLAIN):
    """The model's prediction: references prepared for the rows of ``ref_mask`` (none when it is all False), the
    B2D-R ControlNet's residuals, the UNet. ``fast``: memory format and autocast (fastpath.py)."""
    dev = x_t.device
    with fast.autocast_ctx(dev):
        refs = None
        if bool(ref_mask.any()):
            m = ref_mask.to(dev)
            refs = controlnet.prepare_references(fast.inputs(ref_latents[m]), [p[m] for p in pe_cur],
                                                 [p[m] for p in pe_ref])
        xi = fast.inputs(x_t)
        down, mid = controlnet(xi, t, ctx, fast.inputs(masks), fast.inputs(z), n, refs=refs,
                               ref_mask=ref_mask.to(dev) if refs is not None else None)
        return unet(xi, t, ctx, down_block_additional_residuals=down, mid_block_additional_residual=mid).sample


def prediction_loss(pred, b, d: Dict, at, weighting: str = "eps", max_weight: float = 0.0,
                    prediction: str = "epsilon", object_weight: float = 0.0, marking_weight: float = 0.0):
    """The (weighted) MSE between the prediction and its target (epsilon, or v); ``object_weight`` /
    ``marking_weight`` weigh up the latent cells over objects / lane markings (layout_loss_weight)."""
    dev = b["x0"].device
    B = b["x0"].shape[0]
    eps = d["eps"].to(dev)
    if prediction == "v_prediction":
        target = at.sqrt() * eps - (1 - at).sqrt() * b["x0"]
    elif prediction == "epsilon":
        target = eps
    else:
        raise ValueError(f"prediction {prediction!r} (one of {', '.join(PREDICTIONS)})")
    sq = (pred.float() - target.float()) ** 2
    if object_weight > 0 or marking_weight > 0:
        sq = sq * layout_loss_weight(b["masks"], sq.shape[-2:], object_weight, marking_weight)
    if weighting == "eps":
        return sq.mean()
    per = sq.mean(dim=(1, 2, 3))
    return (loss_weight(weighting, at.reshape(B), max_weight) * per).mean()


# the mask channels (controlnet.MASK_CHANNELS order) of the objects: car .. bicycle
OBJECT_CHANNELS = slice(0, 8)
# ... and of the painted structures of the road: lane dividers and crosswalks
MARKING_CHANNELS = [12, 13]


def object_loss_weight(masks: torch.Tensor, latent_hw, w: float) -> torch.Tensor:
    """(B, 15, H, W) image-size masks -> (B, 1, h, w) latent-size weights 1 + w * [an object in the cell]."""
    return layout_loss_weight(masks, latent_hw, w, 0.0)


def layout_loss_weight(masks: torch.Tensor, latent_hw, object_weight: float, marking_weight: float) -> torch.Tensor:
    """(B, 15, H, W) image-size masks -> (B, 1, h, w) latent-size weights 1 + object_weight * [an object in the
    cell] + marking_weight * [a lane divider or crosswalk pixel in the cell]. A marking is one or two pixels
    wide, so it barely moves a latent cell's value and, unweighted, is the last thing the model learns."""
    hw = tuple(int(v) for v in latent_hw)
    w = torch.ones((masks.shape[0], 1) + hw, device=masks.device)
    for weight, ch in ((object_weight, OBJECT_CHANNELS), (marking_weight, MARKING_CHANNELS)):
        if weight > 0:
            m = masks[:, ch].amax(1, keepdim=True).float()
            w = w + weight * F.adaptive_max_pool2d(m, hw)
    return w
