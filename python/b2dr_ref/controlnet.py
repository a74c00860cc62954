"""The Bench2Drive-R ControlNet (docs/b2dr_controlnet.md), on top of diffusers' ControlNetModel.

``B2DRControlNetModel`` subclasses ``diffusers.ControlNetModel``: every standard part keeps diffusers' own module
and parameter names (conv_in, time_proj/time_embedding, controlnet_cond_embedding, down_blocks, mid_block,
controlnet_down_blocks, controlnet_mid_block), and the B2D-R parts are added beside them:

- ``noise_embedding`` (``TimestepEmbedding(C_0, 4 C_0)``): the previous frame's noise level, added to the time embedding;
- ``ref_encoder`` (conv_in, blocks.{i}.resnet, blocks.{i}.downsample): reference latents -> features per down block;
- ``pos_embed.{j}`` (conv_1, conv_2): the PETR geometry -> channels of Ref-Attn location j;
- ``ref_attn.{j}`` (norm, to_q, to_k, to_v, to_out.0): residual cross-attention to the two references.

The forward loop is our own (diffusers' ControlNetModel.forward is not called and not patched); it follows diffusers'
loop step by step and inserts the B2D-R parts where the contract says.
"""

from __future__ import annotations

import inspect
import json
import math
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import nn

from diffusers import ControlNetModel
from diffusers.configuration_utils import register_to_config
from diffusers.models.controlnets.controlnet import ControlNetOutput
from diffusers.models.embeddings import TimestepEmbedding
from diffusers.models.resnet import ResnetBlock2D

CLASS_NAME = "B2DRControlNetModel"
CONFIG_NAME = "config.json"
WEIGHTS_NAME = "diffusion_pytorch_model.safetensors"

MASK_CHANNELS = [
    "car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle", "bicycle",
    "traffic_cone", "barrier", "drivable_area", "lane", "crosswalk", "lane_divider", "road_boundary",
]
# the previous-frame warp's depth cap, metres (b2dr_ref/warp.py); 0 turns the warp off
MAX_WARP_DEPTH = 1000.0
PE_POSITION_RANGE = [-61.2, -61.2, -10.0, 61.2, 61.2, 10.0]
PREV_SOURCES = ("previous", "reference", "composite")

# The B2D-R keys of controlnet/config.json and their defaults (contract section 5). None = derived (see __init__).
B2DR_DEFAULTS: Dict[str, Any] = {
    "mask_channels": MASK_CHANNELS,
    "prev_noise_level": 200,
    "prev_noise_max": 400,
    "prev_blur_sigma": 1.0,
    "prev_warp_max_depth": 0.0,
    "prev_source": "previous",
    "ref_encoder_channels": None,
    "ref_attn": None,
    "pe_depth_num": 64,
    "pe_depth_start": 1.0,
    "pe_position_range": PE_POSITION_RANGE,
    "ref_dropout": 0.2,
}

# diffusers ControlNetModel's own config keys (its __init__ parameters, this diffusers version).
PLAIN_KEYS: List[str] = [p for p in inspect.signature(ControlNetModel.__init__).parameters if p != "self"]

# diffusers options whose non-default values add parts our forward loop does not implement.
_UNSUPPORTED = {
    "encoder_hid_dim": None, "encoder_hid_dim_type": None, "class_embed_type": None, "num_class_embeds": None,
    "addition_embed_type": None, "addition_time_embed_dim": None, "projection_class_embeddings_input_dim": None,
}


class ConfigError(ValueError):
    """A B2D-R ControlNet config that is not valid (unknown key, bad value)."""


def locations(n_blocks: int) -> List[str]:
    """All Ref-Attn locations in their canonical order: down.0 .. down.{B-1}, mid."""
    return [f"down.{i}" for i in range(n_blocks)] + ["mid"]


# ---------------------------------------------------------------------------------------------------------------
# B2D-R parts
# ---------------------------------------------------------------------------------------------------------------


class RefEncoderBlock(nn.Module):
    """``ref_encoder.blocks.{i}``: ResnetBlock2D (no time embedding), then a stride-2 conv3x3 (all blocks but the last)."""

    def __init__(self, cin: int, cout: int, groups: int, eps: float, act_fn: str, downsample: bool):
        super().__init__()
        self.resnet = ResnetBlock2D(in_channels=cin, out_channels=cout, temb_channels=None, groups=groups, eps=eps,
                                    non_linearity=act_fn)
        self.downsample = nn.Conv2d(cout, cout, 3, stride=2, padding=1) if downsample else None

    def forward(self, x):
        x = self.resnet(x, None)
        if self.downsample is not None:
            x = self.downsample(x)
        return x


class ReferenceEncoder(nn.Module):
    """``ref_encoder``: reference latent (M, 4, h_0, w_0) -> [F_0 .. F_{B-1}], F_i of shape (M, R_i, h_{min(i+1,B-1)}, ..)."""

    def __init__(self, channels: Sequence[int], groups: int, eps: float, act_fn: str, latent_channels: int = 4):
        super().__init__()
        self.conv_in = nn.Conv2d(latent_channels, channels[0], 3, padding=1)
        blocks = []
        for i, c in enumerate(channels):
            cin = channels[i - 1] if i > 0 else channels[0]
            blocks.append(RefEncoderBlock(cin, c, groups, eps, act_fn, downsample=i < len(channels) - 1))
        self.blocks = nn.ModuleList(blocks)

    def forward(self, z) -> List[torch.Tensor]:
        x = self.conv_in(z)
        feats = []
        for b in self.blocks:
            x = b(x)
            feats.append(x)
        return feats


class PosEmbed(nn.Module):
    """``pos_embed.{j}``: conv1x1 3D -> 4C, ReLU, conv1x1 4C -> C (both with bias)."""

    def __init__(self, in_channels: int, channels: int):
        super().__init__()
        self.conv_1 = nn.Conv2d(in_channels, 4 * channels, 1)
        self.conv_2 = nn.Conv2d(4 * channels, channels, 1)

    def forward(self, pe):
        """pe: (..., 3D, h, w) -> (..., C, h, w) (leading dims flattened into the batch)."""
        lead = pe.shape[:-3]
        x = pe.reshape((-1,) + tuple(pe.shape[-3:]))
        x = self.conv_2(F.relu(self.conv_1(x)))
        return x.reshape(tuple(lead) + tuple(x.shape[1:]))


class RefAttention(nn.Module):
    """``ref_attn.{j}``: H' = H + to_out.0(MHA(Q = to_q(norm(H) + P_cur), K = to_k([F^a + P^a; F^b + P^b]),
    V = to_v([F^a; F^b])))."""

    def __init__(self, channels: int, heads: int, groups: int, eps: float):
        super().__init__()
        if channels % heads:
            raise ConfigError(f"Ref-Attn: {channels} channels do not split into {heads} heads")
        self.heads = heads
        self.norm = nn.GroupNorm(groups, channels, eps=eps, affine=True)
        self.to_q = nn.Linear(channels, channels, bias=False)
        self.to_k = nn.Linear(channels, channels, bias=False)
        self.to_v = nn.Linear(channels, channels, bias=False)
        self.to_out = nn.ModuleList([nn.Linear(channels, channels, bias=True)])

    @staticmethod
    def tokens(x):
        """(B, C, h, w) -> (B, h w, C), row-major h, w."""
        return x.flatten(2).transpose(1, 2)

    def forward(self, h, feats, p_cur, p_ref):
        """h: (B, C, h, w); feats, p_ref: (B, 2, C, h, w) (front, rear); p_cur: (B, C, h, w). Returns H'."""
        b, c, hh, ww = h.shape
        q = self.to_q(self.tokens(self.norm(h) + p_cur))
        k = self.to_k(torch.cat([self.tokens(feats[:, r] + p_ref[:, r]) for r in range(2)], dim=1))
        v = self.to_v(torch.cat([self.tokens(feats[:, r]) for r in range(2)], dim=1))
        d = c // self.heads
        q, k, v = (x.reshape(b, -1, self.heads, d).transpose(1, 2) for x in (q, k, v))
        a = F.scaled_dot_product_attention(q, k, v, scale=1.0 / math.sqrt(d))
        a = a.transpose(1, 2).reshape(b, hh * ww, c)
        out = self.to_out[0](a)
        return h + out.transpose(1, 2).reshape(b, c, hh, ww)


@dataclass
class References:
    """Per-frame reference inputs of the Ref-Attn locations (index j = position in ``config.ref_attn``).

    ``features[j]``: (M, 2, C_j, h_j, w_j) reference-encoder features (front, rear); ``p_cur[j]``: (M, C_j, h_j, w_j)
    and ``p_ref[j]``: (M, 2, C_j, h_j, w_j) PE-MLP outputs. M = the rows that use references (see ``ref_mask``).
    Build it once per frame with ``B2DRControlNetModel.prepare_references``.
    """

    features: List[torch.Tensor]
    p_cur: List[torch.Tensor]
    p_ref: List[torch.Tensor]

    @property
    def rows(self) -> int:
        return self.features[0].shape[0] if self.features else 0


@dataclass
class ReferenceInputs:
    """Raw per-frame reference inputs: latents (M, 2, 4, h_0, w_0) (front, rear; VAE mean x scaling) and the PE
    geometry per location, pe_cur[j] (M, 3D, h_j, w_j), pe_ref[j] (M, 2, 3D, h_j, w_j). forward() accepts it and
    runs prepare_references (better: call prepare_references once per frame and pass the References)."""

    latents: torch.Tensor
    pe_cur: List[torch.Tensor]
    pe_ref: List[torch.Tensor]


# ---------------------------------------------------------------------------------------------------------------


class B2DRControlNetModel(ControlNetModel):
    """diffusers ControlNetModel + the B2D-R parts (docs/b2dr_controlnet.md). Defaults: diffusers' (SD1.5), except
    ``in_channels = 8`` and ``conditioning_channels = 15``."""

    @register_to_config
    def __init__(
        self,
        in_channels: int = 8,
        conditioning_channels: int = 15,
        flip_sin_to_cos: bool = True,
        freq_shift: int = 0,
        down_block_types: Tuple[str, ...] = ("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                             "DownBlock2D"),
        mid_block_type: Optional[str] = "UNetMidBlock2DCrossAttn",
        only_cross_attention=False,
        block_out_channels: Tuple[int, ...] = (320, 640, 1280, 1280),
        layers_per_block: int = 2,
        downsample_padding: int = 1,
        mid_block_scale_factor: float = 1,
        act_fn: str = "silu",
        norm_num_groups: Optional[int] = 32,
        norm_eps: float = 1e-5,
        cross_attention_dim: int = 1280,
        transformer_layers_per_block=1,
        encoder_hid_dim: Optional[int] = None,
        encoder_hid_dim_type: Optional[str] = None,
        attention_head_dim=8,
        num_attention_heads=None,
        use_linear_projection: bool = False,
        class_embed_type: Optional[str] = None,
        addition_embed_type: Optional[str] = None,
        addition_time_embed_dim: Optional[int] = None,
        num_class_embeds: Optional[int] = None,
        upcast_attention: bool = False,
        resnet_time_scale_shift: str = "default",
        projection_class_embeddings_input_dim: Optional[int] = None,
        controlnet_conditioning_channel_order: str = "rgb",
        conditioning_embedding_out_channels: Optional[Tuple[int, ...]] = (16, 32, 96, 256),
        global_pool_conditions: bool = False,
        addition_embed_type_num_heads: int = 64,
        # --- B2D-R keys (contract section 5) ---
        mask_channels: Sequence[str] = tuple(MASK_CHANNELS),
        prev_noise_level: int = 200,
        prev_noise_max: int = 400,
        prev_blur_sigma: float = 1.0,
        prev_warp_max_depth: float = 0.0,
        prev_source: str = "previous",
        ref_encoder_channels: Optional[Sequence[int]] = None,
        ref_attn: Optional[Sequence[str]] = None,
        pe_depth_num: int = 64,
        pe_depth_start: float = 1.0,
        pe_position_range: Sequence[float] = tuple(PE_POSITION_RANGE),
        ref_dropout: float = 0.2,
    ):
        n_blocks = len(block_out_channels)
        # ---- validation of the values the B2D-R forward relies on ----
        # [x_t, z_prev]: twice the latent channels (8 for SD1.5's 4-channel VAE)
        if in_channels < 2 or in_channels % 2:
            raise ConfigError(f"{CLASS_NAME} config: in_channels must be 2 x the latent channels ([x_t, z_prev]), "
                              f"got {in_channels}")
        mask_channels = list(mask_channels)
        if conditioning_channels != len(mask_channels):
            raise ConfigError(f"{CLASS_NAME} config: conditioning_channels {conditioning_channels} != "
                              f"len(mask_channels) {len(mask_channels)}")
        if len(set(mask_channels)) != len(mask_channels):
            raise ConfigError(f"{CLASS_NAME} config: mask_channels has duplicates: {mask_channels}")
        if controlnet_conditioning_channel_order != "rgb":
            raise ConfigError(f"{CLASS_NAME} config: controlnet_conditioning_channel_order must be \"rgb\"")
        if global_pool_conditions:
            raise ConfigError(f"{CLASS_NAME} config: global_pool_conditions must be false")
        args = dict(locals())
        for k, default in _UNSUPPORTED.items():
            if args[k] != default:
                raise ConfigError(f"{CLASS_NAME} config: key `{k}` = {args[k]!r} is not supported (only {default!r})")
        if ref_encoder_channels is None:
            ref_encoder_channels = list(block_out_channels)
        ref_encoder_channels = [int(c) for c in ref_encoder_channels]
        if ref_encoder_channels != [int(c) for c in block_out_channels]:
            raise ConfigError(f"{CLASS_NAME} config: ref_encoder_channels {ref_encoder_channels} must equal "
                              f"block_out_channels {list(block_out_channels)}")
        canon = locations(n_blocks)
        if ref_attn is None:
            ref_attn = canon
        ref_attn = [str(x) for x in ref_attn]
        for loc in ref_attn:
            if loc not in canon:
                raise ConfigError(f"{CLASS_NAME} config: ref_attn location `{loc}` unknown (have {canon})")
        if ref_attn != [c for c in canon if c in ref_attn]:
            raise ConfigError(f"{CLASS_NAME} config: ref_attn {ref_attn} must be a subset of {canon} in that order, "
                              "without repeats")
        if int(pe_depth_num) < 1:
            raise ConfigError(f"{CLASS_NAME} config: pe_depth_num must be >= 1")
        pr = [float(v) for v in pe_position_range]
        if len(pr) != 6 or not (pr[3] > pr[0] and pr[4] > pr[1] and pr[5] > pr[2]):
            raise ConfigError(f"{CLASS_NAME} config: pe_position_range {pr} must be (lo_xyz, hi_xyz) with hi > lo")
        if not 0 <= int(prev_noise_level) <= 999 or not 0 <= int(prev_noise_max) <= 999:
            raise ConfigError(f"{CLASS_NAME} config: prev_noise_level / prev_noise_max must lie in 0..999")
        if not float(prev_blur_sigma) > 0:
            raise ConfigError(f"{CLASS_NAME} config: prev_blur_sigma must be > 0")
        # 0: the previous frame as recorded; D > 0: warped to the current pose over the ground (b2dr_ref/warp.py)
        if not 0.0 <= float(prev_warp_max_depth) <= MAX_WARP_DEPTH:
            raise ConfigError(f"{CLASS_NAME} config: prev_warp_max_depth must lie in [0, {MAX_WARP_DEPTH:g}] m "
                              "(0: no warp)")
        # where a rollout's previous-frame input comes from (the engine's PrevSource): the frame rendered before,
        # or a retrieved reference warped to the current pose (src/render/warp.rs reference_base_choice), or that
        # reference with the agents' pixels from the frame rendered before (src/eval/prev_base.rs)
        if prev_source not in PREV_SOURCES:
            raise ConfigError(f"{CLASS_NAME} config: prev_source {prev_source!r} must be one of {PREV_SOURCES}")
        if prev_source != "previous" and not float(prev_warp_max_depth) > 0:
            raise ConfigError(f"{CLASS_NAME} config: prev_source {prev_source!r} needs prev_warp_max_depth > 0")
        if not 0.0 <= float(ref_dropout) <= 1.0:
            raise ConfigError(f"{CLASS_NAME} config: ref_dropout must lie in [0, 1]")

        plain = {k: args[k] for k in PLAIN_KEYS}
        super().__init__(**plain)
        # the resolved values are what config.json stores
        self.register_to_config(ref_encoder_channels=ref_encoder_channels, ref_attn=ref_attn,
                                 mask_channels=mask_channels, pe_position_range=pr)

        c0 = block_out_channels[0]
        self.noise_embedding = TimestepEmbedding(c0, 4 * c0, act_fn=act_fn)
        self.ref_encoder = ReferenceEncoder(ref_encoder_channels, norm_num_groups, norm_eps, act_fn,
                                            latent_channels=in_channels // 2)
        heads = num_attention_heads or attention_head_dim
        if isinstance(heads, int):
            heads = [heads] * n_blocks
        heads = list(heads)
        pos, attn = [], []
        for loc in ref_attn:
            i = n_blocks - 1 if loc == "mid" else int(loc.split(".")[1])
            c = block_out_channels[i]
            pos.append(PosEmbed(3 * int(pe_depth_num), c))
            attn.append(RefAttention(c, heads[i], norm_num_groups, norm_eps))
        self.pos_embed = nn.ModuleList(pos)
        # `ref_attn` is also a config key (diffusers' ConfigMixin.__getattr__ would answer the config value):
        # the module is reached through `ref_attn_modules`.
        self.ref_attn = nn.ModuleList(attn)
        self.zero_init_new_outputs()

    @property
    def latent_channels(self) -> int:
        """C: the VAE's latent channels (x_t and z_prev each have C; in_channels = 2 C)."""
        return int(self.config.in_channels) // 2

    # -----------------------------------------------------------------------------------------------------------

    @torch.no_grad()
    def zero_init_new_outputs(self):
        """Contract section 1: conv_in's weights for input channels C..2C (z_prev; C = 4 for SD1.5),
        noise_embedding.linear_2, every ref_attn.{j}.to_out.0 are zero, so a fresh model equals the plain
        ControlNet on x_t."""
        self.conv_in.weight[:, self.latent_channels:].zero_()
        nn.init.zeros_(self.noise_embedding.linear_2.weight)
        nn.init.zeros_(self.noise_embedding.linear_2.bias)
        for a in self.ref_attn_modules:
            nn.init.zeros_(a.to_out[0].weight)
            nn.init.zeros_(a.to_out[0].bias)

    def zero_init_names(self) -> List[str]:
        """state_dict names of the tensors that zero_init_new_outputs touches (conv_in.weight only partly)."""
        names = ["conv_in.weight", "noise_embedding.linear_2.weight", "noise_embedding.linear_2.bias"]
        for j in range(len(self.ref_attn_modules)):
            names += [f"ref_attn.{j}.to_out.0.weight", f"ref_attn.{j}.to_out.0.bias"]
        return names

    @property
    def ref_attn_modules(self) -> nn.ModuleList:
        """The ``ref_attn`` ModuleList (``self.ref_attn`` is shadowed by the config key of the same name)."""
        return self._modules["ref_attn"]

    @property
    def n_blocks(self) -> int:
        return len(self.config.block_out_channels)

    def location_index(self, loc: str) -> Optional[int]:
        ra = list(self.config.ref_attn)
        return ra.index(loc) if loc in ra else None

    def location_block(self, j: int) -> int:
        """The down block whose channels / encoder features location j uses (mid: the last)."""
        loc = self.config.ref_attn[j]
        return self.n_blocks - 1 if loc == "mid" else int(loc.split(".")[1])

    # -----------------------------------------------------------------------------------------------------------
    # Config I/O
    # -----------------------------------------------------------------------------------------------------------

    @classmethod
    def config_keys(cls) -> List[str]:
        return PLAIN_KEYS + list(B2DR_DEFAULTS)

    @classmethod
    def check_config(cls, config: Dict[str, Any], where: str = "config") -> Dict[str, Any]:
        """Keys of a config dict -> init kwargs. Keys starting with `_` are metadata (`_class_name`, when present,
        must be B2DRControlNetModel); any other key must be a ControlNetModel or B2D-R key."""
        allowed = set(cls.config_keys())
        out = {}
        for k, v in config.items():
            if k.startswith("_"):
                if k == "_class_name" and v != CLASS_NAME:
                    raise ConfigError(f"{where}: _class_name is {v!r}, not {CLASS_NAME!r}")
                continue
            if k not in allowed:
                raise ConfigError(f"{where}: unknown key `{k}` (not a ControlNetModel or B2D-R ControlNet key)")
            out[k] = v
        return out

    @classmethod
    def from_config(cls, config: Dict[str, Any] = None, **kwargs) -> "B2DRControlNetModel":
        cfg = dict(config or {})
        cfg.update(kwargs)
        return cls(**cls.check_config(cfg))

    def config_dict(self) -> Dict[str, Any]:
        """The config as config.json stores it (diffusers-style, `_class_name` B2DRControlNetModel)."""
        import diffusers

        d = {"_class_name": CLASS_NAME, "_diffusers_version": diffusers.__version__}
        for k in self.config_keys():
            v = self.config[k]
            d[k] = list(v) if isinstance(v, tuple) else v
        return json.loads(json.dumps(d))

    def save_pretrained(self, save_directory: str, dtype: torch.dtype = torch.float32, **_ignored):
        """Writes config.json + diffusion_pytorch_model.safetensors (diffusers layout)."""
        from safetensors.torch import save_file

        os.makedirs(save_directory, exist_ok=True)
        with open(os.path.join(save_directory, CONFIG_NAME), "w") as f:
            json.dump(self.config_dict(), f, indent=2, sort_keys=True)
        sd = {k: v.detach().to(dtype).contiguous() for k, v in self.state_dict().items()}
        save_file(sd, os.path.join(save_directory, WEIGHTS_NAME), metadata={"format": "pt"})

    @classmethod
    def from_pretrained(cls, directory: str, subfolder: Optional[str] = None,
                        torch_dtype: Optional[torch.dtype] = None) -> "B2DRControlNetModel":
        """Reads a folder written by save_pretrained (strict: unknown config keys, missing or extra tensors fail).
        Weights stored in f16 are widened to f32 unless torch_dtype says otherwise."""
        from safetensors.torch import load_file

        if subfolder:
            directory = os.path.join(directory, subfolder)
        path = os.path.join(directory, CONFIG_NAME)
        with open(path) as f:
            cfg = json.load(f)
        if cfg.get("_class_name") != CLASS_NAME:
            raise ConfigError(f"{path}: _class_name is {cfg.get('_class_name')!r}, not {CLASS_NAME!r}")
        model = cls(**cls.check_config(cfg, where=path))
        sd = load_file(os.path.join(directory, WEIGHTS_NAME))
        sd = {k: v.to(torch.float32) for k, v in sd.items()}
        model.load_state_dict(sd, strict=True)
        if torch_dtype is not None:
            model = model.to(torch_dtype)
        return model.eval()

    @classmethod
    def from_unet(cls, unet, conditioning_embedding_out_channels: Optional[Sequence[int]] = (16, 32, 96, 256),
                  load_weights_from_unet: bool = True, **b2dr_keys) -> "B2DRControlNetModel":
        """A fresh B2D-R ControlNet with a UNet's encoder (diffusers ControlNetModel.from_unet, then conv_in widened to
        8 input channels with zero weights on 4..8; the B2D-R parts fresh). b2dr_keys: the B2D-R config keys."""
        for k in b2dr_keys:
            if k not in B2DR_DEFAULTS:
                raise ConfigError(f"{CLASS_NAME}.from_unet: unknown key `{k}` (not a B2D-R key)")
        n_masks = len(b2dr_keys.get("mask_channels", MASK_CHANNELS))
        plain = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=conditioning_embedding_out_channels,
                                          load_weights_from_unet=load_weights_from_unet, conditioning_channels=n_masks)
        cfg = {k: v for k, v in plain.config.items() if not k.startswith("_")}
        cfg.update(in_channels=2 * int(unet.config.in_channels), **b2dr_keys)
        model = cls.from_config(cfg)
        model.load_plain_weights(plain.state_dict())
        return model

    def plain_config(self) -> Dict[str, Any]:
        """The diffusers ControlNetModel config of the standard part on x_t alone (in_channels C)."""
        d = {k: self.config[k] for k in PLAIN_KEYS}
        d["in_channels"] = self.latent_channels
        return d

    @torch.no_grad()
    def load_plain_weights(self, plain_state_dict: Dict[str, torch.Tensor]):
        """Copies a plain (in_channels C) ControlNet's weights in; conv_in's channels C..2C stay as they are."""
        own = self.state_dict()
        for k, v in plain_state_dict.items():
            if k == "conv_in.weight":
                own[k][:, :self.latent_channels].copy_(v)
            else:
                own[k].copy_(v)

    # -----------------------------------------------------------------------------------------------------------
    # Per-frame parts
    # -----------------------------------------------------------------------------------------------------------

    def noise_embed(self, noise_level, batch: int, dtype=torch.float32) -> torch.Tensor:
        """Contract 2a: noise_embedding(time_proj(n)), (batch, 4 C_0)."""
        n = noise_level
        if not torch.is_tensor(n):
            n = torch.tensor([int(n)], dtype=torch.int64)
        elif n.dim() == 0:
            n = n[None]
        n = n.expand(batch)
        return self.noise_embedding(self.time_proj(n).to(dtype))

    def ref_encoder_features(self, latents: torch.Tensor) -> List[torch.Tensor]:
        """(M, 4, h_0, w_0) -> [F_0 .. F_{B-1}]."""
        return self.ref_encoder(latents)

    def encode_references(self, ref_latents: torch.Tensor) -> List[torch.Tensor]:
        """ref_latents (N, 2, 4, h, w) (front, rear) -> per Ref-Attn location j: (N, 2, C_j, h_j, w_j)."""
        n = ref_latents.shape[0]
        feats = self.ref_encoder(ref_latents.reshape((2 * n,) + tuple(ref_latents.shape[2:])))
        out = []
        for j in range(len(self.ref_attn_modules)):
            f = feats[self.location_block(j)]
            out.append(f.reshape((n, 2) + tuple(f.shape[1:])))
        return out

    def pos_embed_at(self, j: int, pe: torch.Tensor) -> torch.Tensor:
        """PE MLP of location j: (..., 3D, h, w) -> (..., C_j, h, w)."""
        return self.pos_embed[j](pe)

    def prepare_references(self, ref_latents: torch.Tensor, pe_cur: Sequence[torch.Tensor],
                           pe_ref: Sequence[torch.Tensor]) -> References:
        """Once per frame: reference features and PE-MLP outputs of every location."""
        nl = len(self.ref_attn_modules)
        if len(pe_cur) != nl or len(pe_ref) != nl:
            raise ValueError(f"prepare_references: {nl} Ref-Attn locations, got {len(pe_cur)} pe_cur / "
                             f"{len(pe_ref)} pe_ref")
        feats = self.encode_references(ref_latents)
        return References(features=feats, p_cur=[self.pos_embed[j](pe_cur[j]) for j in range(nl)],
                          p_ref=[self.pos_embed[j](pe_ref[j]) for j in range(nl)])

    def apply_ref_attn(self, j: int, h: torch.Tensor, refs: Optional[References],
                       ref_mask: Optional[torch.Tensor]) -> torch.Tensor:
        """H' of location j. Rows without references (ref_mask False, or refs None) keep H exactly (contract 2e)."""
        if refs is None:
            return h
        args = (refs.features[j], refs.p_cur[j], refs.p_ref[j])
        for a in args:
            if a.shape[-2:] != h.shape[-2:] or a.shape[0] != refs.rows:
                raise ValueError(f"Ref-Attn {self.config.ref_attn[j]}: reference input {tuple(a.shape)} does not fit "
                                 f"H {tuple(h.shape)}")
        if ref_mask is None:
            if refs.rows != h.shape[0]:
                raise ValueError(f"Ref-Attn: {refs.rows} reference rows for a batch of {h.shape[0]}")
            return self.ref_attn_modules[j](h, *args)
        idx = torch.nonzero(ref_mask.to(torch.bool), as_tuple=False).reshape(-1)
        if idx.numel() != refs.rows:
            raise ValueError(f"Ref-Attn: ref_mask selects {idx.numel()} rows, references have {refs.rows}")
        if idx.numel() == 0:
            return h
        out = h.clone()
        out[idx] = self.ref_attn_modules[j](h[idx], *args)
        return out

    # -----------------------------------------------------------------------------------------------------------

    def forward(
        self,
        sample: torch.Tensor,
        timestep,
        encoder_hidden_states: torch.Tensor,
        controlnet_cond: torch.Tensor,
        prev_latent: torch.Tensor,
        noise_level,
        refs=None,
        conditioning_scale: float = 1.0,
        ref_mask: Optional[torch.Tensor] = None,
        return_dict: bool = False,
    ):
        """sample (B, 4, h, w) = x_t; controlnet_cond (B, 15, H, W) masks; prev_latent (B, 4, h, w) the NOISED z_prev;
        noise_level: int or (B,) ints; refs: References or ReferenceInputs (None = no references: every Ref-Attn
        is skipped);
        ref_mask: optional (B,) bool, the rows that use references (refs then holds exactly those rows, in order).

        Returns (down residuals (list of 3 B + 1 ... tensors, as diffusers), mid residual), or ControlNetOutput
        with return_dict=True.
        """
        if isinstance(refs, ReferenceInputs):
            refs = self.prepare_references(refs.latents, refs.pe_cur, refs.pe_ref)
        # 1. time (diffusers ControlNetModel.forward step 1) + the noise-level embedding (contract 2a)
        timesteps = timestep
        if not torch.is_tensor(timesteps):
            dtype = torch.float64 if isinstance(timestep, float) else torch.int64
            timesteps = torch.tensor([timesteps], dtype=dtype, device=sample.device)
        elif len(timesteps.shape) == 0:
            timesteps = timesteps[None].to(sample.device)
        timesteps = timesteps.expand(sample.shape[0])
        t_emb = self.time_proj(timesteps).to(dtype=sample.dtype)
        emb = self.time_embedding(t_emb)
        emb = emb + self.noise_embed(noise_level, sample.shape[0], sample.dtype)

        # 2. pre-process: conv_in([x_t, z_prev]) + conditioning embedding
        x = self.conv_in(torch.cat([sample, prev_latent], dim=1))
        x = x + self.controlnet_cond_embedding(controlnet_cond)

        # 3. down, with Ref-Attn after down block i (its output replaces the block's last skip too)
        res = (x,)
        for i, block in enumerate(self.down_blocks):
            if getattr(block, "has_cross_attention", False):
                x, r = block(hidden_states=x, temb=emb, encoder_hidden_states=encoder_hidden_states)
            else:
                x, r = block(hidden_states=x, temb=emb)
            j = self.location_index(f"down.{i}")
            if j is not None and refs is not None:
                assert r[-1] is x, "diffusers down block: the last skip is the block output"
                x = self.apply_ref_attn(j, x, refs, ref_mask)
                r = tuple(r[:-1]) + (x,)
            res += tuple(r)

        # 4. mid, then its Ref-Attn
        if getattr(self.mid_block, "has_cross_attention", False):
            x = self.mid_block(x, emb, encoder_hidden_states=encoder_hidden_states)
        else:
            x = self.mid_block(x, emb)
        j = self.location_index("mid")
        if j is not None and refs is not None:
            x = self.apply_ref_attn(j, x, refs, ref_mask)

        # 5. zero convs, 6. scaling (diffusers, guess_mode off)
        down = [blk(s) * conditioning_scale for s, blk in zip(res, self.controlnet_down_blocks)]
        mid = self.controlnet_mid_block(x) * conditioning_scale
        if return_dict:
            return ControlNetOutput(down_block_res_samples=down, mid_block_res_sample=mid)
        return down, mid
