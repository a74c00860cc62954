"""Test-sized configs and weight helpers shared by python/tests and tools/make_golden_b2dr.py."""

from __future__ import annotations

import copy
from typing import Dict

import numpy as np
import torch

from .controlnet import B2DRControlNetModel

DOWN = ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"]
UP = ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"]

# "b2dr_test": UNet / ControlNet (16, 16, 32), 1 layer per block, heads (2, 4, 8) (head dims 8, 4, 4; mid 8 heads),
# context 32, 8 groups; three blocks so that the Ref-Attn locations have two different sizes (down.0 at h_1,
# down.1 / down.2 / mid at h_2);
# ControlNet conditioning embedding (8, 16, 16, 32) (factor 8, like the VAE); PE with 16 depth bins;
# VAE (8, 16, 16, 16), 1 layer per block, 4 groups (factor 8).
TEST_CONFIGS = {
    "unet": dict(block_out_channels=[16, 16, 32], layers_per_block=1, cross_attention_dim=32,
                 attention_head_dim=[2, 4, 8],
                 norm_num_groups=8, in_channels=4, out_channels=4, down_block_types=DOWN, up_block_types=UP),
    "controlnet": dict(block_out_channels=[16, 16, 32], layers_per_block=1, cross_attention_dim=32,
                       attention_head_dim=[2, 4, 8], norm_num_groups=8, down_block_types=DOWN,
                       conditioning_embedding_out_channels=[8, 16, 16, 32], pe_depth_num=16),
    "vae": dict(block_out_channels=[8, 16, 16, 16], in_channels=3, out_channels=3, layers_per_block=1,
                down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
                latent_channels=4, norm_num_groups=4),
}


def configs(latent_channels: int = 4):
    """The test configs; ``latent_channels`` C != 4: the VAE's latent, the UNet's in / out and the ControlNet's
    in_channels (2 C) follow (the design variant with more latent channels)."""
    c = copy.deepcopy(TEST_CONFIGS)
    if latent_channels != 4:
        c["vae"]["latent_channels"] = latent_channels
        c["unet"]["in_channels"] = c["unet"]["out_channels"] = latent_channels
        c["controlnet"]["in_channels"] = 2 * latent_channels
    return c


def is_norm(name: str) -> bool:
    module = name.rsplit(".", 1)[0]
    last = module.rsplit(".", 1)[-1]
    return last.startswith("norm") or last in ("conv_norm_out", "group_norm")


@torch.no_grad()
def nontrivial_init(model, seed: int):
    """As tools/make_golden_models.py: every all-zero tensor drawn uniform +-1/sqrt(fan_in), norm parameters
    perturbed by U(+-0.1). For a B2DRControlNetModel also conv_in's zeroed input channels C..2C are drawn."""
    g = torch.Generator().manual_seed(seed)
    sd = model.state_dict()
    for name, p in sd.items():
        u = torch.rand(p.shape, generator=g) * 2 - 1
        if is_norm(name):
            p.copy_((1.0 if name.endswith(".weight") else 0.0) + 0.1 * u)
        elif torch.all(p == 0):
            w = sd.get(name.replace(".bias", ".weight"), p) if name.endswith(".bias") else p
            fan_in = max(1, int(np.prod(w.shape[1:])))
            p.copy_(u / np.sqrt(fan_in))
    if isinstance(model, B2DRControlNetModel):
        w = sd["conv_in.weight"]
        fan_in = int(np.prod(w.shape[1:]))
        c = model.latent_channels
        u = torch.rand(w[:, c:].shape, generator=g) * 2 - 1
        w[:, c:].copy_(u / np.sqrt(fan_in))


def build_models(seed: int = 0, nontrivial: bool = True, latent_channels: int = 4) -> Dict[str, torch.nn.Module]:
    from diffusers import AutoencoderKL, UNet2DConditionModel

    cfg = configs(latent_channels)
    torch.manual_seed(seed)
    models = {"unet": UNet2DConditionModel(**cfg["unet"]).eval(),
              "controlnet": B2DRControlNetModel.from_config(cfg["controlnet"]).eval(),
              "vae": AutoencoderKL(**cfg["vae"]).eval()}
    if nontrivial:
        for i, k in enumerate(("unet", "controlnet", "vae")):
            nontrivial_init(models[k], seed * 10 + i + 1)
    return models
