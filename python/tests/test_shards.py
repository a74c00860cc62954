"""The sharded training data (python/b2dr_ref/training/shards.py; issue #33 item 4).

- pack: a `b2dr export-training` folder (built-in scenarios with a perturbed offset; the Python-written raw export
  when there is no b2dr binary, printed) -> shards; every row reads back equal to the raw export's (PNG), within
  JPEG_MAX_MEAN_ABS / JPEG_MIN_PSNR (JPEG quality 95, 4:4:4); masks and poses exactly in both;
- references re-drawn per epoch on a dense synthetic log (shard_bench): reproducible for (seed, epoch), different
  between epochs and seeds, every one inside a distance bin measured from the poses (perturbed samples: from the
  logged pose), slot 0 ahead and slot 1 behind where the log has both, the bins' frequencies; the image and pose of
  a drawn reference are the logged frame's (its target image, its ego2global); DataLoader workers see the epoch;
- memory: over an epoch of 10x the rows a DataLoader worker's resident memory grows by at most MEMORY_GROWTH_MB
  more (the full figures: tools/bench_shards.py, BENCHMARKS.md);
- the sd15 recipe trains from a shard folder (in this process, a tiny SD1.5-shaped folder), the epoch reaching the
  source.
"""
import json
import math
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from b2dr_ref.dataset import TrainingSet  # noqa: E402
from b2dr_ref.training import common, shard_bench, shards  # noqa: E402

# JPEG quality 95, no chroma subsampling; worst image measured: the built-in scenarios' 24 x 40 renders (much detail
# per pixel) mean |error| 2.84 levels, PSNR 36.5 dB; the Python-written fallback export 0.90, 45.5 dB
JPEG_QUALITY = 95
JPEG_MAX_MEAN_ABS = 4.0
JPEG_MIN_PSNR = 33.0
# a DataLoader worker's RSS growth over an epoch (after its first 32 items) of 60 vs 600 rows (16 x 32, one camera):
# measured 0.00-0.02 MB for both (three runs); a reader that kept the decoded images it read: 0.02 / 1.77 MB (fails)
MEMORY_GROWTH_MB = 0.5
BINS = common.REFERENCE_BINS


def b2dr_binary():
    from scale_helpers import b2dr_binary as find

    try:
        return find()
    except pytest.skip.Exception:
        return None


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """Built-in scenarios with a perturbed offset (b2dr export-training), else the Python-written raw export."""
    out = str(tmp_path_factory.mktemp("export"))
    exe = b2dr_binary()
    if exe is None:
        print("test_shards: no b2dr binary: packing the Python-written raw export (shard_bench.write_export)")
        header = shard_bench.synthetic_header(12, (24, 40), ["CAM_FRONT", "CAM_BACK"], 20)
        shard_bench.write_export(shard_bench.synthetic_rows(header, 12, perturb_every=3), header, out, 5)
        return out
    subprocess.run([exe, "export-training", "--scenario", "builtin:straight:1", "builtin:town:2", "--out", out,
                    "--size", "24x40", "--samples-per-scenario", "4", "--offsets", "0,0,0;0,-1.5,4",
                    "--cameras", "CAM_FRONT,CAM_BACK", "--shard-samples", "5", "--seed", "5", "--quiet"], check=True)
    return out


@pytest.fixture(scope="module")
def packed(export, tmp_path_factory):
    out = str(tmp_path_factory.mktemp("shards"))
    shards.main(["pack", "--data", export, "--out", out, "--shard-rows", "3"])
    return out


@pytest.fixture(scope="module")
def dense(tmp_path_factory):
    """A synthetic log: one camera, 160-step scenarios at 10 Hz, every step a target, a perturbed twin every 10th."""
    out = str(tmp_path_factory.mktemp("dense"))
    shard_bench.write_synthetic(out, 600, size=(16, 32), cameras=1, steps=160, perturb_every=10)
    return out


def assert_rows_equal(a, b, images_exact=True):
    assert a.keys() == b.keys(), a.keys() ^ b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
            if images_exact or k not in ("target", "prev", "ref"):
                assert np.array_equal(a[k], b[k]), k
        else:
            assert a[k] == b[k], (k, a[k], b[k])


def test_pack_png_reads_back_the_export_exactly(export, packed):
    ds, sh = TrainingSet(export), shards.ShardSet(packed)
    assert len(sh) == len(ds) and sh.cameras == ds.cameras
    assert any(s["perturbed"] for s in ds.samples)
    for i in range(len(ds)):
        assert_rows_equal(ds[i], sh.export_row(i))
    idx = json.load(open(os.path.join(packed, "index.json")))
    assert (idx["format"], idx["version"], idx["image_format"]) == ("b2dr-training-shards", 1, "png")
    assert idx["reference_intervals"] == ds.index["reference_intervals"]
    # rows.jsonl: each row's shard, members (offsets as tar reads them), poses
    lines = [json.loads(line) for line in open(os.path.join(packed, "rows.jsonl"))]
    assert [d["row"] for d in lines] == list(range(len(ds)))
    for d in lines[:4]:
        s, raw = ds.samples[d["row"]], ds[d["row"]]
        assert (d["scenario"], d["step"], d["perturbed"], d["offset"]) == \
            (s["scenario"], s["step"], s["perturbed"], s["offset"])
        np.testing.assert_array_equal(np.array(d["ego2global"]), raw["ego2global"])
        np.testing.assert_array_equal(np.array(d["ref_ego2global"]), raw["ref_ego2global"])
        with tarfile.open(os.path.join(packed, idx["shards"][d["shard"]]["file"])) as tf:
            m = tf.getmember(f"{d['key']}.CAM_BACK.ref1.png")
            assert [m.offset_data, m.size] == d["members"]["CAM_BACK"]["ref1"]
            assert json.load(tf.extractfile(f"{d['key']}.json"))["step"] == s["step"]


def test_pack_jpeg_within_the_stated_error(export, tmp_path):
    out = str(tmp_path / "jpeg")
    shards.pack(export, out, image_format="jpeg", quality=JPEG_QUALITY)
    ds, sh = TrainingSet(export), shards.ShardSet(out)
    assert sh.index["jpeg"] == {"quality": JPEG_QUALITY, "subsampling": "4:4:4"}
    worst_mae, worst_psnr = 0.0, math.inf
    for i in range(len(ds)):
        a, b = ds[i], sh.export_row(i)
        assert_rows_equal(a, b, images_exact=False)       # masks, poses, steps exactly
        for k in ("target", "prev", "ref"):
            d = a[k].astype(np.float64) - b[k].astype(np.float64)
            worst_mae = max(worst_mae, float(np.abs(d).mean()))
            worst_psnr = min(worst_psnr, 10 * math.log10(255.0 ** 2 / max(float((d ** 2).mean()), 1e-12)))
    print(f"JPEG q{JPEG_QUALITY}: worst mean |error| {worst_mae:.2f}, worst PSNR {worst_psnr:.1f} dB")
    assert worst_mae <= JPEG_MAX_MEAN_ABS and worst_psnr >= JPEG_MIN_PSNR, (worst_mae, worst_psnr)


def draws(src, items, epoch):
    src.set_epoch(epoch)
    return [[(r["row"], r["member"], r["step"]) for r in src.references(i)] for i in items]


def test_references_are_redrawn_each_epoch_and_reproducible(dense):
    a, b = shards.ShardSource(dense, seed=3), shards.ShardSource(dense, seed=3)
    items = range(0, len(a), 7)
    e0, e1 = draws(a, items, 0), draws(a, items, 1)
    assert draws(b, items, 0) == e0 and draws(b, items, 1) == e1          # a fresh reader, the same draws
    assert sum(x != y for x, y in zip(e0, e1)) > 0.8 * len(e0)
    assert sum(x != y for x, y in zip(e0, draws(shards.ShardSource(dense, seed=4), items, 0))) > 0.8 * len(e0)
    a.set_epoch(1)
    b.set_epoch(1)
    s, t = a[11], b[11]
    np.testing.assert_array_equal(s.refs, t.refs)
    np.testing.assert_array_equal(s.ref_ego2global, t.ref_ego2global)


def test_drawn_references_lie_in_the_bins_ahead_and_behind(dense):
    src = shards.ShardSource(dense, bins=BINS)
    n = len(src)
    logged = {}                                   # (scenario, step) -> the unperturbed row's pose and image
    for r in range(src.n_rows):
        rec = src.record(r)
        if not rec["perturbed"]:
            logged[(int(rec["scenario_index"]), int(rec["step"]))] = (np.array(rec["ego2global"][0]), r)
    counts, both_sides, checked_images = np.zeros(3), 0, 0
    for epoch in range(2):
        src.set_epoch(epoch)
        for i in range(0, n, 2):
            rec = src.record(i)
            s = src[i]
            cur = logged[(int(rec["scenario_index"]), int(rec["step"]))][0]      # the logged pose, also if perturbed
            if not rec["perturbed"]:
                np.testing.assert_array_equal(cur, s.ego2global)
            p = shards.along_heading(cur, s.ref_ego2global[:, :2, 3])
            # (StopIteration: a reference outside every bin)
            bins = [next(k for k, (lo, hi, _) in enumerate(BINS) if lo <= abs(d) < hi) for d in p]
            refs = src.references(i)
            assert [r["redrawn"] for r in refs] == [True, True]
            np.testing.assert_allclose(p, [r["along"] for r in refs], atol=1e-9)
            # the reference is a logged frame of the scenario: its target image and its ego2global
            for slot, r in enumerate(refs):
                pose, row = logged[(int(rec["scenario_index"]), r["step"])] \
                    if (int(rec["scenario_index"]), r["step"]) in logged else (None, None)
                np.testing.assert_array_equal(s.ref_ego2global[slot], r["ego2global"])
                if row is not None and checked_images < 40:
                    np.testing.assert_array_equal(s.ref_ego2global[slot], pose)
                    np.testing.assert_array_equal(s.refs[slot], src.export_row(row)["target"][0])
                    checked_images += 1
            # mid-log (15 m of log on both sides): slot 0 ahead, slot 1 behind, the bins' frequencies
            if 25 <= int(rec["step"]) <= 135:
                assert p[0] > 0 > p[1], p
                both_sides += 1
                for k in bins:
                    counts[k] += 1
    freq = counts / counts.sum()
    print(f"reference bins over {int(counts.sum())} draws: {np.round(freq, 3).tolist()} (want 0.1 / 0.3 / 0.6)")
    assert both_sides > 200 and checked_images == 40
    np.testing.assert_allclose(freq, [b[2] for b in BINS], atol=0.05)


def test_without_logged_images_in_the_bins_the_export_references_stay(packed):
    src = shards.ShardSource(packed, bins=[[1e5, 2e5, 1.0]])
    for i in range(len(src)):
        r, c = divmod(i, len(src.cameras))
        s, row = src[i], src.export_row(r)
        assert [x["redrawn"] for x in src.references(i)] == [False, False]
        np.testing.assert_array_equal(s.refs, row["ref"][c])
        np.testing.assert_array_equal(s.ref_ego2global, row["ref_ego2global"][c])


class _Tiny(dict):
    __getattr__ = dict.__getitem__


TINY_PE = _Tiny(pe_depth_num=4, pe_depth_start=1.0, pe_position_range=[-61.2, -61.2, -10.0, 61.2, 61.2, 10.0],
                ref_attn=["down.0", "mid"], block_out_channels=[16, 16, 32])


def test_dataloader_workers_draw_for_the_trainers_epoch(dense):
    """CameraSamples.set_epoch in this process reaches the source in a persistent DataLoader worker."""
    ds = common.CameraSamples(dense, (16, 32), TINY_PE, seed=7)
    assert ds.redraws
    items = list(range(0, 48, 3))
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, items), batch_size=len(items),
                                         collate_fn=common.collate_fn, num_workers=1, persistent_workers=True)
    ref = shards.ShardSource(dense, seed=7)
    got = {}
    for epoch in (0, 1, 0):
        ds.set_epoch(epoch)
        (batch,) = list(loader)
        ref.set_epoch(epoch)
        np.testing.assert_array_equal(batch["refs"].numpy(), np.stack([ref[i].refs for i in items]))
        got.setdefault(epoch, batch["refs"].numpy())
    assert not np.array_equal(got[0], got[1])


class _RssPerItem(shard_bench._Bare):
    """The bare source's items, each answered with the worker's resident memory after reading it."""

    def __getitem__(self, i):
        import psutil

        super().__getitem__(i)
        return psutil.Process().memory_info().rss


def _worker_growth_mb(data: str, warm_up: int = 32) -> float:
    """One epoch of the bare source through a DataLoader with one worker: the worker's largest RSS over the epoch
    minus its RSS after the first ``warm_up`` items (imports, first decodes)."""
    ds = _RssPerItem(data)
    loader = torch.utils.data.DataLoader(ds, batch_size=16, collate_fn=list, num_workers=1)
    rss = [v for b in loader for v in b]
    assert len(rss) == len(ds)
    return (max(rss[warm_up:]) - rss[warm_up]) / 2 ** 20


def test_reader_memory_does_not_grow_with_the_rows(dense, tmp_path):
    small = str(tmp_path / "small")
    shard_bench.write_synthetic(small, 60, size=(16, 32), cameras=1, steps=160, perturb_every=10)
    assert len(shards.ShardSet(dense)) == 10 * len(shards.ShardSet(small))
    g_small, g_large = _worker_growth_mb(small), _worker_growth_mb(dense)
    print(f"DataLoader worker RSS growth: {g_small:.2f} MB over 60 rows, {g_large:.2f} MB over 600 rows")
    assert g_large - g_small <= MEMORY_GROWTH_MB, (g_small, g_large)


def _in_process(args):
    from accelerate.state import AcceleratorState, GradientState

    from b2dr_ref.training import sd15

    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    old = os.environ.get("ACCELERATE_USE_CPU")
    os.environ["ACCELERATE_USE_CPU"] = "true"
    try:
        return sd15.main(sd15.parse_args([str(a) for a in args]))
    finally:
        AcceleratorState._reset_state(True)
        GradientState._reset_state()
        if old is None:
            os.environ.pop("ACCELERATE_USE_CPU")
        else:
            os.environ["ACCELERATE_USE_CPU"] = old


def test_sd15_trains_from_a_shard_folder(packed, tmp_path, monkeypatch):
    """Three optimizer steps over two epochs of the packed export (16 camera samples, batch 8): finite losses, a
    checkpoint, and the trainer's epochs reaching the source (references drawn for epochs 0 and 1)."""
    from b2dr_ref.training.tiny_sd15 import write_tiny_sd15

    seen = []
    orig = shards.ShardSource.set_epoch
    monkeypatch.setattr(shards.ShardSource, "set_epoch", lambda self, e: (seen.append(int(e)), orig(self, e)))
    pretrained = write_tiny_sd15(str(tmp_path / "sd15"))
    out = str(tmp_path / "run")
    n = len(shards.ShardSource(packed))
    step = _in_process(["--pretrained", pretrained, "--data", packed, "--output_dir", out, "--resolution", "24x40",
                        "--pe_depth_num", "4", "--conditioning_embedding_out_channels", "8,16,16,32",
                        "--train_batch_size", str(n // 2), "--max_train_steps", "3", "--lr_warmup_steps", "1",
                        "--validation_steps", "0", "--report_to", "none", "--checkpointing_steps", "10"])
    assert step == 3
    rows = [line.split(",") for line in open(os.path.join(out, "log.csv")).read().split()[1:]]
    assert [int(r[0]) for r in rows] == [1, 2, 3] and all(math.isfinite(float(r[1])) for r in rows)
    assert os.path.isdir(os.path.join(out, "checkpoint-3"))
    assert {0, 1} <= set(seen), seen
