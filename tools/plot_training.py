#!/usr/bin/env python3
"""The training curves of a b2dr-nano run (docs/training.md): the diffusion stage's epsilon loss and the VAE
stage's L1, both as a running mean over 50 steps beside the raw per-step values, and the learning rate.

    python tools/plot_training.py --diffusion RUN/log.csv --vae VAE_RUN/log.csv --out docs/b2dr-nano-training.png

Needs matplotlib (a development tool, not part of the test environment: pip install matplotlib).
"""
import argparse
import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def read(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def running(x, n=50):
    c = np.cumsum(np.insert(x, 0, 0.0))
    out = np.empty_like(x)
    for i in range(len(x)):
        lo = max(0, i + 1 - n)
        out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--diffusion", required=True)
    p.add_argument("--vae", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="b2dr-nano training (2-vCPU CPU, 1 thread)")
    a = p.parse_args()
    d, v = read(a.diffusion), read(a.vae)
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    ax[0].plot(d["step"], d["loss"], color="0.8", lw=0.5, label="per step")
    ax[0].plot(d["step"], running(d["loss"]), color="C0", label="mean of 50")
    ax[0].set(title="diffusion: epsilon MSE", xlabel="step (batch 8)", yscale="log")
    ax[0].legend()
    ax[1].plot(v["step"], v["l1"], color="0.8", lw=0.5, label="per step")
    ax[1].plot(v["step"], running(v["l1"]), color="C1", label="mean of 50")
    ax[1].set(title="VAE: L1 reconstruction (per pixel, [-1, 1])", xlabel="step (batch 8, 56x104 crops)", yscale="log")
    ax[1].legend()
    ax[2].plot(d["step"], d["lr"], label="diffusion")
    ax[2].plot(v["step"], v["lr"], label="VAE")
    ax[2].set(title="learning rate", xlabel="step")
    ax[2].legend()
    fig.suptitle(a.title)
    fig.tight_layout()
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
