#!/usr/bin/env python3
"""The training curves of a b2dr-nano run (docs/training.md): the diffusion stage's loss and the VAE stage's L1,
both as a running mean over 50 steps beside the raw per-step values, and the learning rate.

    python tools/plot_training.py --diffusion RUN/log.csv --vae VAE_RUN/log.csv --out docs/b2dr-nano-training.png

Several diffusion runs that continued one another (each started with --init-from the previous one's export) are
drawn one after the other: `--diffusion A/log.csv:2250 B/log.csv --labels "eps, v weight" "v prediction"`
(`:N` keeps a run's first N steps: the step it was exported at).

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


def save(fig, title, out):
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--diffusion", required=True, nargs="+", help="log.csv[:LAST_STEP] of each continued run, in order")
    p.add_argument("--labels", nargs="+", default=None, help="one label per --diffusion run")
    p.add_argument("--vae", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="b2dr-nano training (2-vCPU CPU, 1 thread)")
    a = p.parse_args()
    runs = []
    for spec in a.diffusion:
        path, _, last = spec.partition(":")
        r = read(path)
        if last:
            keep = r["step"] <= int(last)
            r = {k: x[keep] for k, x in r.items()}
        runs.append(r)
    labels = a.labels or [f"run {i + 1}" for i in range(len(runs))]
    if len(labels) != len(runs):
        raise SystemExit(f"--labels: {len(labels)} labels for {len(runs)} runs")
    v = read(a.vae)
    fig, ax = plt.subplots(1, 3, figsize=(15, 5.6))
    offset = 0
    for i, (d, lab) in enumerate(zip(runs, labels)):
        x = d["step"] + offset
        ax[0].plot(x, d["loss"], color="0.8", lw=0.5, label="per step" if i == 0 else None)
        ax[0].plot(x, running(d["loss"]), color=f"C{i}", label=f"{lab} (mean of 50)")
        ax[2].plot(x, d["lr"], color=f"C{i}", label=f"diffusion: {lab}")
        offset = x[-1]
    ax[0].set(title="diffusion: training loss", xlabel="step (batch 8), runs continued one after the other",
              yscale="log")
    ax[0].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    ax[1].plot(v["step"], v["l1"], color="0.8", lw=0.5, label="per step")
    ax[1].plot(v["step"], running(v["l1"]), color="C3", label="mean of 50")
    ax[1].set(title="VAE: L1 reconstruction (per pixel, [-1, 1])", xlabel="step (batch 8, 56x104 crops)", yscale="log")
    ax[1].legend()
    ax[2].plot(v["step"], v["lr"], color="k", ls="--", label="VAE")
    ax[2].set(title="learning rate", xlabel="step")
    ax[2].legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    save(fig, a.title, a.out)


if __name__ == "__main__":
    main()
