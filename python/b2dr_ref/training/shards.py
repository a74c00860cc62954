"""The training data compressed and sharded, references re-drawn at every epoch (issue #33 item 4;
docs/training_data.md "Shards").

    python -m b2dr_ref.training.shards pack --data EXPORT --out DIR [--shard-rows 256] [--format png|jpeg]
                                            [--quality 95] [--workers N]
    python -m b2dr_ref.training.shards info DIR

``pack`` turns a ``b2dr export-training`` folder (raw uint8 safetensors rows, dataset.TrainingSet) into:

    DIR/index.json          format, version, the export's header, image codec, shards, the files below
    DIR/shard-00000.tar     rows in the WebDataset layout: per row ``KEY.json`` (the row's metadata and poses) and
                            per camera ``KEY.CAM.target.png``, ``.prev.png``, ``.ref0.png``, ``.ref1.png`` (the
                            export's references) and ``KEY.CAM.masks.png`` (the bit-packed masks as a 16-bit PNG)
    DIR/rows.jsonl          the index, one JSON line per row: shard, byte offset and size of each member, scenario,
                            step, poses, perturbed flag, ego offset, the export's references
    DIR/rows.npy            the same per-row fields as fixed-size binary records (what the reader reads)
    DIR/candidates.npy      the logged images of every (scenario, camera) (targets of unperturbed rows, previous
    DIR/candidate_ranges.npy    frames, the export's references; one per log step), sorted, with their poses

Images are PNG (lossless, the default) or JPEG (``--quality``, 4:4:4); masks are always PNG (lossless). Tar, PNG
and JPEG are written by the standard library's tarfile and Pillow; a WebDataset pipeline can stream the shards.

``ShardSource`` (training/data.py's SampleSource; ``open_source`` returns it for a shard folder) reads one camera
sample at a time with ``os.pread`` from the shards and from the record files: nothing of the data set is held in
memory or memory-mapped (memory does not grow with the data set: tools/bench_shards.py, BENCHMARKS.md). Each process
(DataLoader worker) opens its own file descriptors, at most ``max_open`` shards at once. Its references are drawn
again for every epoch (``set_epoch``) from the logged images of the sample's scenario, with the export's rule
(src/projection/retrieval.rs ``sample_reference_pair``): per slot a distance bin by the bins' probabilities (2-5 /
5-10 / 10-15 m at 0.1 / 0.3 / 0.6, the export's ``reference_intervals``), slot 0 an image AHEAD along the logged
heading, slot 1 one BEHIND, the other side's image where that side has none in the bin, another bin (renormalised)
where the bin is empty on both sides; seeded by (seed, epoch, sample index). A sample whose scenario holds no
stored logged image within the bins keeps the export's references.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import sys
import tarfile
from collections import OrderedDict
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

FORMAT = "b2dr-training-shards"
VERSION = 1
EXPORT_FORMAT = "b2dr-training"        # dataset.FORMAT: the raw export's
IMAGES = ("target", "prev", "ref0", "ref1")
MEMBERS = IMAGES + ("masks",)
TARGET, PREV, REF0, REF1, MASKS = range(5)
DEFAULT_QUALITY = 95
# the export's header keys kept in index.json (dataset.TrainingSet's, less its per-row samples and shards)
HEADER_KEYS = ("height", "width", "cameras", "mask_channels", "mask_packing", "matrices", "prev_gap_s",
               "reference_intervals", "seed", "scenarios", "skipped_off_map")
# one logged image of a (scenario, camera): its log step, where it is stored (row, member; shard, byte offset and
# size in that shard) and its ego -> global
CANDIDATE = np.dtype([("step", "<i4"), ("row", "<i4"), ("member", "u1"), ("shard", "<i4"), ("offset", "<i8"),
                      ("size", "<i8"), ("ego2global", "<f8", (4, 4))])


def row_dtype(cameras: int) -> np.dtype:
    """One record of rows.npy (C cameras): the export's per-row tensors, the logged pose and the members' places."""
    c = int(cameras)
    return np.dtype([
        ("shard", "<i4"), ("scenario_index", "<i4"), ("step", "<i4"), ("prev_step", "<i4"), ("perturbed", "u1"),
        ("offset", "<f8", (3,)),
        ("intrinsics", "<f8", (c, 3, 3)), ("cam2ego", "<f8", (c, 4, 4)), ("ego2global", "<f8", (c, 4, 4)),
        ("prev_ego2global", "<f8", (c, 4, 4)), ("ref_ego2global", "<f8", (c, 2, 4, 4)),
        ("ref_distance", "<f4", (c, 2)), ("ref_step", "<i4", (c, 2)),
        # the logged pose of the target (a perturbed row's ego2global is the displaced one): references are drawn
        # along its heading, as the export draws them
        ("logged_ego2global", "<f8", (c, 4, 4)),
        ("member_offset", "<i8", (c, len(MEMBERS))), ("member_size", "<i8", (c, len(MEMBERS))),
    ])


# ---------------------------------------------------------------------------------------------------------------
# Codecs (Pillow)
# ---------------------------------------------------------------------------------------------------------------


def encode_rgb(img: np.ndarray, fmt: str = "png", quality: int = DEFAULT_QUALITY) -> bytes:
    """``img`` uint8 (3, H, W) -> PNG (lossless) or JPEG (``quality``, no chroma subsampling) bytes."""
    from PIL import Image

    im = Image.fromarray(np.ascontiguousarray(np.asarray(img, np.uint8).transpose(1, 2, 0)), "RGB")
    buf = io.BytesIO()
    if fmt == "png":
        im.save(buf, format="PNG")
    elif fmt == "jpeg":
        im.save(buf, format="JPEG", quality=int(quality), subsampling=0)
    else:
        raise ValueError(f"image format {fmt!r}: png or jpeg")
    return buf.getvalue()


def decode_rgb(data: bytes) -> np.ndarray:
    """PNG / JPEG bytes -> uint8 (3, H, W)."""
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        a = np.asarray(im.convert("RGB"))
    return np.ascontiguousarray(a.transpose(2, 0, 1))


def encode_mask(packed: np.ndarray) -> bytes:
    """Bit-packed masks uint16 (H, W) (bit k = channel k) -> 16-bit grayscale PNG (lossless)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(packed, dtype=np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def decode_mask(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        if im.mode not in ("I;16", "I;16B", "I"):
            raise ValueError(f"mask PNG of mode {im.mode}: expected 16-bit grayscale")
        return np.asarray(im).astype(np.uint16)


def unpack_masks(packed: np.ndarray, channels: int = 15) -> np.ndarray:
    """``(..., H, W)`` uint16 -> ``(..., channels, H, W)`` uint8 in {0, 1} (dataset.unpack_masks)."""
    bits = np.arange(channels, dtype=np.uint16).reshape((channels, 1, 1))
    return ((packed[..., None, :, :] >> bits) & 1).astype(np.uint8)


# ---------------------------------------------------------------------------------------------------------------
# References (the export's rule: src/projection/retrieval.rs sample_reference_pair)
# ---------------------------------------------------------------------------------------------------------------


def along_heading(ego2global: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``P_i = (xy_i - xy_ego) . v_ego`` on the ground plane (retrieval.rs ``along_distances``): v_ego is the
    pose's x axis with z dropped, normalised. ``xy``: (n, 2) -> (n,)."""
    m = np.asarray(ego2global, np.float64)
    v = m[:2, 0] / max(float(np.hypot(m[0, 0], m[1, 0])), 1e-12)
    return (np.asarray(xy, np.float64) - m[:2, 3]) @ v


def draw_reference_pair(along: np.ndarray, bins, rng: np.random.Generator) -> Optional[Tuple[int, int]]:
    """Indices into ``along`` (signed distances, the training frame itself and P = 0 left out) of the two
    references: (slot 0 = ahead, slot 1 = behind). Per slot a bin is drawn over ALL bins by their probabilities;
    the slot takes an image of its own side in it, else of the other side; a bin empty on both sides is redrawn
    among the non-empty ones (renormalised); uniform within. None when no image lies in any bin.
    ``bins``: [[lo, hi, p], ...] metres, ``lo <= |P| < hi``."""
    along = np.asarray(along, np.float64)
    b = np.asarray(bins, np.float64).reshape(-1, 3)
    a = np.abs(along)
    inside = [(a >= lo) & (a < hi) for lo, hi, _ in b]
    buckets = [[np.flatnonzero(m & (along > 0)) for m in inside], [np.flatnonzero(m & (along < 0)) for m in inside]]
    nonempty = np.array([len(buckets[0][k]) + len(buckets[1][k]) > 0 for k in range(len(b))])
    if not nonempty.any():
        return None
    p = b[:, 2]
    out = []
    for side in (0, 1):
        k = int(rng.choice(len(b), p=p / p.sum()))
        if not nonempty[k]:
            q = np.where(nonempty, p, 0.0)
            k = int(rng.choice(len(b), p=q / q.sum()))
        own = buckets[side][k]
        v = own if len(own) else buckets[1 - side][k]
        out.append(int(v[int(rng.integers(len(v)))]))
    return out[0], out[1]


def logged_pose(displaced: np.ndarray, offset) -> np.ndarray:
    """The logged ego -> global of a perturbed sample: the export displaces the logged ground pose p by the
    ego-frame offset o (``p.compose(o)``, scene/geometry.rs) and writes ``ego2global(p o)`` (z = 0, no tilt); this
    undoes it: heading = yaw - dyaw, position = position - R(heading) (dx, dy)."""
    m = np.asarray(displaced, np.float64)
    dx, dy, dyaw = float(offset[0]), float(offset[1]), math.radians(float(offset[2]))
    yaw = math.atan2(m[1, 0], m[0, 0]) - dyaw
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[0, 3] = m[0, 3] - (c * dx - s * dy)
    out[1, 3] = m[1, 3] - (s * dx + c * dy)
    return out


# ---------------------------------------------------------------------------------------------------------------
# Writer
# ---------------------------------------------------------------------------------------------------------------


def encode_row(row: Dict[str, Any], cameras: Sequence[str], fmt: str, quality: int) -> List[Tuple[str, bytes]]:
    """The tar members of one row except its KEY.json: (suffix, bytes) per camera and member."""
    out = []
    for c, cam in enumerate(cameras):
        imgs = [row["target"][c], row["prev"][c], row["ref"][c, 0], row["ref"][c, 1]]
        for name, img in zip(IMAGES, imgs):
            out.append((f"{cam}.{name}.{'png' if fmt == 'png' else 'jpg'}", encode_rgb(img, fmt, quality)))
        out.append((f"{cam}.masks.png", encode_mask(row["masks_packed"][c])))
    return out


def _encode_job(job):
    row, cameras, fmt, quality = job
    return encode_row(row, cameras, fmt, quality)


def _lists(a) -> Any:
    return np.asarray(a).tolist()


class ShardWriter:
    """Writes rows (the export's per-row tensors, as dataset.TrainingSet.raw returns them, plus ``scenario``,
    ``perturbed`` and the export's ``refs`` entry) into a shard folder; ``close`` writes the candidates and
    index.json. Memory: one row at a time, plus one entry per distinct logged image (scenario, camera, step)."""

    def __init__(self, out: str, header: Dict[str, Any], shard_rows: int = 256, image_format: str = "png",
                 quality: int = DEFAULT_QUALITY):
        if image_format not in ("png", "jpeg"):
            raise ValueError(f"--format {image_format}: png or jpeg")
        if shard_rows < 1:
            raise ValueError("--shard-rows must be >= 1")
        self.out = out
        self.header = {k: header[k] for k in HEADER_KEYS if k in header}
        self.cameras = list(header["cameras"])
        bad = [c for c in self.cameras if not c or any(ch in c for ch in "./\\")]
        if bad:
            raise ValueError(f"camera names {bad}: tar member names KEY.CAM.member take no '.', '/' or '\\'")
        self.fmt, self.quality, self.shard_rows = image_format, int(quality), int(shard_rows)
        self.dtype = row_dtype(len(self.cameras))
        os.makedirs(out, exist_ok=True)
        self.rows = 0
        self.shards: List[Dict[str, Any]] = []
        self.tar: Optional[tarfile.TarFile] = None
        self.jsonl = open(os.path.join(out, "rows.jsonl.tmp"), "w", encoding="utf-8")
        self.records = open(os.path.join(out, "rows.npy.tmp"), "wb")
        self.cands: Dict[Tuple[int, int, int], Tuple] = {}        # (scenario, camera, step) -> CANDIDATE fields

    def _member(self, name: str, data: bytes) -> Tuple[int, int]:
        ti = tarfile.TarInfo(name)
        ti.size, ti.mtime, ti.mode = len(data), 0, 0o644
        start = self.tar.offset
        self.tar.addfile(ti, io.BytesIO(data))
        # ustar: one 512-byte header block per member (a name it cannot hold is an error, not an extra header)
        return start + tarfile.BLOCKSIZE, len(data)

    def _open_shard(self):
        name = f"shard-{len(self.shards):05d}.tar"
        self.tar = tarfile.open(os.path.join(self.out, name), "w", format=tarfile.USTAR_FORMAT)
        self.shards.append(dict(file=name, rows=0))

    def _close_shard(self):
        if self.tar is not None:
            self.tar.close()
            self.shards[-1]["bytes"] = os.path.getsize(os.path.join(self.out, self.shards[-1]["file"]))
            self.tar = None

    def add(self, row: Dict[str, Any], encoded: Optional[List[Tuple[str, bytes]]] = None):
        if self.tar is None or self.shards[-1]["rows"] == self.shard_rows:
            self._close_shard()
            self._open_shard()
        if encoded is None:
            encoded = encode_row(row, self.cameras, self.fmt, self.quality)
        r, C = self.rows, len(self.cameras)
        key = f"{r:09d}"
        perturbed = bool(row["perturbed"])
        offset = np.asarray(row["offset"], np.float64)
        e2g = np.asarray(row["ego2global"], np.float64)
        logged = np.stack([logged_pose(m, offset) for m in e2g]) if perturbed else e2g
        meta = dict(row=r, key=key, shard=len(self.shards) - 1, scenario=row["scenario"],
                    scenario_index=int(row["scenario_index"]), step=int(row["step"]),
                    prev_step=int(row["prev_step"]), perturbed=perturbed, offset=_lists(offset),
                    refs=row.get("refs"), cameras=self.cameras, intrinsics=_lists(row["intrinsics"]),
                    cam2ego=_lists(row["cam2ego"]), ego2global=_lists(e2g), logged_ego2global=_lists(logged),
                    prev_ego2global=_lists(row["prev_ego2global"]), ref_ego2global=_lists(row["ref_ego2global"]),
                    ref_distance=_lists(row["ref_distance"]), ref_step=_lists(row["ref_step"]))
        start = self.tar.offset
        self._member(f"{key}.json", json.dumps(meta).encode())
        rec = np.zeros((), self.dtype)
        places: Dict[str, Dict[str, List[int]]] = {}
        for suffix, data in encoded:
            cam, member = suffix.split(".")[:2]
            c, m = self.cameras.index(cam), MEMBERS.index(member)
            off, size = self._member(f"{key}.{suffix}", data)
            rec["member_offset"][c, m], rec["member_size"][c, m] = off, size
            places.setdefault(cam, {})[member] = [off, size]
        meta.update(tar_offset=start, tar_bytes=self.tar.offset - start, members=places)
        self.jsonl.write(json.dumps(meta) + "\n")
        for k in ("scenario_index", "step", "prev_step", "intrinsics", "cam2ego", "ego2global", "prev_ego2global",
                  "ref_ego2global", "ref_distance", "ref_step"):
            rec[k] = row[k]
        rec["shard"], rec["perturbed"], rec["offset"], rec["logged_ego2global"] = \
            len(self.shards) - 1, perturbed, offset, logged
        self.records.write(rec.tobytes())
        # the logged images of this row (one candidate per scenario, camera and log step)
        si = int(row["scenario_index"])
        for c in range(C):
            own = [] if perturbed else [(int(row["step"]), TARGET, e2g[c])]
            own.append((int(row["prev_step"]), PREV, row["prev_ego2global"][c]))
            own += [(int(row["ref_step"][c, k]), REF0 + k, row["ref_ego2global"][c, k]) for k in range(2)]
            for step, member, pose in own:
                place = (len(self.shards) - 1, int(rec["member_offset"][c, member]), int(rec["member_size"][c, member]))
                self.cands.setdefault((si, c, step), (r, member) + place + (np.array(pose, np.float64),))
        self.shards[-1]["rows"] += 1
        self.rows += 1

    def close(self) -> Dict[str, Any]:
        self._close_shard()
        self.jsonl.close()
        self.records.close()
        out = self.out
        os.replace(os.path.join(out, "rows.jsonl.tmp"), os.path.join(out, "rows.jsonl"))
        # rows.npy: the npy header written before the streamed records
        with open(os.path.join(out, "rows.npy"), "wb") as f, open(os.path.join(out, "rows.npy.tmp"), "rb") as g:
            np.lib.format.write_array_header_1_0(f, dict(descr=np.lib.format.dtype_to_descr(self.dtype),
                                                         fortran_order=False, shape=(self.rows,)))
            while True:
                b = g.read(1 << 20)
                if not b:
                    break
                f.write(b)
        os.remove(os.path.join(out, "rows.npy.tmp"))
        n_scen, C = len(self.header.get("scenarios", [])), len(self.cameras)
        n_scen = max([n_scen] + [k[0] + 1 for k in self.cands])
        keys = sorted(self.cands)
        cands = np.zeros(len(keys), CANDIDATE)
        for j, k in enumerate(keys):
            cands[j] = (k[2],) + self.cands[k]
        flat = np.array([k[0] * C + k[1] for k in keys], np.int64)
        ranges = np.searchsorted(flat, np.arange(n_scen * C + 1), side="left").astype(np.int64)
        np.save(os.path.join(out, "candidates.npy"), cands)
        np.save(os.path.join(out, "candidate_ranges.npy"), ranges)
        index = dict(format=FORMAT, version=VERSION, **self.header, source_format=EXPORT_FORMAT,
                     rows=self.rows, image_format=self.fmt,
                     jpeg=dict(quality=self.quality, subsampling="4:4:4") if self.fmt == "jpeg" else None,
                     masks="KEY.CAM.masks.png: 16-bit grayscale PNG of masks_packed (bit k = mask channel k)",
                     members=list(MEMBERS), shards=self.shards,
                     files=dict(rows_jsonl="rows.jsonl", rows="rows.npy", candidates="candidates.npy",
                                candidate_ranges="candidate_ranges.npy"),
                     candidates=len(keys))
        tmp = os.path.join(out, "index.json.tmp")
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(index, f, indent=1)
        os.replace(tmp, os.path.join(out, "index.json"))
        return index


def export_rows(ds) -> Iterable[Dict[str, Any]]:
    """The rows of a raw export (dataset.TrainingSet) in ShardWriter.add's form."""
    for i in range(len(ds)):
        row = dict(ds.raw(i))
        s = ds.samples[i]
        row.update(scenario=s["scenario"], perturbed=bool(s["perturbed"]), refs=s.get("refs"))
        yield row


def write_rows(rows: Iterable[Dict[str, Any]], header: Dict[str, Any], out: str, shard_rows: int = 256,
               image_format: str = "png", quality: int = DEFAULT_QUALITY, workers: int = 0) -> Dict[str, Any]:
    """Rows -> a shard folder; ``workers`` > 0 encodes the images in that many processes (in row order)."""
    w = ShardWriter(out, header, shard_rows, image_format, quality)
    if workers > 0:
        import itertools
        import multiprocessing as mp

        it = iter(rows)
        with mp.get_context("fork").Pool(workers) as pool:
            while True:
                chunk = list(itertools.islice(it, 8 * workers))      # a bounded number of rows in flight
                if not chunk:
                    break
                for r, enc in zip(chunk, pool.map(_encode_job, [(r, w.cameras, image_format, quality)
                                                                for r in chunk])):
                    w.add(r, enc)
    else:
        for r in rows:
            w.add(r)
    return w.close()


def pack(data: str, out: str, shard_rows: int = 256, image_format: str = "png", quality: int = DEFAULT_QUALITY,
         workers: int = 0) -> Dict[str, Any]:
    """A raw export folder (b2dr export-training) -> a shard folder."""
    from ..dataset import TrainingSet

    ds = TrainingSet(data)
    return write_rows(export_rows(ds), ds.index, out, shard_rows, image_format, quality, workers)


# ---------------------------------------------------------------------------------------------------------------
# Reader
# ---------------------------------------------------------------------------------------------------------------


def is_shard_dir(path: str) -> bool:
    """A folder with index.json and rows.npy (ShardSet checks the format; a raw export's index.json, which grows
    with its rows, is not parsed here)."""
    return all(os.path.isfile(os.path.join(path, f)) for f in ("index.json", "rows.npy"))


def _npy_layout(path: str) -> Tuple[int, np.dtype, int]:
    """(data offset, dtype, rows) of a 1-D .npy file."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read:
            raise ValueError(f"{path}: .npy format version {version} (1.0 or 2.0 expected)")
        shape, fortran, dtype = read[version](f)
        if fortran or len(shape) != 1:
            raise ValueError(f"{path}: a 1-D C-order record array expected, got shape {shape}")
        return f.tell(), dtype, int(shape[0])


class _Files:
    """pread access for one process: file descriptors opened on first use, at most ``max_open`` shard files open
    (least recently used closed); a forked process (DataLoader worker) drops the parent's and opens its own."""

    def __init__(self, root: str, max_open: int = 8):
        self.root, self.max_open = root, max(1, int(max_open))
        self.pid = None
        self.fds: "OrderedDict[str, int]" = OrderedDict()

    def read(self, name: str, offset: int, size: int, pinned: bool = False) -> bytes:
        if self.pid != os.getpid():
            self.fds = OrderedDict()        # the parent's descriptors are not this process's to close
            self.pid = os.getpid()
        fd = self.fds.get(name)
        if fd is None:
            fd = os.open(os.path.join(self.root, name), os.O_RDONLY)
            self.fds[name] = fd
            shards = [k for k in self.fds if k.endswith(".tar")]
            if len(shards) > self.max_open:
                os.close(self.fds.pop(shards[0]))
        self.fds.move_to_end(name)
        b = os.pread(fd, int(size), int(offset))
        if len(b) != size:
            raise IOError(f"{os.path.join(self.root, name)}: {len(b)} of {size} bytes at offset {offset}")
        return b

    def close(self):
        if self.pid == os.getpid():
            for fd in self.fds.values():
                os.close(fd)
        self.fds = OrderedDict()

    def __getstate__(self):
        return dict(root=self.root, max_open=self.max_open, pid=None, fds=OrderedDict())


class ShardSet:
    """Random access to the rows of a shard folder; everything read on demand (pread), nothing cached."""

    def __init__(self, root: str, max_open: int = 8):
        self.root = root
        with open(os.path.join(root, "index.json"), "r", encoding="utf-8") as f:
            self.index: Dict[str, Any] = json.load(f)
        if self.index.get("format") != FORMAT or self.index.get("version") != VERSION:
            raise ValueError(f"{root}: not a {FORMAT} v{VERSION} folder (format {self.index.get('format')!r}, "
                             f"version {self.index.get('version')!r})")
        self.cameras: List[str] = list(self.index["cameras"])
        self.mask_channels: List[str] = list(self.index["mask_channels"])
        self.height, self.width = int(self.index["height"]), int(self.index["width"])
        files = self.index["files"]
        self._rows_file, self._cands_file = files["rows"], files["candidates"]
        self._rows_at, self.row_dtype, self.n_rows = _npy_layout(os.path.join(root, self._rows_file))
        if self.row_dtype != row_dtype(len(self.cameras)):
            raise ValueError(f"{root}: rows.npy records do not match {len(self.cameras)} cameras")
        self._cands_at, cd, _ = _npy_layout(os.path.join(root, self._cands_file))
        if cd != CANDIDATE:
            raise ValueError(f"{root}: candidates.npy records of another layout")
        # (scenarios x cameras + 1) int64: small, kept
        self.candidate_ranges = np.load(os.path.join(root, files["candidate_ranges"]))
        self.shard_files = [s["file"] for s in self.index["shards"]]
        self.files = _Files(root, max_open)

    def __len__(self) -> int:
        return self.n_rows

    def record(self, r: int) -> np.void:
        """Row ``r`` of rows.npy (its poses, steps, the members' places)."""
        if not 0 <= r < self.n_rows:
            raise IndexError(f"row {r} of {self.n_rows}")
        n = self.row_dtype.itemsize
        return np.frombuffer(self.files.read(self._rows_file, self._rows_at + r * n, n), self.row_dtype)[0]

    def candidates(self, scenario_index: int, camera: int) -> np.ndarray:
        """The logged images of one scenario and camera (CANDIDATE records, by step)."""
        k = int(scenario_index) * len(self.cameras) + int(camera)
        a, b = int(self.candidate_ranges[k]), int(self.candidate_ranges[k + 1])
        n = CANDIDATE.itemsize
        if b <= a:
            return np.zeros(0, CANDIDATE)
        return np.frombuffer(self.files.read(self._cands_file, self._cands_at + a * n, (b - a) * n), CANDIDATE)

    def member(self, rec: np.void, camera: int, member: int) -> bytes:
        return self.files.read(self.shard_files[int(rec["shard"])], rec["member_offset"][camera, member],
                               rec["member_size"][camera, member])

    def image(self, rec: np.void, camera: int, member: int) -> np.ndarray:
        return decode_rgb(self.member(rec, camera, member))

    def masks_packed(self, rec: np.void, camera: int) -> np.ndarray:
        return decode_mask(self.member(rec, camera, MASKS))

    def export_row(self, r: int) -> Dict[str, Any]:
        """Row ``r`` as dataset.TrainingSet[r] gives it (the export's own references)."""
        rec = self.record(r)
        C = len(self.cameras)
        e2g = np.array(rec["ego2global"])
        ref_e2g = np.array(rec["ref_ego2global"])
        cam2ego = np.array(rec["cam2ego"])
        ref_distance = np.array(rec["ref_distance"])
        return {
            "target": np.stack([self.image(rec, c, TARGET) for c in range(C)]),
            "prev": np.stack([self.image(rec, c, PREV) for c in range(C)]),
            "ref": np.stack([np.stack([self.image(rec, c, REF0), self.image(rec, c, REF1)]) for c in range(C)]),
            "masks": unpack_masks(np.stack([self.masks_packed(rec, c) for c in range(C)]), len(self.mask_channels)),
            "intrinsics": np.array(rec["intrinsics"]), "cam2ego": cam2ego, "ego2global": e2g,
            "prev_ego2global": np.array(rec["prev_ego2global"]), "ref_ego2global": ref_e2g,
            "cam2cur_ref": np.linalg.inv(e2g)[:, None] @ ref_e2g @ cam2ego[:, None],
            "ref_distance": ref_distance, "ref_step": np.array(rec["ref_step"]),
            "ref_side": [["ahead" if d > 0 else "behind" for d in cam] for cam in ref_distance.tolist()],
            "step": int(rec["step"]), "prev_step": int(rec["prev_step"]), "offset": np.array(rec["offset"]),
            "perturbed": bool(rec["perturbed"]),
            "scenario": self.index["scenarios"][int(rec["scenario_index"])]["name"],
            "cameras": self.cameras,
        }


class ShardSource(ShardSet):
    """training/data.py's SampleSource over a shard folder: item ``i = row * n_cameras + camera``, references drawn
    again at every epoch (module docs). ``bins``: [[lo, hi, p], ...] (default: the export's
    ``reference_intervals``); ``seed``: the run's seed."""

    def __init__(self, root: str, bins=None, seed: int = 0, max_open: int = 8):
        super().__init__(root, max_open)
        self.bins = np.asarray(bins if bins is not None else self.index["reference_intervals"], np.float64)
        if self.bins.ndim != 2 or self.bins.shape[1] != 3 or (self.bins[:, 2] < 0).any() or self.bins[:, 2].sum() <= 0:
            raise ValueError(f"reference bins {bins}: [[lo, hi, p], ...] with probabilities >= 0, not all 0")
        self.seed = int(seed)
        self.epoch = 0
        self.render_size = (self.height, self.width)

    def set_epoch(self, epoch: int):
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n_rows * len(self.cameras)

    def references(self, i: int, rec: Optional[np.void] = None) -> List[Dict[str, Any]]:
        """The two references of sample ``i`` at the current epoch: per slot ``row``, ``member``, ``step``,
        ``along`` (m, along the logged heading), ``ego2global``, ``redrawn`` (False: the export's, kept because
        the scenario's stored logged images hold none within the bins) and, when redrawn, ``place`` (shard, byte
        offset, size of the image)."""
        r, c = divmod(int(i), len(self.cameras))
        rec = self.record(r) if rec is None else rec
        cur = rec["logged_ego2global"][c]
        cands = self.candidates(rec["scenario_index"], c)
        cands = cands[cands["step"] != rec["step"]]
        along = along_heading(cur, cands["ego2global"][:, :2, 3])
        cands, along = cands[along != 0.0], along[along != 0.0]
        rng = np.random.default_rng([self.seed, self.epoch, int(i)])
        pick = draw_reference_pair(along, self.bins, rng)
        if pick is None:
            return [dict(row=r, member=REF0 + k, step=int(rec["ref_step"][c, k]),
                         along=float(rec["ref_distance"][c, k]), ego2global=np.array(rec["ref_ego2global"][c, k]),
                         redrawn=False) for k in range(2)]
        return [dict(row=int(cands[j]["row"]), member=int(cands[j]["member"]), step=int(cands[j]["step"]),
                     along=float(along[j]), ego2global=np.array(cands[j]["ego2global"]), redrawn=True,
                     place=(int(cands[j]["shard"]), int(cands[j]["offset"]), int(cands[j]["size"])))
                for j in pick]

    def __getitem__(self, i: int):
        from .data import Sample

        if not 0 <= int(i) < len(self):
            raise IndexError(f"sample {i} of {len(self)}")
        r, c = divmod(int(i), len(self.cameras))
        rec = self.record(r)
        refs = self.references(i, rec)
        ref_imgs = [decode_rgb(self.files.read(self.shard_files[ref["place"][0]], *ref["place"][1:]))
                    if ref["redrawn"] else self.image(rec, c, ref["member"]) for ref in refs]
        return Sample(target=self.image(rec, c, TARGET), prev=self.image(rec, c, PREV), refs=np.stack(ref_imgs),
                      masks=unpack_masks(self.masks_packed(rec, c), len(self.mask_channels)),
                      k=np.array(rec["intrinsics"][c]), cam2ego=np.array(rec["cam2ego"][c]),
                      ego2global=np.array(rec["ego2global"][c]), prev_ego2global=np.array(rec["prev_ego2global"][c]),
                      ref_ego2global=np.stack([ref["ego2global"] for ref in refs]), camera=self.cameras[c])


# ---------------------------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------------------------


def info(root: str) -> Dict[str, Any]:
    s = ShardSet(root)
    shard_bytes = sum(int(x.get("bytes", 0)) for x in s.index["shards"])
    C, H, W = len(s.cameras), s.height, s.width
    raw = s.n_rows * C * (4 * 3 + 2) * H * W       # the raw export's image + mask bytes (docs/training_data.md)
    return dict(rows=s.n_rows, cameras=C, size=[H, W], shards=len(s.shard_files), shard_bytes=shard_bytes,
                raw_image_bytes=raw, ratio=raw / max(shard_bytes, 1), image_format=s.index["image_format"],
                jpeg=s.index.get("jpeg"), candidates=s.index.get("candidates"))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.training.shards", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack", help="a b2dr export-training folder -> a shard folder")
    a.add_argument("--data", required=True, help="the export folder (index.json + shard_*.safetensors)")
    a.add_argument("--out", required=True)
    a.add_argument("--shard-rows", type=int, default=256, help="rows (all cameras of one target) per tar shard")
    a.add_argument("--format", choices=["png", "jpeg"], default="png", help="images: png (lossless) or jpeg")
    a.add_argument("--quality", type=int, default=DEFAULT_QUALITY, help="JPEG quality (4:4:4)")
    a.add_argument("--workers", type=int, default=0, help="processes encoding images (0: this one)")
    b = sub.add_parser("info", help="rows, bytes and compression of a shard folder")
    b.add_argument("dir")
    args = p.parse_args(argv)
    if args.cmd == "pack":
        idx = pack(args.data, args.out, args.shard_rows, args.format, args.quality, args.workers)
        print(json.dumps(info(args.out)))
        return idx
    r = info(args.dir)
    print(json.dumps(r, indent=1))
    return r


if __name__ == "__main__":
    main(sys.argv[1:])
