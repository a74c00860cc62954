#!/usr/bin/env python3
"""The training curve of the image-reading planner (docs/e2e_planner.md): train and held-out L1 (normalised pose
units) and the held-out L2 error of the 4 s pose, per epoch.

    python tools/plot_planner.py --log RUN/log.csv --out docs/e2e-planner-training.png

Needs matplotlib (a development tool, not part of the test environment: pip install matplotlib).
"""
import argparse
import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--log", required=True)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    rows = list(csv.DictReader(open(a.log)))
    ep = [int(r["epoch"]) for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(ep, [float(r["train_l1"]) for r in rows], label="train (jittered)")
    ax1.plot(ep, [float(r["val_l1"]) for r in rows], label="held-out seeds 100-101")
    ax1.set_xlabel("epoch")
    ax1.set_ylabel("L1 (x/10 m, y/1 m, heading/0.1 rad)")
    ax1.set_yscale("log")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.plot(ep, [float(r["val_l2_4s_m"]) for r in rows], color="C1")
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("held-out L2 of the 4 s pose (m)")
    ax2.grid(alpha=0.3)
    fig.suptitle("e2e planner: imitation on ground-truth cameras (1 CPU thread)")
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)


if __name__ == "__main__":
    main()
