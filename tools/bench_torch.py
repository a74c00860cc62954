#!/usr/bin/env python3
"""PyTorch-CPU baseline for `b2dr bench ops` (run by developers, not CI).

Times the same cases as b2dr (same names, same FLOP counts) with PyTorch on the CPU and prints one JSON object
{case: {"ms": .., "gflops": ..}}. With --compare B2DR_JSON it also prints b2dr / PyTorch throughput ratios.

    python3 tools/bench_torch.py --threads 2 > torch.json
    b2dr bench ops --json > b2dr.json
    python3 tools/bench_torch.py --threads 2 --compare b2dr.json

Needs: pip install torch (CPU wheel is enough).
"""
import argparse
import json
import time

import torch
import torch.nn.functional as F


def timeit(fn, min_time=1.0):
    for _ in range(2):
        fn()
    times = []
    start = time.perf_counter()
    while len(times) < 3 or time.perf_counter() - start < min_time:
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return times[len(times) // 2], times[0]


def cases(dtype):
    g = torch.Generator().manual_seed(0)
    r = lambda *s: (torch.rand(*s, generator=g) * 2 - 1).to(dtype)
    name = "f32" if dtype == torch.float32 else "f16"
    out = {}
    # matmul MxNxK = 1400 x 1280 x 320: x (1400, 320) @ W^T, W (1280, 320) (a Linear layer)
    x, w = r(1400, 320), r(1280, 320)
    out[f"matmul_{name}_1400x1280x320"] = (lambda: F.linear(x, w), 2 * 1400 * 1280 * 320)
    # conv 3x3, 320 -> 320, 28 x 50, pad 1, batch 1
    xc, wc, bc = r(1, 320, 28, 50), r(320, 320, 3, 3), r(320)
    out[f"conv2d_{name}_3x3_320to320_28x50"] = (lambda: F.conv2d(xc, wc, bc, padding=1), 2 * 320 * 320 * 9 * 28 * 50)
    # attention, batch 1, 8 heads, dim 40; FLOP = 4 * B * H * Lq * Lk * d
    for lk in (1400, 77):
        q, k, v = r(1, 8, 1400, 40), r(1, 8, lk, 40), r(1, 8, lk, 40)
        out[f"attention_{name}_1400x{lk}_h8_d40"] = (
            (lambda q=q, k=k, v=v: F.scaled_dot_product_attention(q, k, v)),
            4 * 8 * 1400 * lk * 40,
        )
    xg, gg, bg = r(1, 320, 28, 50), r(320), r(320)
    out[f"group_norm_{name}_320c_28x50_g32"] = (
        lambda: F.silu(F.group_norm(xg, 32, gg, bg, 1e-5)),
        10 * 320 * 28 * 50,
    )
    return out


def model_cases():
    """diffusers b2dr-tiny (configs from tests/golden/models.json): one guided step (ControlNet + UNet, batch 2,
    latent 28x50, context 77x64, conditioning image 224x400) and one VAE decode to 224x400. Random weights."""
    import os
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel

    root = os.path.join(os.path.dirname(__file__), "..", "tests", "golden", "models.json")
    cfgs = json.load(open(root))["sets"]["tiny"]["configs"]
    clean = lambda c: {k: v for k, v in c.items() if not k.startswith("_")}
    unet = UNet2DConditionModel(**clean(cfgs["unet"])).eval()
    cn = ControlNetModel(**clean(cfgs["controlnet"])).eval()
    vae = AutoencoderKL(**clean(cfgs["vae"])).eval()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 4, 28, 50, generator=g)
    t = torch.tensor([500.0, 500.0])
    c = torch.randn(2, 77, cfgs["unet"]["cross_attention_dim"], generator=g)
    cond = torch.rand(2, 3, 224, 400, generator=g)
    z = torch.randn(1, 4, 28, 50, generator=g)

    def step():
        down, mid = cn(x, t, c, controlnet_cond=cond, return_dict=False)
        unet(x, t, c, down_block_additional_residuals=down, mid_block_additional_residual=mid)

    return {
        "guided_step_tiny_f32_28x50_b2": (step, 0),
        "vae_decode_tiny_f32_224x400": (lambda: vae.decode(z), 0),
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--min-time", type=float, default=1.0)
    ap.add_argument("--f16", action="store_true", help="also time f16 on the CPU (slow/unsupported on many CPUs)")
    ap.add_argument("--compare", help="b2dr bench ops/model --json output to compare against")
    ap.add_argument("--models", action="store_true", help="time the b2dr-tiny model cases (needs diffusers)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    res = {}
    with torch.no_grad():
        if a.models:
            suites = [model_cases()]
        else:
            suites = [cases(dt) for dt in [torch.float32] + ([torch.float16] if a.f16 else [])]
        for suite in suites:
            for name, (fn, flops) in suite.items():
                s, fastest = timeit(fn, a.min_time)
                res[name] = {"ms": s * 1e3, "min_ms": fastest * 1e3, "gflops": flops / s * 1e-9}
    if a.compare:
        b = json.load(open(a.compare))
        # medians, and the fastest replays (steadier on a noisy machine; b2dr writes min_ms since session 3)
        print(f"{'case':<40} {'b2dr ms':>10} {'torch ms':>10} {'b2dr/torch time':>16} {'fastest: b2dr':>14} {'torch':>8} {'ratio':>7}")
        for k, v in res.items():
            # b2dr's `_loop` step (conditioning embedding once per run, as its pipeline runs) against the
            # diffusers step, which its ControlNet pipeline runs whole (embedding included) at every step
            for bk in [k, k + "_loop"]:
                if bk in b:
                    bm = b[bk].get("min_ms", float("nan"))
                    print(f"{bk:<40} {b[bk]['ms']:>10.2f} {v['ms']:>10.2f} {b[bk]['ms'] / v['ms']:>16.3f}"
                          f" {bm:>14.2f} {v['min_ms']:>8.2f} {bm / v['min_ms']:>7.3f}")
    else:
        print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
