"""One frame of the B2D-R renderer (contract sections 3 and 4): the previous-frame chain, reference encoding and the
guided sampling loop (diffusers UNet2DConditionModel + B2DRControlNetModel + UniPCMultistepScheduler)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from .controlnet import B2DRControlNetModel, References

# SD1.5 schedule (tools/make_golden.py SD15); the rest are diffusers' UniPCMultistepScheduler defaults.
SD15_SCHEDULE = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear")


def make_scheduler(kind: str = "unipc", prediction_type: str = "epsilon"):
    """The sampler of the plain pipeline: UniPC (bh2, order 2, predict x0, lower order final, final sigma zero,
    linspace) or DDIM (SD1.5: leading, steps_offset 1, no clipping, set_alpha_to_one False); the model predicts
    epsilon or v (b2dr.json prediction_type)."""
    from diffusers import DDIMScheduler, UniPCMultistepScheduler

    if kind == "unipc":
        return UniPCMultistepScheduler(**SD15_SCHEDULE, solver_order=2, solver_type="bh2", lower_order_final=True,
                                       final_sigmas_type="zero", timestep_spacing="linspace",
                                       prediction_type=prediction_type)
    if kind == "ddim":
        return DDIMScheduler(**SD15_SCHEDULE, set_alpha_to_one=False, steps_offset=1, clip_sample=False,
                             timestep_spacing="leading", prediction_type=prediction_type)
    raise ValueError(f"unknown sampler {kind!r} (unipc or ddim)")


def alphas_cumprod() -> torch.Tensor:
    """diffusers' SD1.5 alphas_cumprod, (1000,) float32."""
    return make_scheduler("unipc").alphas_cumprod.to(torch.float32)


# ---------------------------------------------------------------------------------------------------------------
# Previous frame (contract section 3)
# ---------------------------------------------------------------------------------------------------------------


def blur_radius(sigma: float) -> int:
    return int(math.ceil(3.0 * sigma))


def gaussian_weights(sigma: float) -> np.ndarray:
    """1-D Gaussian taps exp(-x^2 / (2 sigma^2)), x = -r..r, r = ceil(3 sigma), normalised (f64)."""
    r = blur_radius(sigma)
    x = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-(x * x) / (2.0 * sigma * sigma))
    return w / w.sum()


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(N, C, H, W) -> same; separable (rows, i.e. along W, then columns), REFLECT borders (PyTorch 'reflect': the
    edge pixel is not repeated), taps as gaussian_weights rounded to the tensor's dtype."""
    n, c, hh, ww = x.shape
    r = blur_radius(sigma)
    if r >= hh or r >= ww:
        raise ValueError(f"gaussian_blur: radius {r} needs an image larger than {hh}x{ww}")
    k = torch.tensor(gaussian_weights(sigma), dtype=x.dtype, device=x.device)
    y = x.reshape(n * c, 1, hh, ww)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="reflect"), k.reshape(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="reflect"), k.reshape(1, 1, -1, 1))
    return y.reshape(n, c, hh, ww)


def vae_encode_mean(vae, images01: torch.Tensor) -> torch.Tensor:
    """Images in [0, 1] (M, 3, H, W) -> posterior mean x scaling factor (M, 4, H/f, W/f)."""
    return vae.encode(2.0 * images01 - 1.0).latent_dist.mean * vae.config.scaling_factor


def noise_latent(z0: torch.Tensor, eps: torch.Tensor, n: int, abar: Optional[torch.Tensor] = None):
    """z = sqrt(abar_n) z0 + sqrt(1 - abar_n) eps (f32, as diffusers' add_noise). Returns (z, sqrt_abar, sqrt_1m)."""
    abar = alphas_cumprod() if abar is None else abar
    a = abar[int(n)].to(z0.dtype)
    sa = a ** 0.5
    sb = (1 - a) ** 0.5
    return sa * z0 + sb * eps, sa, sb


@dataclass
class PrevChain:
    blurred: torch.Tensor
    z_prev: torch.Tensor
    z: torch.Tensor
    sqrt_abar: torch.Tensor
    sqrt_one_minus_abar: torch.Tensor


def prev_frame_chain(vae, prev: torch.Tensor, eps_prev: torch.Tensor, sigma: float, n: int) -> PrevChain:
    """prev (N, 3, H, W) in [0, 1] -> blur -> VAE mean x scaling -> noised to level n with eps_prev."""
    blurred = gaussian_blur(prev, sigma)
    z_prev = vae_encode_mean(vae, blurred)
    z, sa, sb = noise_latent(z_prev, eps_prev, n)
    return PrevChain(blurred, z_prev, z, sa, sb)


def encode_reference_images(vae, refs: torch.Tensor) -> torch.Tensor:
    """refs (N, 2, 3, H, W) in [0, 1] (front, rear) -> (N, 2, 4, h, w) latents (mean x scaling, no blur, no noise)."""
    n = refs.shape[0]
    z = vae_encode_mean(vae, refs.reshape((2 * n,) + tuple(refs.shape[2:])))
    return z.reshape((n, 2) + tuple(z.shape[1:]))


def decode_image(vae, latent: torch.Tensor) -> torch.Tensor:
    """clamp(D(x_0 / scaling) / 2 + 0.5, 0, 1)."""
    return (vae.decode(latent / vae.config.scaling_factor).sample / 2 + 0.5).clamp(0, 1)


def upsample_for_planner(img: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bicubic (PyTorch, align_corners=False, A = -0.75) to the camera's native size."""
    return F.interpolate(img, size=(height, width), mode="bicubic", align_corners=False)


# ---------------------------------------------------------------------------------------------------------------
# Sampling one frame (contract section 4)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class FrameResult:
    image: torch.Tensor                      # (N, 3, H, W) in [0, 1]
    # the decoded x_0 (N, C, h, w); with x0_base "prev" the sampled residual + z_prev (the engine's
    # FrameRenderer::latent() is the sampler's own variable, the residual, and base_latent() the base)
    latent: torch.Tensor
    timesteps: List[int]
    latents: List[torch.Tensor] = field(default_factory=list)     # after each step
    eps_noref: List[torch.Tensor] = field(default_factory=list)   # per step (empty when not run)
    eps_ref: List[torch.Tensor] = field(default_factory=list)     # per step (empty when not run)
    eps: List[torch.Tensor] = field(default_factory=list)         # the guided eps per step
    decoded: Optional[torch.Tensor] = None   # raw VAE output, before /2 + 0.5 and clamp
    prev: Optional[PrevChain] = None
    ref_latents: Optional[torch.Tensor] = None
    refs: Optional[References] = None


def expand_context(context: torch.Tensor, n: int) -> torch.Tensor:
    """(77, D) or (n, 77, D) -> (n, 77, D)."""
    if context.dim() == 2:
        return context[None].expand(n, -1, -1)
    if context.shape[0] != n:
        raise ValueError(f"context has {context.shape[0]} cameras, the frame {n}")
    return context


@torch.no_grad()
def render_frame(unet, controlnet: B2DRControlNetModel, vae, x_T: torch.Tensor, context: torch.Tensor,
                 masks: torch.Tensor, prev: torch.Tensor, eps_prev: torch.Tensor,
                 ref_images: Optional[torch.Tensor] = None, pe_cur: Optional[Sequence[torch.Tensor]] = None,
                 pe_ref: Optional[Sequence[torch.Tensor]] = None, steps: int = 20, ref_guidance: float = 2.0,
                 sampler: str = "unipc", noise_level: Optional[int] = None,
                 conditioning_scale: float = 1.0, prediction_type: str = "epsilon",
                 sdedit: Optional[Tuple[int, torch.Tensor]] = None, x0_base: str = "none") -> FrameResult:
    """A full frame of N cameras.

    sdedit = (t0, z_start) (a diagnostic, not the engine's path): the sampler starts at its first timestep <= t0
    from sqrt(abar) z_start + sqrt(1 - abar) x_T instead of x_T at its first timestep (SDEdit; z_start e.g. the
    previous frame's latent).

    x0_base "prev" (b2dr.json x0_base): the model diffuses the residual against the previous frame's clean blurred
    latent z_prev; the frame's latent is the sampled residual + z_prev.

    x_T (N, 4, h, w); context (77, D) or (N, 77, D); masks (N, 15, H, W); prev (N, 3, H, W) in [0, 1]; eps_prev
    (N, 4, h, w); ref_images (N, 2, 3, H, W) in [0, 1] or None (references off); pe_cur / pe_ref: per Ref-Attn
    location (N, 3D, h_j, w_j) / (N, 2, 3D, h_j, w_j). With references and w != 1 every step runs the batch
    [no-ref; ref] (2N rows) and eps = eps_noref + w (eps_ref - eps_noref); w == 1 runs the N ref rows only; without
    references the N no-ref rows only.
    """
    cfg = controlnet.config
    n = x_T.shape[0]
    nl = int(cfg.prev_noise_level) if noise_level is None else int(noise_level)
    chain = prev_frame_chain(vae, prev, eps_prev, float(cfg.prev_blur_sigma), nl)
    ctx = expand_context(context, n)
    refs = None
    ref_latents = None
    if ref_images is not None:
        ref_latents = encode_reference_images(vae, ref_images)
        refs = controlnet.prepare_references(ref_latents, pe_cur, pe_ref)  # once per frame
    guided = refs is not None and ref_guidance != 1.0

    sched = make_scheduler(sampler, prediction_type)
    sched.set_timesteps(steps)
    res = FrameResult(image=None, latent=None, timesteps=[int(t) for t in sched.timesteps], prev=chain,
                      ref_latents=ref_latents, refs=refs)
    x = x_T.clone()
    timesteps = sched.timesteps
    if sdedit is not None:
        t0, z_start = sdedit
        timesteps = [t for t in sched.timesteps if int(t) <= int(t0)]
        if not timesteps:
            raise ValueError(f"sdedit t0 {t0}: no sampler timestep at or below it")
        a = sched.alphas_cumprod[int(timesteps[0])]
        x = a.sqrt() * z_start + (1 - a).sqrt() * x_T
        res.timesteps = [int(t) for t in timesteps]
    if guided:
        ctx_b, masks_b, z_b = torch.cat([ctx] * 2), torch.cat([masks] * 2), torch.cat([chain.z] * 2)
        ref_mask = torch.tensor([False] * n + [True] * n)
    else:
        ctx_b, masks_b, z_b, ref_mask = ctx, masks, chain.z, None
    noise_b = torch.full((ctx_b.shape[0],), nl, dtype=torch.int64)
    for t in timesteps:
        xin = torch.cat([x] * 2) if guided else x
        down, mid = controlnet(xin, t, ctx_b, masks_b, z_b, noise_b, refs=refs, ref_mask=ref_mask,
                               conditioning_scale=conditioning_scale)
        eps = unet(xin, t, ctx_b, down_block_additional_residuals=down, mid_block_additional_residual=mid).sample
        if guided:
            eu, ec = eps.chunk(2)
            res.eps_noref.append(eu)
            res.eps_ref.append(ec)
            eps = eu + ref_guidance * (ec - eu)
        elif refs is not None:
            res.eps_ref.append(eps)
        else:
            res.eps_noref.append(eps)
        res.eps.append(eps)
        x = sched.step(eps, t, x).prev_sample
        res.latents.append(x)
    if x0_base == "prev":
        x = x + chain.z_prev
    elif x0_base != "none":
        raise ValueError(f"x0_base {x0_base!r} (none or prev)")
    res.latent = x
    res.decoded = vae.decode(x / vae.config.scaling_factor).sample
    res.image = (res.decoded / 2 + 0.5).clamp(0, 1)
    return res
