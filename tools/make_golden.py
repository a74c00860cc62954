#!/usr/bin/env python3
"""Writes b2dr's golden files (tests/golden/) by running diffusers (PyTorch, CPU, fp32).

Run by developers, not by CI:
    python3 -m venv .venv && .venv/bin/pip install -r tools/requirements.txt
    .venv/bin/python tools/make_golden.py            # everything
    .venv/bin/python tools/make_golden.py --only sampling
    .venv/bin/python tools/make_golden.py --only models

Everything written comes from diffusers' own code on this machine; nothing is typed in. The format version
below is stored in tests/golden/manifest.json; the Rust tests refuse another version and say how to regenerate.
"""

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

FORMAT_VERSION = 1
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GOLDEN = os.path.join(ROOT, "tests", "golden")

SD15 = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear")
STEP_COUNTS = [1, 2, 20, 25, 1000]


def f32list(t):
    """Exact f32 values as Python floats (JSON numbers that parse back to the same f32)."""
    return [float(v) for v in np.asarray(t, dtype=np.float32).reshape(-1)]


# ---------------------------------------------------------------------------------------------------------------
# Samplers
# ---------------------------------------------------------------------------------------------------------------


def synthetic_inputs():
    """The synthetic loop of the sampler goldens: x_T and a fixed noise field, shape (1, 4, 3, 5)."""
    g = torch.Generator().manual_seed(1234)
    x_t = torch.randn((1, 4, 3, 5), generator=g, dtype=torch.float32)
    noise = torch.randn((1, 4, 3, 5), generator=g, dtype=torch.float32)
    return x_t, noise


def synthetic_model(x, t, noise):
    """eps = 0.1 x + sin(t / 100) noise (f32): simple enough for the Rust side to compute identically."""
    return 0.1 * x + math.sin(float(t) / 100.0) * noise


def run_loop(sched, n, x_t, noise, **step_kwargs):
    sched.set_timesteps(n)
    x = x_t.clone()
    latents = []
    for t in sched.timesteps:
        eps = synthetic_model(x, int(t), noise)
        x = sched.step(eps, t, x, **step_kwargs).prev_sample
        latents.append(f32list(x))
    return latents


def dummy_sample_deter():
    """diffusers tests/schedulers/test_schedulers.py SchedulerCommonTest.dummy_sample_deter, (4, 3, 8, 8)."""
    n = 4 * 3 * 8 * 8
    s = torch.arange(n).reshape(3, 8, 8, 4) / n
    return s.permute(3, 0, 1, 2)


def dummy_noise_deter():
    """SchedulerCommonTest.dummy_noise_deter: the flipped arange, (4, 3, 8, 8)."""
    n = 4 * 3 * 8 * 8
    s = torch.arange(n).flip(-1).reshape(3, 8, 8, 4) / n
    return s.permute(3, 0, 1, 2)


def dummy_model(sample, t):
    """SchedulerCommonTest.dummy_model: sample * t / (t + 1)."""
    t = torch.as_tensor(t).reshape(-1, 1, 1, 1).to(sample.dtype)
    return sample * t / (t + 1)


def diffusers_test_loops():
    """The full loops of diffusers' test_scheduler_unipc.py / test_scheduler_ddim.py, run here."""
    from diffusers import DDIMScheduler, UniPCMultistepScheduler

    out = {}
    base = dict(num_train_timesteps=1000, beta_start=0.0001, beta_end=0.02, beta_schedule="linear")
    # UniPC: get_scheduler_config = base + solver_order 2, bh2, final_sigmas_type sigma_min; 10 steps.
    for name, extra in [("unipc_full_loop", {}), ("unipc_full_loop_v_prediction", {"prediction_type": "v_prediction"})]:
        s = UniPCMultistepScheduler(**base, solver_order=2, solver_type="bh2", final_sigmas_type="sigma_min", **extra)
        s.set_timesteps(10)
        x = dummy_sample_deter()
        for t in s.timesteps:
            x = s.step(dummy_model(x, t), t, x).prev_sample
        out[name] = {"sum_abs": float(x.abs().sum()), "mean_abs": float(x.abs().mean()), "result": f32list(x)}
    s = UniPCMultistepScheduler(**base, solver_order=2, solver_type="bh2", final_sigmas_type="sigma_min")
    s.set_timesteps(10)
    ts = s.timesteps[8:]
    x = s.add_noise(dummy_sample_deter(), dummy_noise_deter(), ts[:1])
    for t in ts:
        x = s.step(dummy_model(x, t), t, x).prev_sample
    out["unipc_full_loop_with_noise"] = {"start": 8, "sum_abs": float(x.abs().sum()), "mean_abs": float(x.abs().mean())}
    # DDIM: base + clip_sample True; 10 steps, eta 0.
    for name, extra in [
        ("ddim_full_loop", {}),
        ("ddim_full_loop_v_prediction", {"prediction_type": "v_prediction"}),
        ("ddim_full_loop_set_alpha_to_one", {"set_alpha_to_one": True, "beta_start": 0.01}),
        ("ddim_full_loop_no_set_alpha_to_one", {"set_alpha_to_one": False, "beta_start": 0.01}),
    ]:
        cfg = dict(base, clip_sample=True)
        cfg.update(extra)
        s = DDIMScheduler(**cfg)
        s.set_timesteps(10)
        x = dummy_sample_deter()
        for t in s.timesteps:
            x = s.step(dummy_model(x, t), t, x, 0.0).prev_sample
        out[name] = {"config": cfg, "sum_abs": float(x.abs().sum()), "mean_abs": float(x.abs().mean())}
    return out


def make_sampling():
    from diffusers import DDIMScheduler, UniPCMultistepScheduler

    x_t, noise = synthetic_inputs()
    doc = {
        "format_version": FORMAT_VERSION,
        "synthetic": {
            "shape": [1, 4, 3, 5],
            "model": "eps = 0.1 * x + sin(t / 100) * noise",
            "x_T": f32list(x_t),
            "noise": f32list(noise),
        },
    }
    uni_cfg = dict(SD15, solver_order=2, solver_type="bh2", predict_x0=True, lower_order_final=True,
                   final_sigmas_type="zero", timestep_spacing="linspace", disable_corrector=[])
    uni = UniPCMultistepScheduler(**uni_cfg)
    doc["alphas_cumprod"] = f32list(uni.alphas_cumprod)
    u = {"config": uni_cfg, "timesteps": {}, "sigmas": {}}
    for n in STEP_COUNTS:
        uni.set_timesteps(n)
        u["timesteps"][str(n)] = [int(t) for t in uni.timesteps]
        u["sigmas"][str(n)] = f32list(uni.sigmas)
    u["loop20"] = run_loop(UniPCMultistepScheduler(**uni_cfg), 20, x_t, noise)
    u["loop25"] = run_loop(UniPCMultistepScheduler(**uni_cfg), 25, x_t, noise)
    u["loop1"] = run_loop(UniPCMultistepScheduler(**uni_cfg), 1, x_t, noise)
    # 1000 steps: linspace repeats t = 500; diffusers divides by zero there and turns NaN. Stored up to the
    # last finite step (b2dr handles the repeat, see src/sampling/unipc.rs).
    l1000 = run_loop(UniPCMultistepScheduler(**uni_cfg), 1000, x_t, noise)
    finite = [all(math.isfinite(v) for v in lat) for lat in l1000]
    first_nan = finite.index(False) if False in finite else None
    u["loop1000"] = {"first_nonfinite_step": first_nan, "latents_every_10": {
        str(i): l1000[i] for i in range(0, 1000, 10) if finite[i]}}
    # Other UniPC settings (20-step synthetic loop each); NaN steps (diffusers' degenerate cases) are None.
    variants = {
        "order1": dict(solver_order=1),
        "order3": dict(solver_order=3),
        "bh1_sigma_min": dict(solver_type="bh1", final_sigmas_type="sigma_min"),
        "bh1_order3_sigma_min": dict(solver_type="bh1", solver_order=3, final_sigmas_type="sigma_min"),
        "disable_corrector_0_1_2": dict(disable_corrector=[0, 1, 2]),
        "no_lower_order_final_sigma_min": dict(lower_order_final=False, final_sigmas_type="sigma_min"),
        "leading_offset1": dict(timestep_spacing="leading", steps_offset=1),
        "trailing": dict(timestep_spacing="trailing"),
        "v_prediction": dict(prediction_type="v_prediction"),
    }
    u["variants"] = {}
    for name, extra in variants.items():
        cfg = dict(uni_cfg, **extra)
        lat = run_loop(UniPCMultistepScheduler(**cfg), 20, x_t, noise)
        s = UniPCMultistepScheduler(**cfg)
        s.set_timesteps(20)
        u["variants"][name] = {"config": cfg, "timesteps": [int(t) for t in s.timesteps],
                               "loop20": [l if all(math.isfinite(v) for v in l) else None for l in lat]}
    doc["unipc"] = u

    d = {"variants": {}}
    for name, cfg in [
        ("sd15_leading", dict(SD15, set_alpha_to_one=False, steps_offset=1, clip_sample=False, timestep_spacing="leading")),
        ("linspace", dict(SD15, set_alpha_to_one=False, steps_offset=1, clip_sample=False, timestep_spacing="linspace")),
        ("trailing", dict(SD15, set_alpha_to_one=False, steps_offset=1, clip_sample=False, timestep_spacing="trailing")),
    ]:
        s = DDIMScheduler(**cfg)
        v = {"config": cfg, "timesteps": {}}
        for n in STEP_COUNTS:
            s.set_timesteps(n)
            v["timesteps"][str(n)] = [int(t) for t in s.timesteps]
        v["loop20"] = run_loop(DDIMScheduler(**cfg), 20, x_t, noise, eta=0.0)
        try:
            v["loop1000_last"] = run_loop(DDIMScheduler(**cfg), 1000, x_t, noise, eta=0.0)[-1]
        except Exception as e:  # leading + steps_offset 1 indexes abar[1000]
            v["loop1000_error"] = f"{type(e).__name__}: {e}"
        d["variants"][name] = v
    doc["ddim"] = d
    doc["diffusers_tests"] = diffusers_test_loops()
    path = os.path.join(GOLDEN, "sampling.json")
    with open(path, "w") as f:
        json.dump(doc, f)
    return {"sampling.json": "UniPC and DDIM timesteps, sigmas, synthetic-model loops; diffusers' scheduler-test loops"}


# ---------------------------------------------------------------------------------------------------------------


def write_manifest(files):
    import diffusers

    path = os.path.join(GOLDEN, "manifest.json")
    old = {}
    if os.path.exists(path):
        with open(path) as f:
            old = json.load(f).get("files", {})
    old.update(files)
    man = {
        "format_version": FORMAT_VERSION,
        "generator": "tools/make_golden.py",
        "diffusers": diffusers.__version__,
        "torch": torch.__version__,
        "files": old,
    }
    with open(path, "w") as f:
        json.dump(man, f, indent=1, sort_keys=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=["sampling", "models"], default=None)
    args = ap.parse_args()
    torch.set_num_threads(max(1, min(4, os.cpu_count() or 1)))
    os.makedirs(GOLDEN, exist_ok=True)
    files = {}
    if args.only in (None, "sampling"):
        files.update(make_sampling())
    if args.only in (None, "models"):
        import make_golden_models  # noqa: E402  (tools/ is on sys.path when run as a script)

        files.update(make_golden_models.make_models(GOLDEN, FORMAT_VERSION))
    write_manifest(files)
    total = sum(os.path.getsize(os.path.join(GOLDEN, f)) for f in os.listdir(GOLDEN))
    print(f"wrote {len(files)} golden entries to {GOLDEN} ({total / 1e6:.2f} MB in total)")


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
