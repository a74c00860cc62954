"""The B2D-R model package folder (contract section 5):

    b2dr.json, unet/, controlnet/, vae/ (diffusers folders: config.json + diffusion_pytorch_model.safetensors),
    context.safetensors ("cond": (77, D) or (n_cameras, 77, D)).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Dict, List, Sequence

import torch

from .controlnet import CLASS_NAME, CONFIG_NAME, B2DRControlNetModel

FORMAT = "b2dr-model"
VERSION = 1
META_KEYS = {"format", "version", "render_size", "cameras", "sampler", "steps", "ref_guidance", "dtype"}
# absent: prediction_type "epsilon", x0_base "none" (packages written before they existed)
OPTIONAL_META_KEYS = {"prediction_type", "x0_base"}
PREDICTION_TYPES = ("epsilon", "v_prediction")
# what the sampled x_0 is added to before decoding: nothing, or the previous frame's clean (blurred) latent
X0_BASES = ("none", "prev")
DTYPES = {"f32": torch.float32, "f16": torch.float16}


class PackageError(ValueError):
    pass


@dataclass
class B2DRPackage:
    meta: Dict[str, Any]
    unet: Any
    controlnet: Any          # B2DRControlNetModel, or a plain diffusers ControlNetModel
    vae: Any
    context: torch.Tensor    # (77, D) or (n_cameras, 77, D)


def make_meta(render_size: Sequence[int], cameras: Sequence[str], sampler: str = "unipc", steps: int = 20,
              ref_guidance: float = 2.0, dtype: str = "f32", prediction_type: str = "epsilon",
              x0_base: str = "none") -> Dict[str, Any]:
    meta = {"format": FORMAT, "version": VERSION, "render_size": [int(render_size[0]), int(render_size[1])],
            "cameras": list(cameras), "sampler": sampler, "steps": int(steps), "ref_guidance": float(ref_guidance),
            "dtype": dtype, "prediction_type": prediction_type}
    if x0_base != "none":       # written only when it matters: older readers then refuse it instead of ignoring it
        meta["x0_base"] = x0_base
    check_meta(meta, "b2dr.json")
    return meta


def check_meta(meta: Dict[str, Any], where: str):
    for k in meta:
        if k not in META_KEYS | OPTIONAL_META_KEYS:
            raise PackageError(f"{where}: unknown key `{k}`")
    for k in META_KEYS:
        if k not in meta:
            raise PackageError(f"{where}: missing key `{k}`")
    if meta["format"] != FORMAT or meta["version"] != VERSION:
        raise PackageError(f"{where}: format {meta['format']!r} version {meta['version']!r}, expected "
                           f"{FORMAT!r} version {VERSION}")
    rs = meta["render_size"]
    if len(rs) != 2 or any(int(v) <= 0 for v in rs):
        raise PackageError(f"{where}: render_size {rs} must be [H, W], positive")
    if not meta["cameras"] or len(set(meta["cameras"])) != len(meta["cameras"]):
        raise PackageError(f"{where}: cameras must be a non-empty list of distinct names")
    if meta["sampler"] not in ("unipc", "ddim"):
        raise PackageError(f"{where}: sampler {meta['sampler']!r} (unipc or ddim)")
    if int(meta["steps"]) < 1:
        raise PackageError(f"{where}: steps must be >= 1")
    if meta.get("prediction_type", "epsilon") not in PREDICTION_TYPES:
        raise PackageError(f"{where}: prediction_type {meta['prediction_type']!r} ({' or '.join(PREDICTION_TYPES)})")
    if meta.get("x0_base", "none") not in X0_BASES:
        raise PackageError(f"{where}: x0_base {meta['x0_base']!r} ({' or '.join(X0_BASES)})")
    if meta["dtype"] not in DTYPES:
        raise PackageError(f"{where}: dtype {meta['dtype']!r} (f32 or f16)")


def check_context(context: torch.Tensor, cameras: Sequence[str], where: str):
    if context.dim() == 2 and context.shape[0] == 77:
        return
    if context.dim() == 3 and context.shape[0] == len(cameras) and context.shape[1] == 77:
        return
    raise PackageError(f"{where}: cond {tuple(context.shape)} must be (77, D) or ({len(cameras)}, 77, D)")


def save_package(directory: str, unet, controlnet, vae, context: torch.Tensor, meta: Dict[str, Any]):
    from safetensors.torch import save_file

    check_meta(meta, "b2dr.json")
    check_context(context, meta["cameras"], "context.safetensors")
    dt = DTYPES[meta["dtype"]]
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, "b2dr.json"), "w") as f:
        json.dump(meta, f, indent=2)
    for name, m in (("unet", unet), ("vae", vae)):
        m.to(dt).save_pretrained(os.path.join(directory, name), safe_serialization=True)
        m.to(torch.float32)
    if isinstance(controlnet, B2DRControlNetModel):
        controlnet.save_pretrained(os.path.join(directory, "controlnet"), dtype=dt)
    else:
        controlnet.to(dt).save_pretrained(os.path.join(directory, "controlnet"), safe_serialization=True)
        controlnet.to(torch.float32)
    save_file({"cond": context.detach().to(dt).contiguous()}, os.path.join(directory, "context.safetensors"))


def load_controlnet(directory: str):
    """B2DRControlNetModel when config.json says so, else diffusers' plain ControlNetModel."""
    from diffusers import ControlNetModel

    with open(os.path.join(directory, CONFIG_NAME)) as f:
        cls = json.load(f).get("_class_name")
    if cls == CLASS_NAME:
        return B2DRControlNetModel.from_pretrained(directory)
    if cls not in (None, "ControlNetModel"):
        raise PackageError(f"{directory}/{CONFIG_NAME}: _class_name {cls!r} (ControlNetModel or {CLASS_NAME})")
    return ControlNetModel.from_pretrained(directory, torch_dtype=torch.float32).eval()


def load_package(directory: str) -> B2DRPackage:
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from safetensors.torch import load_file

    where = os.path.join(directory, "b2dr.json")
    with open(where) as f:
        meta = json.load(f)
    check_meta(meta, where)
    unet = UNet2DConditionModel.from_pretrained(os.path.join(directory, "unet"), torch_dtype=torch.float32).eval()
    vae = AutoencoderKL.from_pretrained(os.path.join(directory, "vae"), torch_dtype=torch.float32).eval()
    controlnet = load_controlnet(os.path.join(directory, "controlnet"))
    ctx_path = os.path.join(directory, "context.safetensors")
    ctx = load_file(ctx_path)
    if set(ctx) != {"cond"}:
        raise PackageError(f"{ctx_path}: tensors {sorted(ctx)}, expected only `cond`")
    context = ctx["cond"].to(torch.float32)
    check_context(context, meta["cameras"], ctx_path)
    return B2DRPackage(meta=meta, unet=unet, controlnet=controlnet, vae=vae, context=context)
