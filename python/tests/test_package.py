import json

import pytest
import torch

from b2dr_ref.controlnet import B2DRControlNetModel
from b2dr_ref.package import PackageError, load_package, make_meta, save_package

from helpers import frame_inputs


def _sd_equal(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    return list(sa) == list(sb) and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_package_roundtrip(tmp_path, models):
    ctx = torch.randn(6, 77, 32)
    cams = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    meta = make_meta([56, 104], cams, steps=3, ref_guidance=2.0)
    save_package(str(tmp_path), models["unet"], models["controlnet"], models["vae"], ctx, meta)
    for f in ("b2dr.json", "unet/config.json", "unet/diffusion_pytorch_model.safetensors", "controlnet/config.json",
              "controlnet/diffusion_pytorch_model.safetensors", "vae/config.json",
              "vae/diffusion_pytorch_model.safetensors", "context.safetensors"):
        assert (tmp_path / f).exists(), f
    assert json.loads((tmp_path / "controlnet/config.json").read_text())["_class_name"] == "B2DRControlNetModel"
    pkg = load_package(str(tmp_path))
    assert pkg.meta == meta
    assert isinstance(pkg.controlnet, B2DRControlNetModel)
    for k in ("unet", "controlnet", "vae"):
        assert _sd_equal(getattr(pkg, k), models[k]), k
    assert torch.equal(pkg.context, ctx)
    # same outputs
    fi = frame_inputs(models["controlnet"], n=1, h=4, w=6, seed=1)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4, 4, 6, generator=g)
    with torch.no_grad():
        a = models["controlnet"](x, 500, ctx[:1], fi["masks"], x, 200)[1]
        b = pkg.controlnet(x, 500, ctx[:1], fi["masks"], x, 200)[1]
    assert torch.equal(a, b)


def test_package_rejects_bad_meta(tmp_path, models):
    meta = make_meta([56, 104], ["CAM_FRONT"])
    save_package(str(tmp_path), models["unet"], models["controlnet"], models["vae"], torch.randn(77, 32), meta)
    p = tmp_path / "b2dr.json"
    d = json.loads(p.read_text())
    d["guidance"] = 3.0
    p.write_text(json.dumps(d))
    with pytest.raises(PackageError, match="unknown key `guidance`"):
        load_package(str(tmp_path))
    with pytest.raises(PackageError, match="cond"):
        save_package(str(tmp_path), models["unet"], models["controlnet"], models["vae"], torch.randn(2, 77, 32), meta)
    del d["guidance"]
    d["prediction_type"] = "sample"
    p.write_text(json.dumps(d))
    with pytest.raises(PackageError, match="prediction_type 'sample'"):
        load_package(str(tmp_path))
    # absent (packages written before the key existed) = epsilon
    del d["prediction_type"]
    p.write_text(json.dumps(d))
    assert load_package(str(tmp_path)).meta.get("prediction_type", "epsilon") == "epsilon"
    d["x0_base"] = "next"
    p.write_text(json.dumps(d))
    with pytest.raises(PackageError, match="x0_base 'next'"):
        load_package(str(tmp_path))


def test_plain_controlnet_package_loads(tmp_path, models):
    from diffusers import ControlNetModel

    plain = ControlNetModel(**models["controlnet"].plain_config()).eval()
    meta = make_meta([56, 104], ["CAM_FRONT"])
    save_package(str(tmp_path), models["unet"], plain, models["vae"], torch.randn(77, 32), meta)
    pkg = load_package(str(tmp_path))
    assert type(pkg.controlnet) is ControlNetModel and _sd_equal(pkg.controlnet, plain)
