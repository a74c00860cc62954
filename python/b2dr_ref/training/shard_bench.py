"""A synthetic drive log in the export's row format (as many rows as asked, at any render size), and the memory of
reading a shard folder through a DataLoader (issue #33 item 4: "memory bounded by a stated figure whatever the
dataset size"; tools/bench_shards.py runs it, BENCHMARKS.md and docs/training.md hold the figures).

    python -m b2dr_ref.training.shard_bench synthetic --out DIR --rows 20000 [--size 32x56] [--cameras 2]
    python -m b2dr_ref.training.shard_bench measure --data DIR [--workers 2] [--batch 16] [--epochs 1]

The log: scenarios of ``steps`` log steps at 10 Hz, the ego on a gentle S-curve at 5-9 m/s; every step from 5 on
is a target (its previous frame 5 steps earlier); the references drawn from every log step with the export's rule
(shards.draw_reference_pair); a perturbed twin (ego offset 0 m, 1.5 m, 4 degrees; another target image, the same
previous frame and references) every ``perturb_every`` rows. Images: a camera-tinted gradient with a band that moves
with the step (distinct per camera and step, compressible as camera images are); masks: the lower half drivable,
one car box that moves with the step.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import threading
import time
from typing import Any, Dict, Iterator, Sequence, Tuple

import numpy as np

from . import shards

PREV_GAP = 5                     # log steps: 0.5 s at 10 Hz (plan.rs PREV_GAP_S)
PERTURB_OFFSET = (0.0, 1.5, 4.0)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = (x, y)
    return m


def _cam2ego(yaw: float) -> np.ndarray:
    """A camera at (1.5, 0, 1.6) looking along ``yaw`` (camera x right, y down, z forward)."""
    axes = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    m = _pose(0.0, 0.0, yaw) @ axes
    m[:3, 3] = (1.5, 0.0, 1.6)
    return m


def _log(scenario: int, steps: int) -> np.ndarray:
    """(steps, 3) x, y, yaw of the ego at 10 Hz."""
    k = np.arange(steps, dtype=np.float64)
    v = 7.0 + 2.0 * np.sin(0.05 * k + scenario)
    yaw = 0.3 * np.sin(0.01 * k + scenario)
    x = np.concatenate([[0.0], np.cumsum(0.1 * v[:-1] * np.cos(yaw[:-1]))]) + 1000.0 * scenario
    y = np.concatenate([[0.0], np.cumsum(0.1 * v[:-1] * np.sin(yaw[:-1]))])
    return np.stack([x, y, yaw], 1)


def synthetic_header(rows_hint: int, size: Tuple[int, int], cameras: Sequence[str], steps: int, bins=None):
    from ..controlnet import MASK_CHANNELS
    from .common import REFERENCE_BINS

    n_scen = max(1, math.ceil(rows_hint / max(1, steps - PREV_GAP)))
    return dict(format=shards.EXPORT_FORMAT, version=1, height=int(size[0]), width=int(size[1]),
                cameras=list(cameras), mask_channels=list(MASK_CHANNELS),
                mask_packing="masks_packed[s, c, y, x] bit k = mask channel k (order of mask_channels)",
                prev_gap_s=0.5, reference_intervals=bins if bins is not None else REFERENCE_BINS, seed=0,
                scenarios=[dict(name=f"synthetic-{s:05d}", source="shard_bench", steps=steps, dt=0.1)
                           for s in range(n_scen)], skipped_off_map=0)


def synthetic_rows(header: Dict[str, Any], n_rows: int, perturb_every: int = 0, seed: int = 0) -> Iterator[Dict]:
    """``n_rows`` rows (ShardWriter.add's form) of the header's scenarios; one scenario's log at a time in memory."""
    H, W = int(header["height"]), int(header["width"])
    cams = header["cameras"]
    C = len(cams)
    bins = header["reference_intervals"]
    cam_yaw = [0.0 if i == 0 else math.pi if i == 1 else 2 * math.pi * i / C for i in range(C)]
    cam2ego = np.stack([_cam2ego(y) for y in cam_yaw])
    f = 0.8 * W
    k = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([(xx * 200 // max(W - 1, 1)), (yy * 200 // max(H - 1, 1)), (xx + yy) % 64 + 96]).astype(np.int32)

    def image(s, c, step, shifted=False):
        band = ((xx + 3 * step + (7 if shifted else 0)) % W) < max(2, W // 8)
        img = base.copy()
        img[c % 3] = (img[c % 3] + 40 * c + 13 * s) % 256
        img[:, band] = 255 - img[:, band]
        return img.astype(np.uint8)

    def masks(step):
        m = np.zeros((H, W), np.uint16)
        m[H // 2:] |= 1 << 10
        x0 = (2 * step) % max(1, W - W // 4)
        m[H // 2:H // 2 + max(2, H // 6), x0:x0 + max(2, W // 6)] |= 1
        return m

    n = 0
    for s, sc in enumerate(header["scenarios"]):
        log = _log(s, int(sc["steps"]))
        poses = [_pose(*p) for p in log]
        for step in range(PREV_GAP, len(log)):
            if n == n_rows:
                return
            refs = []
            rng = np.random.default_rng([seed, s, step])
            for c in range(C):
                others = np.array([j for j in range(len(log)) if j != step])
                along = shards.along_heading(poses[step], log[others, :2])
                keep = along != 0
                pick = shards.draw_reference_pair(along[keep], bins, rng)
                if pick is None:
                    break
                refs.append([(int(others[keep][j]), float(along[keep][j])) for j in pick])
            if len(refs) < C:
                continue
            row = dict(
                target=np.stack([image(s, c, step) for c in range(C)]),
                prev=np.stack([image(s, c, step - PREV_GAP) for c in range(C)]),
                ref=np.stack([np.stack([image(s, c, j) for j, _ in refs[c]]) for c in range(C)]),
                masks_packed=np.stack([masks(step)] * C), intrinsics=np.stack([k] * C), cam2ego=cam2ego,
                ego2global=np.stack([poses[step]] * C), prev_ego2global=np.stack([poses[step - PREV_GAP]] * C),
                ref_ego2global=np.stack([np.stack([poses[j] for j, _ in refs[c]]) for c in range(C)]),
                ref_distance=np.array([[d for _, d in refs[c]] for c in range(C)], np.float32),
                ref_step=np.array([[j for j, _ in refs[c]] for c in range(C)], np.int32),
                step=np.int32(step), prev_step=np.int32(step - PREV_GAP), scenario_index=np.int32(s),
                offset=np.zeros(3), scenario=sc["name"], perturbed=False,
                refs=[[dict(step=j, distance=d, side="ahead" if d > 0 else "behind") for j, d in refs[c]]
                      for c in range(C)])
            yield row
            n += 1
            if perturb_every and n % perturb_every == 0 and n < n_rows:
                x, y, yaw = log[step]
                dx, dy, dyaw = PERTURB_OFFSET
                cy, sy = math.cos(yaw), math.sin(yaw)
                moved = _pose(x + cy * dx - sy * dy, y + sy * dx + cy * dy, yaw + math.radians(dyaw))
                twin = dict(row, target=np.stack([image(s, c, step, shifted=True) for c in range(C)]),
                            ego2global=np.stack([moved] * C), offset=np.array(PERTURB_OFFSET), perturbed=True)
                yield twin
                n += 1


EXPORT_TENSORS = ("target", "prev", "ref", "masks_packed", "intrinsics", "cam2ego", "ego2global", "prev_ego2global",
                  "ref_ego2global", "ref_distance", "ref_step", "step", "prev_step", "scenario_index", "offset")


def write_export(rows, header: Dict[str, Any], out: str, shard_samples: int = 64) -> Dict[str, Any]:
    """Rows in the RAW export's format (what `b2dr export-training` writes, docs/training_data.md: safetensors
    shards of stacked rows + index.json), for tests and benchmarks without the b2dr binary."""
    from safetensors.numpy import save_file

    os.makedirs(out, exist_ok=True)
    shards_json, samples, buf = [], [], []

    def flush():
        if not buf:
            return
        name = f"shard_{len(shards_json):05d}.safetensors"
        t = {k: np.ascontiguousarray(np.stack([np.asarray(r[k]) for r in buf])) for k in EXPORT_TENSORS}
        save_file(t, os.path.join(out, name), metadata=dict(format=shards.EXPORT_FORMAT, version="1"))
        shards_json.append(dict(file=name, samples=len(buf)))
        buf.clear()

    for r in rows:
        samples.append(dict(shard=len(shards_json), row=len(buf), scenario=r["scenario"],
                            scenario_index=int(r["scenario_index"]), step=int(r["step"]), prev_step=int(r["prev_step"]),
                            offset=np.asarray(r["offset"]).tolist(), perturbed=bool(r["perturbed"]), refs=r["refs"]))
        buf.append(r)
        if len(buf) == shard_samples:
            flush()
    flush()
    index = dict(header, shards=shards_json, samples=samples)
    with open(os.path.join(out, "index.json"), "w") as f:
        json.dump(index, f)
    return index


def write_synthetic(out: str, rows: int, size=(32, 56), cameras: int = 2, steps: int = 200, shard_rows: int = 256,
                    perturb_every: int = 0, image_format: str = "png", workers: int = 0) -> Dict[str, Any]:
    names = ["CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    header = synthetic_header(rows, size, names[:cameras], steps)
    return shards.write_rows(synthetic_rows(header, rows, perturb_every), header, out, shard_rows, image_format,
                             workers=workers)


# ---------------------------------------------------------------------------------------------------------------
# Peak memory of a DataLoader over a shard folder
# ---------------------------------------------------------------------------------------------------------------


class PeConfigLike(dict):
    """The keys CameraSamples reads of a ControlNet config (item and attribute access, as diffusers' FrozenDict)."""
    __getattr__ = dict.__getitem__


# SD1.5's PE settings (controlnet.B2DR_DEFAULTS; every Ref-Attn location of its four blocks)
SD15_PE = PeConfigLike(pe_depth_num=64, pe_depth_start=1.0, pe_position_range=[-61.2, -61.2, -10.0, 61.2, 61.2, 10.0],
                       ref_attn=["down.0", "down.1", "down.2", "down.3", "mid"],
                       block_out_channels=[320, 640, 1280, 1280])


class RssSampler:
    """Samples this process and its children (psutil) every ``period`` s in a thread: each process's first and
    peak resident set (RSS), and the peak of the processes' summed proportional set (PSS: a page shared by n
    processes counts 1/n in each, so the sum is the memory the group holds; a sum of RSS counts the libraries that
    forked workers share with the main process once per process)."""

    def __init__(self, period: float = 0.05):
        import psutil

        self.me = psutil.Process(os.getpid())
        self.period = period
        self.peak_pss_total = 0
        self.first: Dict[int, int] = {}
        self.peak: Dict[int, int] = {}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def sample(self):
        import psutil

        pss = 0
        for p in [self.me] + self.me.children(recursive=True):
            try:
                m = p.memory_full_info()
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            pss += getattr(m, "pss", m.rss)
            self.first.setdefault(p.pid, m.rss)
            self.peak[p.pid] = max(self.peak.get(p.pid, 0), m.rss)
        self.peak_pss_total = max(self.peak_pss_total, pss)

    def _run(self):
        while not self.stop.is_set():
            self.sample()
            time.sleep(self.period)

    def __enter__(self):
        self.sample()
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def _count(items):
    return len(items)


class _Bare:
    """CameraSamples without the PETR encodings: the source's samples only (the epoch shared with the workers)."""

    def __init__(self, data: str):
        from .common import CameraSamples

        self.inner = CameraSamples.__new__(CameraSamples)
        self.data = data
        self.src = None
        import multiprocessing

        self._epoch = multiprocessing.Value("i", 0, lock=False)
        self.n = len(shards.ShardSource(data))

    def set_epoch(self, e: int):
        self._epoch.value = int(e)

    def __len__(self):
        return self.n

    def __getitem__(self, i: int):
        if self.src is None or self.src.files.pid not in (None, os.getpid()):
            self.src = shards.ShardSource(self.data)
        self.src.set_epoch(self._epoch.value)
        return self.src[int(i)]


def measure(data: str, workers: int = 2, batch: int = 16, epochs: int = 1, pe: bool = True, max_samples: int = 0,
            period: float = 0.05, gc_freeze: bool = True) -> Dict[str, Any]:
    """Iterates the shard folder ``epochs`` times through a DataLoader (shuffled, ``workers`` processes) -- with
    ``pe`` the trainer's CameraSamples (sample + PETR encodings at SD1.5's PE settings), else the bare ShardSource
    -- and returns the peak resident memory (MB) of this process and of its workers and the peak of their summed
    PSS. ``gc_freeze``: as the sd15 recipe does before its workers fork."""
    import torch

    from .common import CameraSamples, collate_fn

    src = shards.ShardSource(data)
    if pe:
        ds = CameraSamples(data, src.render_size, SD15_PE)
        collate = collate_fn
    else:
        ds, collate = _Bare(data), _count
    n = len(ds) if not max_samples else min(len(ds), max_samples)
    sampler = torch.utils.data.RandomSampler(range(len(ds)), num_samples=n, generator=torch.Generator().manual_seed(0))
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, sampler=sampler, collate_fn=collate,
                                         num_workers=workers, persistent_workers=workers > 0,
                                         prefetch_factor=2 if workers > 0 else None)
    mb = 1024.0 * 1024.0
    if gc_freeze:
        import gc

        gc.collect()
        gc.freeze()     # the parent's objects out of the workers' collections (fewer copy-on-write pages)
    seen, t0 = 0, time.perf_counter()
    me = os.getpid()
    with RssSampler(period) as rs:
        for e in range(epochs):
            ds.set_epoch(e)
            for b in loader:
                seen += int(b["index"].shape[0]) if isinstance(b, dict) else int(b)
        rs.sample()
        kids = [pid for pid in rs.peak if pid != me]

        def r(v):
            return round(v / mb, 1)

        out = dict(rows=src.n_rows, samples=seen, epochs=epochs, workers=workers, batch=batch, pe=pe, gc_freeze=gc_freeze,
                   seconds=round(time.perf_counter() - t0, 2), main_before_mb=r(rs.first[me]),
                   peak_main_mb=r(rs.peak[me]),
                   worker_first_mb=r(min((rs.first[p] for p in kids), default=0)),
                   peak_worker_mb=r(max((rs.peak[p] for p in kids), default=0)),
                   peak_pss_total_mb=r(rs.peak_pss_total),
                   ru_maxrss_self_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1))
    del loader
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.training.shard_bench", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("synthetic", help="write a synthetic shard folder")
    a.add_argument("--out", required=True)
    a.add_argument("--rows", type=int, required=True)
    a.add_argument("--size", default="32x56", help="HxW")
    a.add_argument("--cameras", type=int, default=2)
    a.add_argument("--steps", type=int, default=200, help="log steps per scenario")
    a.add_argument("--shard-rows", type=int, default=256)
    a.add_argument("--perturb-every", type=int, default=0)
    a.add_argument("--format", choices=["png", "jpeg"], default="png")
    a.add_argument("--workers", type=int, default=0)
    b = sub.add_parser("measure", help="peak RSS of a DataLoader over a shard folder (JSON on stdout)")
    b.add_argument("--data", required=True)
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--batch", type=int, default=16)
    b.add_argument("--epochs", type=int, default=1)
    b.add_argument("--max-samples", type=int, default=0)
    b.add_argument("--no-pe", action="store_true", help="the bare ShardSource (no PETR encodings)")
    b.add_argument("--no-gc-freeze", action="store_true",
                   help="no gc.freeze() before the workers fork (the sd15 recipe freezes)")
    args = p.parse_args(argv)
    if args.cmd == "synthetic":
        h, w = (int(v) for v in args.size.lower().split("x"))
        t = time.perf_counter()
        idx = write_synthetic(args.out, args.rows, (h, w), args.cameras, args.steps, args.shard_rows,
                              args.perturb_every, args.format, args.workers)
        print(json.dumps(dict(rows=idx["rows"], shards=len(idx["shards"]), seconds=round(time.perf_counter() - t, 1))))
        return idx
    torch_threads = os.environ.get("OMP_NUM_THREADS")
    if torch_threads is None:
        import torch

        torch.set_num_threads(1)
    r = measure(args.data, args.workers, args.batch, args.epochs, pe=not args.no_pe, max_samples=args.max_samples,
                gc_freeze=not args.no_gc_freeze)
    print(json.dumps(r))
    return r


if __name__ == "__main__":
    main(sys.argv[1:])
