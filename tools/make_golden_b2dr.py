#!/usr/bin/env python3
"""Writes the B2D-R golden files (tests/golden/b2dr_*) by running the PyTorch reference modules in python/b2dr_ref
(diffusers UNet2DConditionModel / AutoencoderKL / UniPCMultistepScheduler + B2DRControlNetModel; CPU, fp32).

Run by developers, not by CI (seconds on one core):
    ~/.cache/b2dr-venv/bin/python tools/make_golden_b2dr.py          # or any venv with python/'s dependencies
    ~/.cache/b2dr-venv/bin/python tools/make_golden_b2dr.py --latent-channels 8   # the b2dr_z8_* files only

Everything written comes from running the modules on this machine; nothing is typed in. Files:
- b2dr_weights_{unet,controlnet,vae}.safetensors: F32 weights of the test config (b2dr_ref.testing.TEST_CONFIGS),
  diffusers-initialised with torch seed 0, then made non-trivial: every zero-initialised tensor (ControlNet zero
  convs, conditioning-embedding conv_out, noise_embedding.linear_2, ref_attn.{j}.to_out.0, conv_in's input channels
  4..8) drawn uniform +-1/sqrt(fan_in), norm parameters perturbed U(+-0.1). The cases are computed with the weights
  read back from these files.
- b2dr_case_n1_7x13.safetensors (N = 1 camera, latent 7 x 13, image 56 x 104) and b2dr_case_n6_4x6.safetensors
  (N = 6, latent 4 x 6, image 32 x 48): inputs `in.*` and outputs `out.*` of every component, the previous-frame
  chain and 3-step guided frames (see b2dr_models.json for the list per component).
- b2dr_models.json: configs, state_dict names and shapes, the cases with their inputs/outputs and descriptions.
- with --latent-channels C (C != 4): the same for the design variant whose VAE has C latent channels (UNet in / out
  C, ControlNet in_channels 2 C), prefixed b2dr_zC_ (weights, models json, the N = 1 case only).
tests/golden/manifest.json gets these files' descriptions; its format_version and other entries stay as they are.
"""

import argparse
import json
import math
import os
import sys

import numpy as np
import torch
from safetensors.torch import load_file, save_file

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GOLDEN = os.path.join(ROOT, "tests", "golden")
sys.path.insert(0, os.path.join(ROOT, "python"))

from b2dr_ref import frame as fr  # noqa: E402
from b2dr_ref import pe as pe_mod  # noqa: E402
from b2dr_ref.controlnet import B2DRControlNetModel  # noqa: E402
from b2dr_ref.testing import build_models, configs  # noqa: E402

PREFIX = "b2dr_"          # b2dr_zC_ for the variant with C latent channels (--latent-channels)
LATENT_CHANNELS = 4
WEIGHT_FILES = {k: f"{PREFIX}weights_{k}.safetensors" for k in ("unet", "controlnet", "vae")}
STEPS = 3
CAMERAS6 = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
YAWS6 = [0.0, -55.0, 55.0, 180.0, 110.0, -110.0]  # degrees, nuScenes-like rig


def f32r(a):
    """Round an f64 array to f32 values (kept as f64): stored F32 geometry is then exact."""
    return np.asarray(a, np.float64).astype(np.float32).astype(np.float64)


def pose(yaw, x, y, z=0.0):
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    m[:3, 3] = [x, y, z]
    return f32r(m)


def cam2ego(yaw_deg, t):
    """Camera (x right, y down, z forward) -> ego (x forward, y left, z up), camera looking along ego yaw."""
    yaw = math.radians(yaw_deg)
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: cam x, y, z in ego
    c, s = math.cos(yaw), math.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    m = np.eye(4)
    m[:3, :3] = rz @ base
    m[:3, 3] = t
    return f32r(m)


def geometry(n, render_h, render_w):
    """Cameras, current and reference ego poses of a frame; returns f32-exact numpy arrays."""
    k_native = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
    ks, c2e = [], []
    for i in range(n):
        yaw = YAWS6[i]
        ks.append(f32r(pe_mod.intrinsic_scaled(k_native, 1600, 900, render_w, render_h)))
        c2e.append(cam2ego(yaw, [1.5 * math.cos(math.radians(yaw)), 0.5 * math.sin(math.radians(yaw)), 1.6]))
    cur = pose(0.30, 100.0, 50.0, 0.0)
    front = pose(0.33, 100.0 + 6.0 * math.cos(0.3), 50.0 + 6.0 * math.sin(0.3), 0.05)
    rear = pose(0.28, 100.0 - 4.0 * math.cos(0.3), 50.0 - 4.0 * math.sin(0.3), -0.02)
    ref = np.stack([np.stack([front, rear])] * n)
    return np.stack(ks), np.stack(c2e), cur, ref


def t32(a):
    return torch.as_tensor(np.asarray(a), dtype=torch.float32).contiguous()


def save_weights(models):
    for k, m in models.items():
        sd = {n: v.detach().to(torch.float32).contiguous() for n, v in m.state_dict().items()}
        save_file(sd, os.path.join(GOLDEN, WEIGHT_FILES[k]), metadata={"format": "pt"})


def load_weights():
    """Fresh models with the weights read back from the golden files (what the Rust side loads)."""
    models = build_models(seed=0, nontrivial=False, latent_channels=LATENT_CHANNELS)
    for k, m in models.items():
        m.load_state_dict(load_file(os.path.join(GOLDEN, WEIGHT_FILES[k])), strict=True)
        m.eval()
    return models


@torch.no_grad()
def make_case(models, n, h, w, seed, with_w1):
    unet, cn, vae = models["unet"], models["controlnet"], models["vae"]
    cfg = cn.config
    f = 8
    H, W = h * f, w * f
    g = torch.Generator().manual_seed(seed)
    t, comps = {}, {}
    name = f"{PREFIX}case_n{n}_{h}x{w}.safetensors"

    # ---- inputs ----
    lc = cn.latent_channels
    t["in.x_t"] = torch.randn((n, lc, h, w), generator=g)
    t["in.timestep"] = torch.tensor([601.0])
    ctx_shape = (77, cfg.cross_attention_dim) if n == 1 else (n, 77, cfg.cross_attention_dim)
    t["in.context"] = torch.randn(ctx_shape, generator=g)
    t["in.masks"] = (torch.rand((n, 15, H, W), generator=g) > 0.7).float()
    t["in.prev_image"] = torch.rand((n, 3, H, W), generator=g)
    t["in.eps_prev"] = torch.randn((n, lc, h, w), generator=g)
    t["in.ref_images"] = torch.rand((n, 2, 3, H, W), generator=g)
    t["in.noise_level"] = torch.full((n,), float(cfg.prev_noise_level))
    t["in.x_T"] = torch.randn((n, lc, h, w), generator=g)
    ks, c2e, cur, ref = geometry(n, H, W)
    t["in.geom.k_render"], t["in.geom.cam2ego"] = t32(ks), t32(c2e)
    t["in.geom.cur_ego2global"], t["in.geom.ref_ego2global"] = t32(cur), t32(ref)
    pcfg = pe_mod.PeConfig.from_controlnet_config(cfg)
    cams = [pe_mod.CameraGeometry(ks[i], c2e[i]) for i in range(n)]
    pe_cur, pe_ref = pe_mod.pe_inputs(cams, (H, W), cur, [(ref[i, 0], ref[i, 1]) for i in range(n)],
                                      cfg.ref_attn, len(cfg.block_out_channels), pcfg)
    nl = len(cfg.ref_attn)
    # the stored (F32) geometry reproduces the PE bit for bit
    gk, gc = t["in.geom.k_render"].double().numpy(), t["in.geom.cam2ego"].double().numpy()
    gcur, gref = t["in.geom.cur_ego2global"].double().numpy(), t["in.geom.ref_ego2global"].double().numpy()
    chk_cur, chk_ref = pe_mod.pe_inputs([pe_mod.CameraGeometry(gk[i], gc[i]) for i in range(n)], (H, W), gcur,
                                        [(gref[i, 0], gref[i, 1]) for i in range(n)], cfg.ref_attn,
                                        len(cfg.block_out_channels), pcfg)
    assert all(np.array_equal(a, b) for a, b in zip(chk_cur + chk_ref, pe_cur + pe_ref))
    for j in range(nl):
        t[f"in.pe_cur.{j}"] = t32(pe_cur[j])
        t[f"in.pe_ref.{j}"] = t32(pe_ref[j])
    pe_in = [f"in.pe_cur.{j}" for j in range(nl)] + [f"in.pe_ref.{j}" for j in range(nl)]
    comps["pe"] = {"inputs": ["in.geom.k_render", "in.geom.cam2ego", "in.geom.cur_ego2global",
                              "in.geom.ref_ego2global"], "outputs": pe_in,
                   "description": "PETR geometry per Ref-Attn location (python/b2dr_ref/pe.py = src/projection/pe.rs, "
                                  "PixelGrid::Centre, f64 maths, f32 out): pe_cur.{j} (N, 3D, h_j, w_j) with "
                                  "cam2cur = cur^-1 cur cam2ego (the current pose passed twice, as pe.rs says), "
                                  "pe_ref.{j} (N, 2, 3D, h_j, w_j) with cam2cur = cur^-1 ref_ego2global[c, r] "
                                  "cam2ego[c]; k_render = intrinsics at the render size (intrinsic_scaled from "
                                  "1600 x 900); these pe tensors are INPUTS of the components below",
                   "geometry_layout": "k_render (N, 3, 3) and 4x4 matrices row-major in maths convention "
                                      "(m[row][col], translation in the last column)"}

    # ---- a1. noise embedding ----
    ts = t["in.timestep"].to(torch.int64).expand(n)
    nemb = cn.noise_embed(t["in.noise_level"].to(torch.int64), n)
    temb = cn.time_embedding(cn.time_proj(ts)) + nemb
    t["out.noise_embedding.emb"], t["out.noise_embedding.temb"] = nemb, temb
    comps["noise_embedding"] = {
        "inputs": ["in.noise_level", "in.timestep"], "outputs": ["out.noise_embedding.emb", "out.noise_embedding.temb"],
        "description": "emb = noise_embedding(time_proj(n)) (N, 4 C_0); temb = time_embedding(time_proj(t)) + emb, "
                       "the embedding the blocks see"}

    # ---- b. previous-frame chain ----
    chain = fr.prev_frame_chain(vae, t["in.prev_image"], t["in.eps_prev"], float(cfg.prev_blur_sigma),
                                int(cfg.prev_noise_level))
    t["out.prev.blurred"], t["out.prev.z_prev"], t["out.prev.z"] = chain.blurred, chain.z_prev, chain.z
    t["out.prev.sqrt_abar"] = chain.sqrt_abar.reshape(1)
    t["out.prev.sqrt_one_minus_abar"] = chain.sqrt_one_minus_abar.reshape(1)
    comps["prev_chain"] = {
        "inputs": ["in.prev_image", "in.eps_prev", "in.noise_level"],
        "outputs": ["out.prev.blurred", "out.prev.z_prev", "out.prev.sqrt_abar", "out.prev.sqrt_one_minus_abar",
                    "out.prev.z"],
        "description": f"blur sigma {cfg.prev_blur_sigma} (7 taps, reflect without edge repeat, rows then columns) "
                       "-> VAE encoder mean x scaling (of 2 x - 1) = z_prev -> z = sqrt(abar_n) z_prev + "
                       f"sqrt(1 - abar_n) eps_prev, n = {cfg.prev_noise_level}, abar f32 (diffusers SD1.5)"}

    # ---- a2. references: VAE latents, encoder features per location ----
    ref_lat = fr.encode_reference_images(vae, t["in.ref_images"])
    t["out.ref_latents"] = ref_lat
    feats = cn.encode_references(ref_lat)
    for j in range(nl):
        t[f"out.ref_encoder.features.{j}"] = feats[j]
    comps["ref_vae"] = {"inputs": ["in.ref_images"], "outputs": ["out.ref_latents"],
                        "description": "references (N, 2, 3, H, W) -> VAE encoder mean x scaling (of 2 x - 1), no blur, "
                                       "no noise: (N, 2, 4, h, w)"}
    comps["ref_encoder"] = {"inputs": ["out.ref_latents"],
                            "outputs": [f"out.ref_encoder.features.{j}" for j in range(nl)],
                            "description": "ref_encoder on the 2N latents; features.{j} = F_{block(j)} as (N, 2, C, "
                                           "h_j, w_j) (mid uses F_{B-1})"}

    # ---- a3. PE MLP ----
    p_cur = [cn.pos_embed_at(j, t[f"in.pe_cur.{j}"]) for j in range(nl)]
    p_ref = [cn.pos_embed_at(j, t[f"in.pe_ref.{j}"]) for j in range(nl)]
    for j in range(nl):
        t[f"out.pos_embed.{j}.cur"], t[f"out.pos_embed.{j}.ref"] = p_cur[j], p_ref[j]
    comps["pos_embed"] = {"inputs": pe_in,
                          "outputs": [f"out.pos_embed.{j}.{s}" for j in range(nl) for s in ("cur", "ref")],
                          "description": "pos_embed.{j} (conv1x1 3D -> 4C, ReLU, conv1x1 4C -> C) of pe_cur.{j} "
                                         "(N, C, h, w) and pe_ref.{j} (N, 2, C, h, w)"}

    # ---- a4. one Ref-Attn application per location ----
    sizes = pe_mod.location_sizes(cfg.ref_attn, len(cfg.block_out_channels), (h, w))
    for j in range(nl):
        c = cfg.block_out_channels[cn.location_block(j)]
        t[f"in.ref_attn.{j}.hidden"] = torch.randn((n, c) + tuple(sizes[j]), generator=g)
        t[f"out.ref_attn.{j}.hidden"] = cn.ref_attn_modules[j](t[f"in.ref_attn.{j}.hidden"], feats[j], p_cur[j],
                                                               p_ref[j])
    comps["ref_attn"] = {
        "inputs": [f"in.ref_attn.{j}.hidden" for j in range(nl)]
        + [f"out.ref_encoder.features.{j}" for j in range(nl)]
        + [f"out.pos_embed.{j}.{s}" for j in range(nl) for s in ("cur", "ref")],
        "outputs": [f"out.ref_attn.{j}.hidden" for j in range(nl)],
        "description": "H' = ref_attn.{j}(H = in.ref_attn.{j}.hidden, F = out.ref_encoder.features.{j}, P_cur = "
                       "out.pos_embed.{j}.cur, P_ref = out.pos_embed.{j}.ref)"}

    # ---- a5. full forward with and without references ----
    ctx_n = fr.expand_context(t["in.context"], n)
    refs = cn.prepare_references(ref_lat, [t[f"in.pe_cur.{j}"] for j in range(nl)],
                                 [t[f"in.pe_ref.{j}"] for j in range(nl)])
    for tag, r in (("controlnet_ref", refs), ("controlnet_noref", None)):
        down, mid = cn(t["in.x_t"], t["in.timestep"].to(torch.int64)[0], ctx_n, t["in.masks"], chain.z,
                       t["in.noise_level"].to(torch.int64), refs=r, conditioning_scale=1.0)
        outs = []
        for k, d in enumerate(down):
            t[f"out.{tag}.down.{k}"] = d
            outs.append(f"out.{tag}.down.{k}")
        t[f"out.{tag}.mid"] = mid
        ins = ["in.x_t", "in.timestep", "in.context", "in.masks", "out.prev.z", "in.noise_level"]
        if r is not None:
            ins += ["out.ref_latents"] + pe_in
        comps[tag] = {"inputs": ins, "outputs": outs + [f"out.{tag}.mid"],
                      "description": "B2DRControlNetModel forward (conditioning_scale 1): sample in.x_t, timestep "
                                     "in.timestep, encoder_hidden_states in.context (expanded to N rows when 2-D), "
                                     "controlnet_cond in.masks, prev_latent out.prev.z, noise_level in.noise_level, "
                                     + ("references from out.ref_latents and the pe inputs (all N rows)"
                                        if r is not None else "no references (every Ref-Attn skipped)")
                                     + f"; {len(down)} down residuals then mid"}

    # ---- c. guided frames ----
    pe_cur_t = [t[f"in.pe_cur.{j}"] for j in range(nl)]
    pe_ref_t = [t[f"in.pe_ref.{j}"] for j in range(nl)]
    frames = {}
    for wgt in ([2.0, 1.0] if with_w1 else [2.0]):
        tag = f"frame_w{int(wgt)}"
        res = fr.render_frame(unet, cn, vae, t["in.x_T"], t["in.context"], t["in.masks"], t["in.prev_image"],
                              t["in.eps_prev"], ref_images=t["in.ref_images"], pe_cur=pe_cur_t, pe_ref=pe_ref_t,
                              steps=STEPS, ref_guidance=wgt, sampler="unipc")
        assert torch.equal(res.prev.z, chain.z) and torch.equal(res.ref_latents, ref_lat)
        outs = [f"out.{tag}.timesteps"]
        t[f"out.{tag}.timesteps"] = torch.tensor(res.timesteps, dtype=torch.float32)
        for i in range(STEPS):
            # eps (the guided eps) only where it differs from eps_ref (w != 1)
            for kind, lst in (("eps_noref", res.eps_noref), ("eps_ref", res.eps_ref),
                              ("eps", res.eps if wgt != 1.0 else []), ("latent", res.latents)):
                if lst:
                    t[f"out.{tag}.{kind}.{i}"] = lst[i]
                    outs.append(f"out.{tag}.{kind}.{i}")
        t[f"out.{tag}.decoded"], t[f"out.{tag}.image"] = res.decoded, res.image
        outs += [f"out.{tag}.decoded", f"out.{tag}.image"]
        comps[tag] = {
            "inputs": ["in.x_T", "in.context", "in.masks", "in.prev_image", "in.eps_prev", "in.ref_images"] + pe_in,
            "outputs": outs, "ref_guidance": wgt, "steps": STEPS, "timesteps": res.timesteps,
            "description": (f"render_frame: UniPC {STEPS} steps (SD1.5, bh2, order 2, linspace, final sigma zero), "
                            f"prev chain as out.prev.* (n = {cfg.prev_noise_level}), references as out.ref_latents, "
                            "conditioning_scale 1; "
                            + ("batch [no-ref; ref] (2N rows, the same context / masks / z / t), eps = eps_noref + "
                               f"{wgt} (eps_ref - eps_noref)" if wgt != 1.0 else
                               "w = 1: only the N with-reference rows run (eps = eps_ref, no eps_noref)")
                            + "; latent.{i} after step i; decoded = vae.decode(x_0 / scaling); image = "
                              "clamp(decoded / 2 + 0.5, 0, 1)")}
        frames[tag] = res
    store = {k: v.detach().to(torch.float32).contiguous() for k, v in t.items()}
    save_file(store, os.path.join(GOLDEN, name))
    case = {"file": name, "cameras": n, "latent_hw": [h, w], "image_hw": [H, W], "dtype": "F32",
            "location_sizes": [list(s) for s in sizes], "ref_attn": list(cfg.ref_attn),
            "tensors": {k: list(v.shape) for k, v in store.items()}, "components": comps}
    return case


def main():
    global PREFIX, LATENT_CHANNELS, WEIGHT_FILES
    ap = argparse.ArgumentParser()
    ap.add_argument("--latent-channels", type=int, default=4)
    a = ap.parse_args()
    LATENT_CHANNELS = a.latent_channels
    if LATENT_CHANNELS != 4:
        PREFIX = f"b2dr_z{LATENT_CHANNELS}_"
        WEIGHT_FILES = {k: f"{PREFIX}weights_{k}.safetensors" for k in ("unet", "controlnet", "vae")}
    torch.set_num_threads(1)
    os.makedirs(GOLDEN, exist_ok=True)
    man_path = os.path.join(GOLDEN, "manifest.json")
    with open(man_path) as f:
        manifest = json.load(f)
    models = build_models(seed=0, nontrivial=True, latent_channels=LATENT_CHANNELS)
    save_weights(models)
    models = load_weights()
    cases = [make_case(models, 1, 7, 13, seed=7013, with_w1=True)]
    if LATENT_CHANNELS == 4:
        cases.append(make_case(models, 6, 4, 6, seed=6046, with_w1=False))
    import diffusers

    cn = models["controlnet"]
    cfgs = {"unet": json.loads(json.dumps(dict(models["unet"].config), default=list)),
            "controlnet": cn.config_dict(),
            "vae": json.loads(json.dumps(dict(models["vae"].config), default=list))}
    cfgs["unet"]["_class_name"] = "UNet2DConditionModel"
    cfgs["vae"]["_class_name"] = "AutoencoderKL"
    for c in cfgs.values():
        c.pop("_use_default_values", None)
    doc = {
        "format_version": manifest["format_version"],
        "generator": "tools/make_golden_b2dr.py",
        "diffusers": diffusers.__version__, "torch": torch.__version__,
        "contract": "docs/b2dr_controlnet.md",
        "configs": cfgs,
        "constructor_args": configs(LATENT_CHANNELS),
        "state_dicts": {k: [[n, list(v.shape)] for n, v in m.state_dict().items()] for k, m in models.items()},
        "zero_initialised_on_fresh_model": cn.zero_init_names(),
        "weights": {k: {"file": f, "dtype": "F32",
                        "init": "diffusers init with torch seed 0 (UNet, ControlNet, VAE built in that order); "
                                f"every all-zero tensor and conv_in.weight[:, {LATENT_CHANNELS}:] drawn uniform "
                                "+-1/sqrt(fan_in); "
                                "norms 1 or 0 + U(+-0.1)"} for k, f in WEIGHT_FILES.items()},
        "sampler": {"kind": "UniPCMultistepScheduler", "config": dict(fr.SD15_SCHEDULE, solver_order=2,
                                                                      solver_type="bh2", lower_order_final=True,
                                                                      final_sigmas_type="zero",
                                                                      timestep_spacing="linspace")},
        "cases": cases,
        "notes": __doc__,
    }
    with open(os.path.join(GOLDEN, f"{PREFIX}models.json"), "w") as f:
        json.dump(doc, f, indent=1)
    what = "B2D-R" if LATENT_CHANNELS == 4 else f"B2D-R, {LATENT_CHANNELS} latent channels,"
    files = {f"{PREFIX}models.json": f"{what} goldens index: configs, state_dict names/shapes, cases with "
                                     "inputs/outputs"}
    for k, fn in WEIGHT_FILES.items():
        files[fn] = f"{what} test-config {k} weights (F32)"
    for c in cases:
        files[c["file"]] = (f"{what} components, prev-frame chain and {STEPS}-step guided frame(s), N = {c['cameras']}, "
                            f"latent {c['latent_hw'][0]}x{c['latent_hw'][1]} (F32)")
    manifest["files"].update(files)
    with open(man_path, "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
    total = sum(os.path.getsize(os.path.join(GOLDEN, fn)) for fn in files)
    print(f"wrote {len(files)} B2D-R golden files to {GOLDEN} ({total / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
