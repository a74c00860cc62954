"""The built-in model configs: "b2dr-nano" (trained here, on CPU, from the synthetic world) and "b2dr-test" (the
tiny test config of testing.py, for smoke runs).

A config is a dict with the diffusers kwargs of the three models plus the render size and the context width:

    {"name", "render_size": [H, W], "unet": {...}, "controlnet": {...}, "vae": {...}, "context_dim": D}

b2dr-nano (docs/training.md has the measured step times):
- render 112 x 200 (latent 14 x 25; block sizes 14x25, 7x13, 4x7, 2x4);
- UNet and ControlNet: SD1.5 block structure, block_out_channels (32, 64, 64, 64), layers_per_block 1,
  CrossAttnDownBlock2D x 3 + DownBlock2D / UpBlock2D + CrossAttnUpBlock2D x 3, UNetMidBlock2DCrossAttn,
  attention heads (2, 4, 4, 4) (head dim 16 everywhere, mid 4 heads of 16), cross_attention_dim 64,
  norm_num_groups 16 (every channel count divides), eps 1e-5, silu;
- ControlNet B2D-R parts: conditioning_embedding_out_channels (8, 16, 32, 64) (factor 8, like the VAE),
  15 mask channels, reference encoder = block_out_channels, Ref-Attn at down.0..down.3 and mid, PE with 16 depth
  bins (3 D = 48 input channels of each PE MLP), prev_noise_level 200 / prev_noise_max 400, blur sigma 1,
  ref_dropout 0.2;
- VAE (AutoencoderKL): block_out_channels (16, 32, 64, 64) (4 blocks = factor 8), layers_per_block 1,
  latent_channels 4, norm_num_groups 16; its scaling_factor is measured after the VAE stage (1 / std of the
  latent means, as SD did for 0.18215);
- context: one fixed random (77, 64) embedding per camera (N(0, 1), seed 0), stored in the package.
"""

from __future__ import annotations

import copy
from typing import Any, Dict

DOWN4 = ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"]
UP4 = ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"]
DOWN3 = ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"]
UP3 = ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"]

NANO: Dict[str, Any] = {
    "name": "b2dr-nano",
    "render_size": [112, 200],
    "context_dim": 64,
    "unet": dict(block_out_channels=[32, 64, 64, 64], layers_per_block=1, cross_attention_dim=64,
                 attention_head_dim=[2, 4, 4, 4], norm_num_groups=16, in_channels=4, out_channels=4,
                 down_block_types=DOWN4, up_block_types=UP4),
    "controlnet": dict(block_out_channels=[32, 64, 64, 64], layers_per_block=1, cross_attention_dim=64,
                       attention_head_dim=[2, 4, 4, 4], norm_num_groups=16, down_block_types=DOWN4,
                       conditioning_embedding_out_channels=[8, 16, 32, 64], pe_depth_num=16,
                       prev_noise_level=200, prev_noise_max=400, prev_blur_sigma=1.0, ref_dropout=0.2),
    "vae": dict(block_out_channels=[16, 32, 64, 64], in_channels=3, out_channels=3, layers_per_block=1,
                down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
                latent_channels=4, norm_num_groups=16, scaling_factor=1.0),
}

# The test config of testing.py (3 blocks) at a 56 x 104 render (latent 7 x 13): smoke runs in seconds.
TEST: Dict[str, Any] = {
    "name": "b2dr-test",
    "render_size": [56, 104],
    "context_dim": 32,
    "unet": dict(block_out_channels=[16, 16, 32], layers_per_block=1, cross_attention_dim=32,
                 attention_head_dim=[2, 4, 8], norm_num_groups=8, in_channels=4, out_channels=4,
                 down_block_types=DOWN3, up_block_types=UP3),
    "controlnet": dict(block_out_channels=[16, 16, 32], layers_per_block=1, cross_attention_dim=32,
                       attention_head_dim=[2, 4, 8], norm_num_groups=8, down_block_types=DOWN3,
                       conditioning_embedding_out_channels=[8, 16, 16, 32], pe_depth_num=16),
    "vae": dict(block_out_channels=[8, 16, 16, 16], in_channels=3, out_channels=3, layers_per_block=1,
                down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
                latent_channels=4, norm_num_groups=4, scaling_factor=1.0),
}



def with_latent_channels(cfg: Dict[str, Any], c: int, name: str) -> Dict[str, Any]:
    """A design variant with ``c`` latent channels (VAE latent, UNet in / out); everything else unchanged."""
    d = copy.deepcopy(cfg)
    d["name"] = name
    d["vae"]["latent_channels"] = c
    d["unet"]["in_channels"] = d["unet"]["out_channels"] = c
    d["controlnet"]["in_channels"] = 2 * c
    return d


# Design variants of the renderer issue (docs/training.md "Designs"): more latent channels at the same 14 x 25
# latent (SD3 / FLUX use 16) keep thin structure through the VAE; the UNet's cost hardly changes.
NANO_Z8 = with_latent_channels(NANO, 8, "b2dr-nano-z8")
NANO_Z16 = with_latent_channels(NANO, 16, "b2dr-nano-z16")
TEST_Z8 = with_latent_channels(TEST, 8, "b2dr-test-z8")
# ... and a VAE four times as wide at full resolution (64 channels instead of 16): the committed VAE's own
# reconstructions lose lane markings and vehicles whatever its latent width (docs/training.md "Designs")
NANO_Z16_WVAE = copy.deepcopy(NANO_Z16)
NANO_Z16_WVAE["name"] = "b2dr-nano-z16-wvae"
NANO_Z16_WVAE["vae"]["block_out_channels"] = [64, 128, 128, 128]

# ... and the committed VAE's blocks with 4 groups in its GroupNorms instead of 16 (with 16 groups every group of
# the 16-channel full-resolution stage is one channel: an instance norm right before conv_out). Measured: no
# difference in loss against 16 groups (docs/training.md); it is the config the L2 gate VAE was trained in.
NANO_Z16_G4 = copy.deepcopy(NANO_Z16)
NANO_Z16_G4["name"] = "b2dr-nano-z16-g4"
NANO_Z16_G4["vae"]["norm_num_groups"] = 4

# ... and b2dr-nano at the paper's render size, 224 x 400 (latent 28 x 50: a lane marking is 2-4 pixels wide and
# a car covers several latent cells; the UNet and ControlNet cost ~4x). The same tensors as b2dr-nano (every
# tensor of a nano package loads). Measured (docs/training.md, session 23): the 4-channel L2 VAE gains nothing at
# this size, so no model was trained in it; kept for `train bench` and a GPU user's larger designs.
NANO_224 = copy.deepcopy(NANO)
NANO_224["name"] = "b2dr-nano-224"
NANO_224["render_size"] = [224, 400]

# ... and the z16 design with a UNet and ControlNet twice as wide at every level (SD3: 16-channel latents pay off only
# with larger denoisers); its step cost is in docs/training.md (session 23).
NANO_Z16_G4_W2 = copy.deepcopy(NANO_Z16_G4)
NANO_Z16_G4_W2["name"] = "b2dr-nano-z16-g4-w2"
for _part in ("unet", "controlnet"):
    NANO_Z16_G4_W2[_part]["block_out_channels"] = [64, 128, 128, 128]
    NANO_Z16_G4_W2[_part]["attention_head_dim"] = [4, 8, 8, 8]      # head dim 16, as in b2dr-nano

# ... and the z16 VAE two resnets deep per encoder level (three per decoder level, as SD's VAE) instead of one: the
# committed z16 VAE, trained on all layouts, keeps markings only on frames it was fitted to (docs/training.md,
# session 24), so capacity is the next suspect. `tools/deepen_vae.py` grows a trained z16 VAE into this shape
# with the added resnets initialised as identities (conv2 zero), so training continues from the same function.
# Measured (session 25): 1.4x a step, a little faster per step, slower per second than the 1-resnet VAE so far.
NANO_Z16_G4_D2 = copy.deepcopy(NANO_Z16_G4)
NANO_Z16_G4_D2["name"] = "b2dr-nano-z16-g4-d2"
NANO_Z16_G4_D2["vae"]["layers_per_block"] = 2

CONFIGS = {"nano": NANO, "b2dr-nano": NANO, "test": TEST, "b2dr-test": TEST, "nano-z8": NANO_Z8,
           "nano-z16": NANO_Z16, "test-z8": TEST_Z8, "nano-z16-wvae": NANO_Z16_WVAE,
           "nano-z16-g4": NANO_Z16_G4, "nano-224": NANO_224,
           "nano-z16-g4-w2": NANO_Z16_G4_W2, "nano-z16-g4-d2": NANO_Z16_G4_D2}


def get_config(name: str) -> Dict[str, Any]:
    if name not in CONFIGS:
        raise ValueError(f"unknown model config {name!r} (have {sorted(CONFIGS)})")
    return copy.deepcopy(CONFIGS[name])


def check_config(cfg: Dict[str, Any]):
    """The Rust engine's constraints: VAE factor 8; the UNet's input and output are the VAE's latent channels;
    channels divisible by the groups."""
    v = cfg["vae"]
    if len(v["block_out_channels"]) != 4:
        raise ValueError(f"{cfg['name']}: the VAE must have 4 blocks (factor 8)")
    c = v["latent_channels"]
    if cfg["unet"].get("in_channels", 4) != c or cfg["unet"].get("out_channels", 4) != c:
        raise ValueError(f"{cfg['name']}: the UNet's in / out channels must be the VAE's {c} latent channels")
    if cfg["controlnet"].get("in_channels", 8) != 2 * c:
        raise ValueError(f"{cfg['name']}: the ControlNet's in_channels must be {2 * c} ([x_t, z_prev])")
    for part in ("unet", "controlnet", "vae"):
        g = cfg[part]["norm_num_groups"]
        for c in cfg[part]["block_out_channels"]:
            if c % g:
                raise ValueError(f"{cfg['name']}: {part} channels {c} not divisible by norm_num_groups {g}")
    if cfg["unet"]["cross_attention_dim"] != cfg["context_dim"] or \
            cfg["controlnet"]["cross_attention_dim"] != cfg["context_dim"]:
        raise ValueError(f"{cfg['name']}: cross_attention_dim must equal context_dim")
    h, w = cfg["render_size"]
    if h % 8 or w % 8:
        raise ValueError(f"{cfg['name']}: render size {h}x{w} must be a multiple of 8")
