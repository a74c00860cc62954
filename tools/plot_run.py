#!/usr/bin/env python3
"""One diffusion run's curves beside what its snapshots draw (docs/training.md "Item 3"): the training loss (per
step and a running mean), and per evaluated snapshot the held-out and training prediction MSE at fixed t and the
held-out PSNRs, all from `tools/diagnose_renderer.py --json` files.

    python tools/plot_run.py --log RUN/log.csv --held-out STEP=diag.json ... [--train STEP=diag.json ...] \
        --out docs/FIGURE.png [--title ...]

Needs matplotlib (a development tool, not part of the test environment: pip install matplotlib).
"""
import argparse
import json

from plot_training import plt, read, running, save   # tools/ (the script's folder) is on sys.path


def snapshots(specs):
    """["STEP=path.json", ...] -> (steps, list of the JSON dicts), sorted by step."""
    out = []
    for s in specs or []:
        step, sep, path = s.partition("=")
        if not sep or not step.isdigit():
            raise SystemExit(f"{s!r}: expected STEP=diag.json")
        with open(path) as f:
            out.append((int(step), json.load(f)))
    out.sort(key=lambda p: p[0])
    return [p[0] for p in out], [p[1] for p in out]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--log", required=True, help="the run's log.csv (step, loss, lr, ...)")
    p.add_argument("--held-out", nargs="+", required=True, help="STEP=diagnose_renderer JSON on held-out frames")
    p.add_argument("--train", nargs="*", default=None, help="STEP=diagnose_renderer JSON on training frames")
    p.add_argument("--mean-of", type=int, default=250)
    p.add_argument("--out", required=True)
    p.add_argument("--title", default="diffusion run")
    a = p.parse_args(argv)
    log = read(a.log)
    step, loss = log["step"], log["loss"]
    hs, hd = snapshots(a.held_out)
    ts, td = snapshots(a.train)

    fig, ax = plt.subplots(1, 3, figsize=(15, 5))
    ax[0].plot(step, loss, color="0.85", lw=0.4, label="per step")
    ax[0].plot(step, running(loss, a.mean_of), color="C0", label=f"mean of {a.mean_of}")
    ax[0].set(title="training loss (weighted v MSE, random t)", xlabel="step (batch 8)", yscale="log")
    ax[0].legend()
    ax[1].plot(hs, [d["val_loss_mean"] for d in hd], "o-", color="C1", label="held-out frames")
    if ts:
        ax[1].plot(ts, [d["val_loss_mean"] for d in td], "s-", color="C2", label="training frames")
    ax[1].set(title="prediction MSE at fixed t = 100..900 (unweighted)", xlabel="step")
    ax[1].legend()
    ax[2].plot(hs, [d["sampled_psnr"] for d in hd], "o-", color="C3", label="sampled (the package's sampler)")
    ax[2].plot(hs, [d["one_shot_x0_psnr"]["999"] for d in hd], "^--", color="C4",
               label="one-shot x0 at t = 999 (the conditional mean)")
    ax[2].axhline(hd[-1]["vae_ceiling_psnr"], color="k", ls=":", label="VAE ceiling")
    ax[2].axhline(hd[-1]["copy_prev_psnr"], color="0.5", ls="-.", label="copy the previous frame")
    ax[2].set(title="held-out PSNR (dB)", xlabel="step")
    ax[2].legend(fontsize=8)
    save(fig, a.title, a.out)


if __name__ == "__main__":
    main()
