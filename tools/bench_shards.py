#!/usr/bin/env python3
"""Peak memory of the sharded training data through a DataLoader, against the data set's size (issue #33 item 4;
BENCHMARKS.md "Training data pipeline", docs/training.md "At the paper's scale").

    B2DR_PY=~/.cache/b2dr-venv/bin/python tools/bench_shards.py [--rows 2000,20000] [--size 32x56] [--cameras 2]
        [--workers 2] [--batch 16] [--pe] [--dir /tmp/b2dr-bench-shards]

For each row count: a synthetic shard folder (python -m b2dr_ref.training.shard_bench synthetic; kept in --dir and
reused), then --epochs full epochs through a shuffled DataLoader with --workers processes in a FRESH process (python -m
b2dr_ref.training.shard_bench measure), which reports its own and its workers' peak RSS and the peak of their summed
PSS (psutil, sampled every 50 ms). Prints a markdown table. With --pe the items are the trainer's (common.
CameraSamples: sample + PETR encodings at SD1.5's PE settings), else the bare ShardSource. As the sd15 recipe, the
main process calls gc.freeze() before the workers fork (--no-gc-freeze: not).
"""
import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run(py, args):
    env = dict(os.environ, PYTHONPATH=str(REPO / "python"), OMP_NUM_THREADS="1")
    r = subprocess.run([py, "-m", "b2dr_ref.training.shard_bench"] + args, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(r.stdout + r.stderr)
    return json.loads(r.stdout.strip().splitlines()[-1])


def cpu_name():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", default="2000,20000")
    p.add_argument("--size", default="32x56")
    p.add_argument("--cameras", type=int, default=2)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--pe", action="store_true", help="the trainer's items (sample + PETR encodings)")
    p.add_argument("--no-gc-freeze", action="store_true", help="no gc.freeze() before the workers fork")
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--dir", default="/tmp/b2dr-bench-shards")
    a = p.parse_args()
    py = os.environ.get("B2DR_PY") or str(Path.home() / ".cache/b2dr-venv/bin/python")
    results = []
    for n in [int(v) for v in a.rows.split(",")]:
        d = Path(a.dir) / f"rows{n}-{a.size}-c{a.cameras}"
        if not (d / "index.json").exists():
            t = time.perf_counter()
            run(py, ["synthetic", "--out", str(d), "--rows", str(n), "--size", a.size, "--cameras", str(a.cameras),
                     "--perturb-every", "10"])
            print(f"wrote {d} ({time.perf_counter() - t:.0f} s)", file=sys.stderr)
        args = ["measure", "--data", str(d), "--workers", str(a.workers), "--batch", str(a.batch),
                "--epochs", str(a.epochs)]
        if not a.pe:
            args.append("--no-pe")
        if a.no_gc_freeze:
            args.append("--no-gc-freeze")
        r = run(py, args)
        r["bytes"] = sum(f.stat().st_size for f in d.iterdir())
        results.append(r)
        print(json.dumps(r), file=sys.stderr)
    print(f"{cpu_name()}, {os.cpu_count()} CPUs, {datetime.date.today()}; {a.size}, {a.cameras} cameras, "
          f"{a.workers} workers, batch {a.batch}, {a.epochs} epoch(s), items: "
          f"{'CameraSamples (PE)' if a.pe else 'ShardSource'}, gc.freeze {'no' if a.no_gc_freeze else 'yes'}")
    print("| rows | samples | folder MB | s / epoch | main before MB | main peak MB | worker peak MB | "
          "summed PSS peak MB |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['rows']} | {r['samples']} | {r['bytes'] / 2**20:.1f} | {r['seconds']:.0f} | "
              f"{r['main_before_mb']:.0f} | {r['peak_main_mb']:.0f} | {r['peak_worker_mb']:.0f} | "
              f"{r['peak_pss_total_mb']:.0f} |")


if __name__ == "__main__":
    main()
