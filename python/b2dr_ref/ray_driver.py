"""Scale-out of `b2dr sim` / `b2dr run` on Ray (spec loop.md 3, docs/scale_out.md): one Ray task per shard
(`--shard K/N`, `num_gpus` / `num_cpus` per task), failed shards retried (every attempt runs with `--resume`, so a
retry skips the scenarios an earlier attempt finished), progress as shards finish, and `b2dr merge` at the end.

    python -m b2dr_ref.ray_driver --shards 3 --out out/ray [--b2dr PATH] [--num-gpus 1] [--num-cpus 2] \\
        [--retries 2] [--address auto] -- run --scenario builtin:town:0,builtin:cross:0,... --renderer b2dr

Everything after `--` is the b2dr command line without `--shard`, `--resume` and `--out`, which the driver adds:
shard K writes `OUT/shard-K/`, the merge `OUT/merged/metrics.json`. On a multi-node cluster OUT and the b2dr
binary must be reachable at the same paths on every node (a shared filesystem). With `num_gpus`, Ray sets each
task's CUDA_VISIBLE_DEVICES and b2dr picks the Vulkan device of that GPU (docs/scale_out.md "Device pinning").
Ray is imported only by `run` (pip install ray).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

RESERVED = ("--shard", "--resume", "--out")


def shard_command(b2dr: str, args: Sequence[str], k: int, n: int, out: Path) -> list[str]:
    """The command line of shard k of n (the same for every attempt: it resumes)."""
    return [b2dr, *args, "--shard", f"{k}/{n}", "--resume", "--out", str(out)]


def run_shard(b2dr: str, args: Sequence[str], k: int, n: int, out: str) -> dict:
    """Runs one shard to the end; raises (and Ray retries the task) when b2dr fails or is killed."""
    t0 = time.time()
    cmd = shard_command(b2dr, args, k, n, Path(out))
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"shard {k}/{n} failed (exit {p.returncode}): {' '.join(cmd)}\n{p.stderr[-4000:]}")
    with open(Path(out) / "metrics.json") as f:
        summary = json.load(f)
    return {"shard": k, "folder": out, "scenarios": len(summary["scenarios"]), "cls": summary["cls"],
            "failures": summary.get("failures", 0), "seconds": time.time() - t0, "host": socket.gethostname(),
            "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}


def run(b2dr_args: Sequence[str], shards: int, out: str | os.PathLike, b2dr: str = "b2dr", num_gpus: float = 0,
        num_cpus: float = 1, retries: int = 2, address: Optional[str] = None,
        progress: Callable[[str], None] = print) -> dict:
    """Runs the shards as Ray tasks, then merges them; returns the merged metrics.json.

    Raises RuntimeError naming the shards that still failed after `retries` retries (their folders keep what
    was finished: rerunning the driver resumes them) or when `b2dr merge` refuses the folders."""
    import ray

    if shards < 1:
        raise ValueError("shards must be at least 1")
    for a in b2dr_args:
        if a.split("=")[0] in RESERVED:
            raise ValueError(f"{a}: the driver sets --shard, --resume and --out itself")
    exe = shutil.which(b2dr) or b2dr
    exe = str(Path(exe).resolve())
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    dirs = [out / f"shard-{k}" for k in range(shards)]
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False)
    # the task's code travels with it: workers need not import b2dr_ref
    if run_shard.__module__ != "__main__":
        ray.cloudpickle.register_pickle_by_value(sys.modules[run_shard.__module__])
    task = ray.remote(num_gpus=num_gpus, num_cpus=num_cpus, max_retries=retries,
                      retry_exceptions=True)(run_shard)
    t0 = time.time()
    refs = {task.remote(exe, list(b2dr_args), k, shards, str(dirs[k])): k for k in range(shards)}
    progress(f"{shards} shard(s) submitted (num_gpus={num_gpus}, num_cpus={num_cpus}, retries={retries})")
    pending, done, failed = list(refs), [], {}
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for r in ready:
            k = refs[r]
            try:
                info = ray.get(r)
            except Exception as e:  # the task failed after all its retries
                failed[k] = e
                progress(f"shard {k}/{shards} FAILED after {retries} retries: {str(e).splitlines()[0]}")
                continue
            done.append(info)
            progress(f"shard {k}/{shards} done [{len(done) + len(failed)}/{shards}, {time.time() - t0:.0f} s]: "
                     f"{info['scenarios']} scenario(s), CLS {info['cls']:.4f}, {info['failures']} failure(s), "
                     f"host {info['host']}, CUDA_VISIBLE_DEVICES={info['cuda_visible_devices']!r}")
    if failed:
        raise RuntimeError(f"shard(s) {sorted(failed)} of {shards} failed; rerun the driver to resume them:\n"
                           + "\n".join(f"{k}: {e}" for k, e in sorted(failed.items())))
    merged = out / "merged"
    p = subprocess.run([exe, "merge", *map(str, dirs), "--out", str(merged)], stdout=subprocess.PIPE,
                       stderr=subprocess.PIPE, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"b2dr merge failed: {p.stderr.strip()}")
    with open(merged / "metrics.json") as f:
        summary = json.load(f)
    progress(f"merged {shards} shard(s): {len(summary['scenarios'])} scenario(s), {summary['cls_kind']} "
             f"{summary['cls']:.4f} -> {merged / 'metrics.json'}")
    return summary


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        print(__doc__, file=sys.stderr)
        print("error: give the b2dr command after --", file=sys.stderr)
        return 2
    i = argv.index("--")
    ap = argparse.ArgumentParser(prog="python -m b2dr_ref.ray_driver",
                                 description="b2dr sim/run shards as Ray tasks, merged at the end")
    ap.add_argument("--shards", type=int, required=True, help="number of shards (Ray tasks)")
    ap.add_argument("--out", required=True, help="output folder: shard-K/ per shard, merged/")
    ap.add_argument("--b2dr", default=os.environ.get("B2DR_BIN", "b2dr"), help="the b2dr binary")
    ap.add_argument("--num-gpus", type=float, default=0, help="GPUs per shard task (Ray resource)")
    ap.add_argument("--num-cpus", type=float, default=1, help="CPUs per shard task (Ray resource)")
    ap.add_argument("--retries", type=int, default=2, help="retries of a failed shard (each resumes)")
    ap.add_argument("--address", default=None, help="Ray cluster address (default: a local cluster)")
    a = ap.parse_args(argv[:i])
    try:
        run(argv[i + 1:], a.shards, a.out, b2dr=a.b2dr, num_gpus=a.num_gpus, num_cpus=a.num_cpus,
            retries=a.retries, address=a.address, progress=lambda m: print(m, flush=True))
    except (RuntimeError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
