"""Model-component goldens (imported by tools/make_golden.py; run that script, not this module).

Sets of configs:
- "tiny": b2dr-tiny (UNet (32, 64, 128, 128) x 4 heads, context 64, 8 groups; ControlNet with the same encoder and
  embedding channels (16, 32, 96, 256); VAE (32, 64, 128, 128), 2 layers, 8 groups). Its ~18 M parameters would be
  70 MB in f32 (36 MB in f16), so the weights are NOT stored: both sides generate them with b2dr's seeded generator
  (src/nn/weights.rs `Weights::random`, reproduced bit for bit by `b2dr_random` below) and the golden stores every
  tensor's fingerprint, which the Rust test checks, so both sides provably run the same weights.
- "dtest": diffusers' own test-sized configs (tests/pipelines/controlnet/test_controlnet.py dummy components:
  UNet/ControlNet (4, 8), norm_num_groups 1, context 32; VAE (4, 8), 2 groups), diffusers-initialised with torch seed
  0, then made non-trivial: zero-initialised tensors (ControlNet zero convs) drawn uniform +-1/sqrt(fan_in) and norm
  parameters perturbed by U(+-0.1). Stored as f32 safetensors (a few KB).
- "dtest_unet": tests/models/unets/test_models_unet_2d_condition.py's UNet config ((4, 8), 1 layer, 2 heads,
  context 8, 4 groups), same treatment.

Per set and latent size, one case file `case_<set>_<h>x<w>.safetensors` holds inputs (`in.*`) and diffusers' outputs
(`out.*`) of: unet, controlnet, unet with the controlnet's residuals, vae encoder, vae decoder. Cases at latent
28 x 50 are stored in f16 (inputs are rounded to f16 BEFORE diffusers runs, so they are exact; outputs carry f16
rounding, ~1e-7 normalised MSE); the other sizes in f32. models.json describes every case.
"""

import json
import os

import numpy as np
import torch
from safetensors.torch import save_file

SD_DOWN = ["CrossAttnDownBlock2D"] * 3 + ["DownBlock2D"]
SD_UP = ["UpBlock2D"] + ["CrossAttnUpBlock2D"] * 3

TINY = {
    "unet": dict(block_out_channels=[32, 64, 128, 128], cross_attention_dim=64, attention_head_dim=4,
                 layers_per_block=2, norm_num_groups=8, in_channels=4, out_channels=4,
                 down_block_types=SD_DOWN, up_block_types=SD_UP),
    "controlnet": dict(block_out_channels=[32, 64, 128, 128], cross_attention_dim=64, attention_head_dim=4,
                       layers_per_block=2, norm_num_groups=8, in_channels=4, down_block_types=SD_DOWN,
                       conditioning_channels=3, conditioning_embedding_out_channels=[16, 32, 96, 256]),
    "vae": dict(block_out_channels=[32, 64, 128, 128], in_channels=3, out_channels=3, layers_per_block=2,
                down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
                latent_channels=4, norm_num_groups=8),
}
DTEST = {
    "unet": dict(block_out_channels=[4, 8], layers_per_block=2, sample_size=32, in_channels=4, out_channels=4,
                 down_block_types=["DownBlock2D", "CrossAttnDownBlock2D"],
                 up_block_types=["CrossAttnUpBlock2D", "UpBlock2D"], cross_attention_dim=32, norm_num_groups=1),
    "controlnet": dict(block_out_channels=[4, 8], layers_per_block=2, in_channels=4,
                       down_block_types=["DownBlock2D", "CrossAttnDownBlock2D"], cross_attention_dim=32,
                       conditioning_embedding_out_channels=[16, 32], norm_num_groups=1),
    "vae": dict(block_out_channels=[4, 8], in_channels=3, out_channels=3,
                down_block_types=["DownEncoderBlock2D"] * 2, up_block_types=["UpDecoderBlock2D"] * 2,
                latent_channels=4, norm_num_groups=2),
}
DTEST_UNET = {
    "unet": dict(block_out_channels=[4, 8], norm_num_groups=4, down_block_types=["CrossAttnDownBlock2D", "DownBlock2D"],
                 up_block_types=["UpBlock2D", "CrossAttnUpBlock2D"], cross_attention_dim=8, attention_head_dim=2,
                 out_channels=4, in_channels=4, layers_per_block=1, sample_size=16),
}
SEEDS = {"unet": 1, "controlnet": 2, "vae": 3}
MASK = (1 << 64) - 1


# --------------------------------------------------------------------------------------------------------------
# b2dr's seeded weight generator (src/nn/weights.rs Weights::random), bit for bit
# --------------------------------------------------------------------------------------------------------------


def fnv1a(s):
    h = 0xCBF29CE484222325
    for b in s.encode():
        h ^= b
        h = (h * 0x100000001B3) & MASK
    return h


def uniform_pm1(key, n):
    i = np.arange(1, n + 1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = np.uint64(key) + i * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    u = (z >> np.uint64(40)).astype(np.float32) / np.float32(16777216.0)
    return np.float32(2.0) * u - np.float32(1.0)


def is_norm(name):
    module = name.rsplit(".", 1)[0]
    last = module.rsplit(".", 1)[-1]
    return last.startswith("norm") or last in ("conv_norm_out", "group_norm")


def b2dr_random(shapes, seed):
    """shapes: {name: shape}. Returns {name: float32 ndarray} equal to Weights::random(expected, seed)."""
    out = {}
    for name, shape in shapes.items():
        n = int(np.prod(shape)) if len(shape) else 1
        x = uniform_pm1(seed ^ fnv1a(name), n)
        if is_norm(name):
            base = np.float32(1.0) if name.endswith(".weight") else np.float32(0.0)
            v = base + np.float32(0.1) * x
        else:
            ws = shapes.get(name.replace(".bias", ".weight")) if name.endswith(".bias") else shape
            fan_in = max(1, int(np.prod(ws[1:]))) if ws is not None else 1
            bound = np.float32(1.0) / np.sqrt(np.float32(fan_in))
            v = x * bound
        out[name] = v.astype(np.float32).reshape(shape)
    return out


def fingerprint(a):
    bits = np.ascontiguousarray(a, dtype=np.float32).reshape(-1).view(np.uint32).astype(np.uint64)
    with np.errstate(over="ignore"):
        return int((bits * np.arange(1, bits.size + 1, dtype=np.uint64)).sum(dtype=np.uint64))


# --------------------------------------------------------------------------------------------------------------


def build(kind, cfg):
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel

    cls = {"unet": UNet2DConditionModel, "controlnet": ControlNetModel, "vae": AutoencoderKL}[kind]
    return cls(**cfg).eval()


def nontrivial_init(model, seed):
    """diffusers' init, then zero tensors drawn uniform +-1/sqrt(fan_in) and norms perturbed (see module doc)."""
    g = torch.Generator().manual_seed(seed)
    sd = model.state_dict()
    with torch.no_grad():
        for name, p in sd.items():
            u = torch.rand(p.shape, generator=g) * 2 - 1
            if is_norm(name):
                p.copy_((1.0 if name.endswith(".weight") else 0.0) + 0.1 * u)
            elif torch.all(p == 0):
                w = sd.get(name.replace(".bias", ".weight"), p) if name.endswith(".bias") else p
                fan_in = max(1, int(np.prod(w.shape[1:])))
                p.copy_(u / np.sqrt(fan_in))


def state_list(model):
    return [[k, list(v.shape)] for k, v in model.state_dict().items()]


def rnd(shape, g, dtype, lo=None, hi=None):
    x = torch.randn(shape, generator=g) if lo is None else torch.rand(shape, generator=g) * (hi - lo) + lo
    return x.to(dtype).to(torch.float32)  # exact in the storage dtype


def make_set(name, cfgs, weights_mode, sizes, out_dir, cases, sets):
    models = {k: build(k, v) for k, v in cfgs.items()}
    entry = {"configs": {}, "state_dicts": {}, "weights": {}}
    for k, m in models.items():
        entry["configs"][k] = dict(m.config)
        entry["configs"][k]["_class_name"] = type(m).__name__
        entry["state_dicts"][k] = state_list(m)
        if weights_mode == "generator":
            shapes = {n: list(v.shape) for n, v in m.state_dict().items()}
            w = b2dr_random(shapes, SEEDS[k])
            m.load_state_dict({n: torch.from_numpy(v) for n, v in w.items()}, strict=True)
            entry["weights"][k] = {"generator": "b2dr-splitmix64-v1", "seed": SEEDS[k],
                                   "fingerprints": {n: str(fingerprint(v)) for n, v in w.items()}}
        else:
            nontrivial_init(m, SEEDS[k])
            fname = f"weights_{name}_{k}.safetensors"
            save_file({n: v.contiguous() for n, v in m.state_dict().items()}, os.path.join(out_dir, fname))
            entry["weights"][k] = {"file": fname, "dtype": "F32"}
    # configs as diffusers writes them contain tuples/lists and metadata; keep JSON-clean values
    entry["configs"] = json.loads(json.dumps(entry["configs"], default=list))
    sets[name] = entry

    for (h, w, dt, batch) in sizes:
        dtype = torch.float16 if dt == "F16" else torch.float32
        g = torch.Generator().manual_seed(1000 + h * 100 + w)
        t = {}
        case = {"set": name, "latent_hw": [h, w], "batch": batch, "dtype": dt,
                "file": f"case_{name}_{h}x{w}.safetensors", "components": {}}
        with torch.no_grad():
            if "unet" in models:
                u = models["unet"]
                ctx = u.config.cross_attention_dim
                t["in.sample"] = rnd((batch, 4, h, w), g, dtype)
                t["in.timestep"] = torch.tensor([601.0, 37.0][:batch])
                t["in.encoder_hidden_states"] = rnd((batch, 77, ctx), g, dtype)
                t["out.unet.sample"] = u(t["in.sample"], t["in.timestep"], t["in.encoder_hidden_states"]).sample
                case["components"]["unet"] = {"inputs": ["in.sample", "in.timestep", "in.encoder_hidden_states"],
                                              "outputs": ["out.unet.sample"]}
            if "controlnet" in models:
                c = models["controlnet"]
                scale = 0.7
                f = 2 ** (len(c.config.conditioning_embedding_out_channels) - 1)
                t["in.controlnet_cond"] = rnd((batch, 3, f * h, f * w), g, dtype, 0.0, 1.0)
                t["in.conditioning_scale"] = torch.tensor([scale])
                down, mid = c(t["in.sample"], t["in.timestep"], t["in.encoder_hidden_states"],
                              controlnet_cond=t["in.controlnet_cond"], conditioning_scale=scale, return_dict=False)
                names = []
                for i, d in enumerate(down):
                    t[f"out.controlnet.down_residual_{i}"] = d
                    names.append(f"out.controlnet.down_residual_{i}")
                t["out.controlnet.mid_residual"] = mid
                case["components"]["controlnet"] = {
                    "inputs": ["in.sample", "in.timestep", "in.encoder_hidden_states", "in.controlnet_cond",
                               "in.conditioning_scale"], "outputs": names + ["out.controlnet.mid_residual"]}
                # UNet with these residuals (as stored: rounded to the case dtype first)
                down = [d.to(dtype).to(torch.float32) for d in down]
                mid = mid.to(dtype).to(torch.float32)
                for i, d in enumerate(down):
                    t[f"out.controlnet.down_residual_{i}"] = d
                t["out.controlnet.mid_residual"] = mid
                t["out.unet_with_residuals.sample"] = models["unet"](
                    t["in.sample"], t["in.timestep"], t["in.encoder_hidden_states"],
                    down_block_additional_residuals=down, mid_block_additional_residual=mid).sample
                case["components"]["unet_with_residuals"] = {
                    "inputs": ["in.sample", "in.timestep", "in.encoder_hidden_states"] + names
                    + ["out.controlnet.mid_residual"], "outputs": ["out.unet_with_residuals.sample"]}
            if "vae" in models:
                v = models["vae"]
                f = 2 ** (len(v.config.block_out_channels) - 1)
                if "in.controlnet_cond" in t and t["in.controlnet_cond"].shape[-1] == f * w:
                    image = "in.controlnet_cond"  # the same [0, 1] image (keeps the goldens small)
                else:
                    image = "in.image"
                    t[image] = rnd((batch, 3, f * h, f * w), g, dtype, -1.0, 1.0)
                enc = v.encode(t[image]).latent_dist
                t["out.vae_encoder.moments"] = enc.parameters
                t["out.vae_encoder.mean"] = enc.mean
                t["in.z"] = rnd((batch, 4, h, w), g, dtype)
                t["out.vae_decoder.sample"] = v.decode(t["in.z"]).sample
                case["components"]["vae_encoder"] = {"inputs": [image],
                                                     "outputs": ["out.vae_encoder.moments", "out.vae_encoder.mean"]}
                case["components"]["vae_decoder"] = {"inputs": ["in.z"], "outputs": ["out.vae_decoder.sample"]}
        store = {k: (v.to(dtype) if k not in ("in.timestep", "in.conditioning_scale") else v.float()).contiguous()
                 for k, v in t.items()}
        save_file(store, os.path.join(out_dir, case["file"]))
        cases.append(case)
    return models


def write_exr(path, img):
    """img: (3, H, W) float32 -> RGB FLOAT EXR. Returns False if the OpenEXR package is missing."""
    try:
        import OpenEXR
    except ImportError:
        return False
    rgb = np.ascontiguousarray(np.transpose(img, (1, 2, 0)).astype(np.float32))
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGB": rgb}) as f:
        f.write(path)
    return True


def make_loop(models, out_dir):
    """A short guided UniPC loop with b2dr-tiny (UNet + ControlNet) and the decode, at latent 7 x 13."""
    from diffusers import UniPCMultistepScheduler

    h, w, steps, scale = 7, 13, 5, 7.5
    g = torch.Generator().manual_seed(77)
    sched = UniPCMultistepScheduler(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012,
                                    beta_schedule="scaled_linear", solver_order=2, solver_type="bh2",
                                    lower_order_final=True, final_sigmas_type="zero", timestep_spacing="linspace")
    sched.set_timesteps(steps)
    t = {"in.x_T": torch.randn((1, 4, h, w), generator=g),
         "in.context_uncond": torch.randn((1, 77, 64), generator=g),
         "in.context_cond": torch.randn((1, 77, 64), generator=g),
         "in.cond_image": torch.rand((1, 3, 8 * h, 8 * w), generator=g)}
    x = t["in.x_T"].clone()
    ctx = torch.cat([t["in.context_uncond"], t["in.context_cond"]])
    cond = torch.cat([t["in.cond_image"]] * 2)
    with torch.no_grad():
        for i, ts in enumerate(sched.timesteps):
            xin = torch.cat([x] * 2)
            down, mid = models["controlnet"](xin, ts, ctx, controlnet_cond=cond, conditioning_scale=1.0,
                                             return_dict=False)
            eps = models["unet"](xin, ts, ctx, down_block_additional_residuals=down,
                                 mid_block_additional_residual=mid).sample
            eu, ec = eps.chunk(2)
            t[f"out.eps_uncond_{i}"] = eu.clone()
            t[f"out.eps_cond_{i}"] = ec.clone()
            x = sched.step(eu + scale * (ec - eu), ts, x).prev_sample
            t[f"out.latent_{i}"] = x.clone()
        vae = models["vae"]
        dec = vae.decode(x / vae.config.scaling_factor).sample
    t["out.decoded"] = dec
    t["out.image"] = (dec / 2 + 0.5).clamp(0, 1)
    save_file({k: v.contiguous() for k, v in t.items()}, os.path.join(out_dir, "loop_tiny_7x13.safetensors"))
    exr = write_exr(os.path.join(out_dir, "loop_tiny_7x13.exr"), t["out.image"][0].numpy())
    return {"file": "loop_tiny_7x13.safetensors", "exr": "loop_tiny_7x13.exr" if exr else None,
            "latent_hw": [h, w], "steps": steps, "guidance_scale": scale, "conditioning_scale": 1.0,
            "sampler": "UniPCMultistepScheduler SD1.5 defaults (bh2, order 2, linspace, final sigma zero)",
            "timesteps": [int(s) for s in sched.timesteps],
            "batch": "[uncond, cond] in one batch; eps = eps_u + s (eps_c - eps_u)",
            "decode": "vae.decode(latent / scaling_factor); image = clamp(x / 2 + 0.5, 0, 1)"}


def make_models(out_dir, format_version):
    torch.manual_seed(0)
    cases, sets = [], {}
    tiny = make_set("tiny", TINY, "generator", [(28, 50, "F16", 1), (7, 13, "F32", 2)], out_dir, cases, sets)
    make_set("dtest", DTEST, "file", [(7, 13, "F32", 2)], out_dir, cases, sets)
    make_set("dtest_unet", DTEST_UNET, "file", [(7, 13, "F32", 2), (4, 6, "F32", 1)], out_dir, cases, sets)
    loop = make_loop(tiny, out_dir)
    doc = {"format_version": format_version, "sets": sets, "cases": cases, "loop": loop,
           "notes": __doc__}
    with open(os.path.join(out_dir, "models.json"), "w") as f:
        json.dump(doc, f)
    files = {"models.json": "model goldens index: configs, diffusers state_dict names/shapes, weights, cases"}
    for c in cases:
        files[c["file"]] = f"{c['set']} inputs/outputs at latent {c['latent_hw']} ({c['dtype']})"
    for s, e in sets.items():
        for k, wv in e["weights"].items():
            if "file" in wv:
                files[wv["file"]] = f"{s} {k} weights (F32)"
    files[loop["file"]] = "b2dr-tiny guided UniPC loop at latent 7x13: latents per step, decoded image"
    if loop["exr"]:
        files[loop["exr"]] = "the loop's decoded image, RGB float EXR"
    return files
