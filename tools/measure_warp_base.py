"""How close the residual renderer's base is to the frame it must draw: PSNR of the previous frame (as the model
is given it: optionally warped to the current pose, b2dr_ref/warp.py, then blurred) against the current frame, over
all pixels, lane-marking pixels (masks crosswalk + lane_divider) and vehicle pixels (car .. construction_vehicle),
per camera group (CAM_FRONT / the others) and logged vs displaced samples, on a `b2dr export-training` folder.

    PYTHONPATH=python python tools/measure_warp_base.py DATA [--shards 0,7,14] [--depth 30]
"""
import argparse
import glob
import json
import os
import sys

import numpy as np
import torch
from safetensors import safe_open

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))
from b2dr_ref.controlnet import MASK_CHANNELS  # noqa: E402
from b2dr_ref.frame import gaussian_blur  # noqa: E402
from b2dr_ref.warp import ground_warp_grid, warp_image  # noqa: E402


def bits(names):
    """The masks_packed bits of these mask channels (bit k = channel k of the export's mask_channels)."""
    return sum(1 << MASK_CHANNELS.index(n) for n in names)


VEHICLE_BITS = bits(["car", "truck", "bus", "trailer", "construction_vehicle"])
MARKING_BITS = bits(["crosswalk", "lane_divider"])


def psnr(a, b, m=None):
    d = ((a - b) ** 2).mean(0)
    if m is not None:
        if m.sum() < 1:
            return None
        d = d[m]
    return float(10 * torch.log10(1 / d.mean()))


def at_source(grid, mask):
    """(H, W) bool: the pixels whose warp source (``grid`` (H, W, 2), NaN: none) falls on ``mask`` (H, W) bool of
    the source image, looked up at the nearest source pixel."""
    ok = np.isfinite(grid).all(-1)
    H, W = mask.shape
    x = np.clip(np.rint(np.nan_to_num(grid[..., 0])), 0, W - 1).astype(int)
    y = np.clip(np.rint(np.nan_to_num(grid[..., 1])), 0, H - 1).astype(int)
    return ok & mask[y, x]


def layout_masked(grid, cur_vehicle, prev_vehicle):
    """The grid with NaN (keep the previous image's own pixel) where the current pixel is a vehicle
    (``cur_vehicle`` (H, W) bool or None) or its source in the previous frame is one (``prev_vehicle`` or None)."""
    g = grid.copy()
    drop = np.zeros(g.shape[:2], bool)
    if cur_vehicle is not None:
        drop |= cur_vehicle
    if prev_vehicle is not None:
        drop |= at_source(g, prev_vehicle)
    g[drop] = np.nan
    return g


def inpaint(img, hole, sigma):
    """(1, 3, H, W) image with the (H, W) bool ``hole`` pixels replaced by the Gaussian-weighted mean of the
    pixels around them that are not holes (normalised convolution; a hole with no such pixel keeps its value)."""
    keep = torch.from_numpy(~hole).float()[None, None]
    num = gaussian_blur(img * keep, sigma)
    den = gaussian_blur(keep, sigma)
    fill = torch.where(den > 1e-3, num / den.clamp_min(1e-3), img)
    return torch.where(torch.from_numpy(hole)[None, None], fill, img)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data")
    p.add_argument("--shards", default="0,7,14", help="shard numbers to read")
    p.add_argument("--depth", type=float, default=30.0, help="the warp's depth cap, metres")
    a = p.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "shard_*.safetensors")))
    if not files:
        raise SystemExit(f"{a.data}: no shard_*.safetensors (a b2dr export-training folder)")
    with open(os.path.join(a.data, "index.json")) as fh:
        index = json.load(fh)
    if list(index["mask_channels"]) != list(MASK_CHANNELS):
        raise SystemExit(f"{a.data}: mask channels {index['mask_channels']} differ from the model's {MASK_CHANNELS}")
    cameras = list(index["cameras"])
    stats = {}
    for k in [int(x) for x in a.shards.split(",")]:
        if k >= len(files):
            raise SystemExit(f"--shards: {a.data} has {len(files)} shards")
        f = safe_open(files[k], "np")
        t, pv, mk = f.get_tensor("target"), f.get_tensor("prev"), f.get_tensor("masks_packed")
        kk, c2e = f.get_tensor("intrinsics"), f.get_tensor("cam2ego")
        e2g, pe2g, off = f.get_tensor("ego2global"), f.get_tensor("prev_ego2global"), f.get_tensor("offset")
        pmk = f.get_tensor("prev_masks_packed") if "prev_masks_packed" in f.keys() else None
        for i in range(t.shape[0]):
            for c in range(t.shape[1]):
                tgt = torch.from_numpy(t[i, c]).float() / 255
                prv = torch.from_numpy(pv[i, c]).float()[None] / 255
                m = mk[i, c]
                masks = {"all": None, "marking": torch.from_numpy((m & MARKING_BITS) > 0),
                         "vehicle": torch.from_numpy((m & VEHICLE_BITS) > 0)}
                g = ground_warp_grid(kk[i, c], c2e[i, c], e2g[i, c], pe2g[i, c], tgt.shape[1:], a.depth)
                w = warp_image(prv, torch.from_numpy(g)[None])
                cur_v = (m & VEHICLE_BITS) > 0
                bases = [("blur 1", gaussian_blur(prv, 1.0)), ("warp + blur 0.5", gaussian_blur(w, 0.5)),
                         ("warp + blur 1", gaussian_blur(w, 1.0))]
                variants = [("cur", cur_v, None)]
                if pmk is not None:
                    prev_v = (pmk[i, c] & VEHICLE_BITS) > 0
                    variants += [("src", None, prev_v), ("cur+src", cur_v, prev_v)]
                    ghost = at_source(g, prev_v) & ~cur_v
                    masks["ghost"] = torch.from_numpy(ghost)
                    for sg in (2.0, 4.0, 8.0):
                        bases.append((f"warp, ghosts inpainted (sigma {sg:g}) + blur 0.5",
                                      gaussian_blur(inpaint(w, ghost, sg), 0.5)))
                for vn, cv, pv_ in variants:
                    wm = warp_image(prv, torch.from_numpy(layout_masked(g, cv, pv_))[None])
                    bases.append((f"warp, {vn} kept + blur 0.5", gaussian_blur(wm, 0.5)))
                group = ("front" if cameras[c] == "CAM_FRONT" else "other") + \
                    (" off-log" if np.abs(off[i]).sum() > 0 else " logged")
                for name, img in bases:
                    for mn, mm in masks.items():
                        v = psnr(tgt, img[0], mm)
                        if v is not None:
                            stats.setdefault((group, name, mn), []).append(v)
    print(f"| samples | base | all px | lane-marking px | vehicle px | ghost px |  (PSNR dB, depth cap {a.depth:g} m;"
          " ghost: not a vehicle now, a vehicle at the warp's source; a chain export only)")
    print("|---|---|---|---|---|---|")
    names = list(dict.fromkeys(k[1] for k in stats))
    for group in sorted({k[0] for k in stats}):
        for name in names:
            row = [np.mean(stats[(group, name, mn)]) if (group, name, mn) in stats else float("nan")
                   for mn in ("all", "marking", "vehicle", "ghost")]
            n = len(stats[(group, name, "all")])
            print(f"| {group} ({n}) | {name} | " + " | ".join(f"{v:.2f}" for v in row) + " |")


if __name__ == "__main__":
    main()
