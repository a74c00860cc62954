"""What the single-process recipes (b2dr_ref.train: the diffusion stage, b2dr_ref.vae_train: the VAE stage) share,
so that neither recipe imports the other: the common command-line flags, threads, the learning-rate schedule, the
one-file checkpoint written atomically, and the frozen VAE's loader. (The accelerate recipes share training.common.)"""

from __future__ import annotations

import argparse
import math
import os
from typing import Dict, List, Optional

import torch

CKPT = "checkpoint.pt"


def lr_lambda(warmup: int, total: int, min_ratio: float = 0.0, anneal: Optional[List] = None):
    """Linear warm-up, then cosine to ``min_ratio`` at ``total``. ``anneal = [s0, end, r0]`` (``--end-at``): from
    step s0 on, a cosine from ratio r0 (the schedule's own value at s0, so the lr is continuous) to 0 at ``end``."""
    def f(step):
        if anneal is not None and step >= anneal[0]:
            s0, end, r0 = anneal
            return r0 * 0.5 * (1 + math.cos(math.pi * min(1.0, (step - s0) / max(1, end - s0))))
        if step < warmup:
            return (step + 1) / max(1, warmup)
        p = min(1.0, (step - warmup) / max(1, total - warmup))
        return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * p))
    return f


def end_at_anneal(warmup: int, total: int, anneal: Optional[List], step: int, end_at: Optional[int]):
    """The anneal of ``--end-at END`` on a resume at ``step``: [step, END, the current lr ratio], or the run's own
    anneal when it already ends at END (a later resume of the same annealed run). None without --end-at."""
    if end_at is None:
        return anneal
    if anneal is not None and anneal[1] == end_at:
        return anneal
    if end_at <= step:
        raise SystemExit(f"--end-at {end_at}: the run is already at step {step}")
    return [step, end_at, lr_lambda(warmup, total, anneal=anneal)(step)]


def set_threads(device: str, threads: Optional[int]):
    torch.set_flush_denormal(True)     # denormal floats are ~100x slower on x86 CPUs
    if device == "cpu":
        torch.set_num_threads(int(threads) if threads else (os.cpu_count() or 1))


def save_checkpoint(path: str, state: Dict):
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_vae(path: str):
    from diffusers import AutoencoderKL

    return AutoencoderKL.from_pretrained(path, torch_dtype=torch.float32).eval().requires_grad_(False)


def add_common(p: argparse.ArgumentParser):
    p.add_argument("--data", required=True, help="exported dataset folder, or synthetic[:N]")
    p.add_argument("--out", required=True, help="run folder (checkpoint.pt, log.csv, run.json)")
    p.add_argument("--config", default="nano", help="model config (nano.py): nano or test")
    p.add_argument("--steps", type=int, default=10000)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--weight-decay", type=float, default=1e-2)
    p.add_argument("--warmup", type=int, default=500)
    p.add_argument("--clip", type=float, default=1.0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: all cores)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ckpt-every", type=int, default=250)
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt")
    p.add_argument("--stop-after", type=int, default=0,
                   help="stop after this many steps of this invocation (the schedule still spans --steps)")
    p.add_argument("--fixed-batch", action="store_true", help="always samples 0..B-1 (overfit check)")
