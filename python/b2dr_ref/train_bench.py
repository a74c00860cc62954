"""``python -m b2dr_ref.train bench``: training throughput of a config (docs/training.md "Throughput").

One setting (the flags of the trainer's fast path) or ``--sweep``: the documented set-up, the best eager f32
setting and each fast path, measured one after the other in ONE process (this machine is noisy: compare the
ratios of one run). Per setting: samples per second (batch / median step), the first steps (compile time), and
with ``--profile`` where the step's CPU time goes (self time per op class: convolution, GroupNorm, SiLU,
attention, matmul, elementwise, copies, optimizer, compiled regions). ``--data-prep`` times the trainer's
per-sample preparation (VAE encodes + PE) with and without the latents cache. The step is the trainer's:
``train.diffusion_loss`` + backward + clip + AdamW, every row with references unless ``--ref-dropout``.
"""

from __future__ import annotations

import json
import re
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np
import torch

from .fastpath import FastPath


@dataclass(frozen=True)
class Setting:
    name: str
    batch: int
    threads: int
    fast: FastPath


def sweep_settings(batch: int, threads: int) -> List[Setting]:
    """The table of docs/training.md: the documented set-up (batch 8, one thread), the best eager f32 (``batch``,
    ``threads``), then each fast path alone and combined at that batch and thread count."""
    big = dict(batch=batch, threads=threads)
    return [
        Setting("documented: eager f32, batch 8, 1 thread", 8, 1, FastPath()),
        Setting(f"eager f32, batch {batch}, {threads} threads", fast=FastPath(), **big),
        Setting("channels_last", fast=FastPath(channels_last=True), **big),
        Setting("autocast bf16", fast=FastPath(autocast="bf16"), **big),
        Setting("compile", fast=FastPath(compile=True), **big),
        Setting("compile + channels_last", fast=FastPath(compile=True, channels_last=True), **big),
    ]


# op-name patterns -> class (first match wins; self CPU time, so nested ops are not counted twice)
OP_CLASSES = [
    ("compiled region", r"Torch-Compiled Region|CompiledFunction|cpp_fused|kernel_cpp|graph_\d"),
    ("convolution", r"conv|mkldnn_convolution"),
    ("group_norm", r"group_norm"),
    ("silu", r"silu"),
    ("attention", r"bmm|baddbmm|softmax|scaled_dot_product|attention"),
    ("matmul / linear", r"addmm|\bmm\b|aten::mm|linear|matmul"),
    ("optimizer", r"_foreach|adamw|Optimizer"),
    ("copies", r"copy_|contiguous|clone|aten::cat|aten::to\b|_to_copy|empty_strided|as_strided|index"),
    ("elementwise", r"add|mul|sub|div|sqrt|exp|pow|neg|where|fill|zero|sum|mean|var|clamp|lerp|rsub|sigmoid"),
]


def classify(name: str) -> str:
    for cls, pat in OP_CLASSES:
        if re.search(pat, name):
            return cls
    return "other"


def conv_backend() -> str:
    """Which ATen kernel runs the step's convolutions on this CPU (from the profiler's op names): oneDNN
    (``aten::mkldnn_convolution``, its AVX2 / AVX-512 / AMX path chosen by the CPU) or a fallback."""
    from torch.profiler import ProfilerActivity, profile

    c = torch.nn.Conv2d(32, 32, 3, padding=1)
    x = torch.randn(2, 32, 14, 25, requires_grad=True)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        c(x).sum().backward()
    names = [e.key for e in prof.key_averages()]
    for k in ("aten::mkldnn_convolution", "aten::_slow_conv2d_forward", "aten::thnn_conv2d"):
        if k in names:
            return k
    return "unknown"


def cpu_flags() -> Dict[str, bool]:
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((ln.split(":", 1)[1].split() for ln in f if ln.startswith("flags")), [])
    except OSError:
        flags = []
    return {k: k in flags for k in ("avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile", "avx512_fp16")}


def build(cfg, device, seed: int = 0):
    from .train import build_diffusion_models

    unet, controlnet = build_diffusion_models(cfg, seed=seed)
    return unet.to(device).train(), controlnet.to(device).train()


def make_batch(cfg, batch: int, device):
    """A batch of the synthetic source at the config's size, through the trainer's Batcher (returns it and the
    Batcher's seconds per sample, VAE encodes + PE included)."""
    from .train import Batcher, SyntheticSource
    from .vae_train import build_vae

    src = SyntheticSource(n=batch, render_size=cfg["render_size"])
    vae = build_vae(cfg).to(device).eval().requires_grad_(False)
    _, controlnet = build(cfg, device)
    t0 = time.perf_counter()
    b = Batcher(src, vae, controlnet, device).batch(list(range(batch)))
    return b, src, (time.perf_counter() - t0) / batch


def time_setting(cfg, s: Setting, steps: int, device, ref_dropout: float, profile: bool = False,
                 warmup: Optional[int] = None) -> Dict:
    from .train import diffusion_loss, make_context, make_noise_scheduler, optimizer_step

    torch.set_num_threads(s.threads)
    unet, controlnet = build(cfg, device)
    unet_f, cn_f = s.fast.prepare(unet, controlnet)
    params = list(unet.parameters()) + list(controlnet.parameters())
    opt = torch.optim.AdamW(params, lr=1e-4)
    b, src, _ = make_batch(cfg, s.batch, device)
    ctx = make_context(cfg, src.cameras)
    gen = torch.Generator().manual_seed(0)
    abar = make_noise_scheduler().alphas_cumprod.to(torch.float32)
    warm = (3 if s.fast.compile else 1) if warmup is None else warmup
    # fp16 steps as the trainer takes them: with its loss scaler
    scaler = torch.amp.GradScaler(device.type) if s.fast.autocast == "fp16" else None

    def step():
        loss = diffusion_loss(unet_f, cn_f, ctx, b, gen, abar, ref_dropout=ref_dropout, fast=s.fast)
        optimizer_step(loss, params, opt, 1.0, scaler)
        if device.type == "cuda":
            torch.cuda.synchronize()
        return float(loss.detach())

    first = []
    for _ in range(warm):
        t0 = time.perf_counter()
        step()
        first.append(time.perf_counter() - t0)
    times, cpu = [], []
    for _ in range(steps):
        t0, c0 = time.perf_counter(), time.process_time()
        step()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    med = float(np.median(times))
    res = dict(setting=s.name, fast=s.fast.describe(), batch=s.batch, threads=s.threads, steps=steps,
               step_s_median=med, step_s_min=float(min(times)), samples_per_s=s.batch / med,
               warmup_s=[round(v, 2) for v in first], cpu_s_per_step=float(np.median(cpu)))
    if profile:
        res["profile"] = profile_steps(step, 2)
    return res


def profile_steps(step, n: int) -> Dict[str, float]:
    """Share of the self CPU time per op class over ``n`` steps."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            step()
    per: Dict[str, float] = defaultdict(float)
    for ev in prof.key_averages():
        per[classify(ev.key)] += ev.self_cpu_time_total
    total = sum(per.values()) or 1.0
    return {k: round(v / total, 4) for k, v in sorted(per.items(), key=lambda kv: -kv[1])}


def data_prep(cfg, device, n: int = 8) -> Dict[str, float]:
    """Seconds per sample of the trainer's preparation: uncached (4 VAE encodes + PE + masks) and with the
    latents already known (PE + masks: what a cached run pays per sample, off the step with --prefetch)."""
    from .train import Batcher, SyntheticSource
    from .vae_train import build_vae

    src = SyntheticSource(n=n, render_size=cfg["render_size"])
    vae = build_vae(cfg).to(device).eval().requires_grad_(False)
    _, controlnet = build(cfg, device)
    bt = Batcher(src, vae, controlnet, device, cache=0, latents=("/nonexistent/latents.pt", "k"))
    t0 = time.perf_counter()
    bt.batch(list(range(n)))
    cold = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    bt.batch(list(range(n)))          # latents from the latents-file table, PE recomputed (cache=0)
    warm = (time.perf_counter() - t0) / n
    return dict(uncached_s_per_sample=cold, latents_known_s_per_sample=warm)


def bench(args) -> Dict:
    from .train import run_config, set_threads

    set_threads(args.device, args.threads)
    device = torch.device(args.device)
    cfg = run_config(args)
    threads = int(args.threads or torch.get_num_threads())
    info = dict(config=cfg["name"], render_size=cfg["render_size"], device=args.device, torch=torch.__version__,
                cpu_capability=torch.backends.cpu.get_cpu_capability(), cpu_flags=cpu_flags(),
                ref_dropout=args.ref_dropout)
    if device.type == "cpu":
        info["conv_kernel"] = conv_backend()
    print(json.dumps(info), flush=True)
    if args.sweep:
        settings = sweep_settings(args.batch, threads)
    else:
        fp = FastPath(channels_last=args.channels_last, compile=args.compile, autocast=args.autocast)
        settings = [Setting(fp.describe(), args.batch, threads, fp)]
    rows = []
    for s in settings:
        try:
            r = time_setting(cfg, s, args.steps, device, args.ref_dropout, profile=args.profile)
        except Exception as e:      # a fast path this machine cannot run (e.g. compile without a C++ compiler)
            r = dict(setting=s.name, fast=s.fast.describe(), batch=s.batch, threads=s.threads,
                     error=f"{type(e).__name__}: {str(e).splitlines()[0][:300]}")
        rows.append(r)
        print(json.dumps(r), flush=True)
    set_threads(args.device, threads)
    res = dict(info, rows=rows)
    ok = [r for r in rows if "samples_per_s" in r]
    eager = [r for r in ok if r["fast"] == "eager f32"]
    if eager:
        best_eager = max(eager, key=lambda r: r["samples_per_s"])
        best = max(ok, key=lambda r: r["samples_per_s"])
        res["best_eager_f32"] = best_eager["setting"]
        res["best"] = best["setting"]
        res["speedup_best_vs_best_eager_f32"] = best["samples_per_s"] / best_eager["samples_per_s"]
    if args.data_prep:
        res["data_prep"] = data_prep(cfg, device)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)
    print_table(res)
    return res


def print_table(res: Dict):
    print(f"\n{res['config']} {res['render_size'][0]}x{res['render_size'][1]}, {res['device']}, torch {res['torch']}, "
          f"CPU capability {res['cpu_capability']}, convolutions: {res.get('conv_kernel', '-')}")
    print("| setting | batch | threads | s / step | samples / s | first steps (s) |")
    print("|---|---|---|---|---|---|")
    for r in res["rows"]:
        if "error" in r:
            print(f"| {r['setting']} | {r['batch']} | {r['threads']} | failed: {r['error']} | | |")
        else:
            print(f"| {r['setting']} | {r['batch']} | {r['threads']} | {r['step_s_median']:.3f} | "
                  f"{r['samples_per_s']:.1f} | {r['warmup_s']} |")
    if "speedup_best_vs_best_eager_f32" in res:
        print(f"best: {res['best']}: {res['speedup_best_vs_best_eager_f32']:.2f}x the best eager f32 "
              f"({res['best_eager_f32']})")
    for r in res["rows"]:
        if "profile" in r:
            top = ", ".join(f"{k} {100 * v:.0f} %" for k, v in r["profile"].items() if v >= 0.01)
            print(f"profile [{r['setting']}]: {top}")
    if "data_prep" in res:
        d = res["data_prep"]
        print(f"data preparation: {d['uncached_s_per_sample']:.3f} s / sample uncached, "
              f"{d['latents_known_s_per_sample']:.3f} s with the latents known")
