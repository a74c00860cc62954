#!/usr/bin/env python3
"""Writes tests/golden/layout_seg_case.safetensors: the committed layout segmenter (models/layout-seg/
seg.safetensors) run by its PyTorch reference (python/b2dr_ref/layout_seg.py, CPU, fp32) on one image.

Run by developers, not by CI (seconds):
    ~/.cache/b2dr-venv/bin/python tools/make_golden_layout_seg.py --image WORLD_OUT/CAM_FRONT.png

The image is a `b2dr world` ground-truth render (the synthetic world: ours to commit), cropped to 41 x 73 (odd sizes) at
its centre so that it holds road, markings and (pick a frame with one) a vehicle. Tensors: `rgb` U8 (41, 73, 3),
`logits` F32 (17, 41, 73), `classes` U8 (41, 73) = argmax. tests/golden/manifest.json gets its description.
"""

import argparse
import json
import os
import sys

import numpy as np
import torch
from PIL import Image
from safetensors.numpy import save_file

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, os.path.join(ROOT, "python"))

from b2dr_ref import layout_seg  # noqa: E402

GOLDEN = os.path.join(ROOT, "tests", "golden")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--image", required=True)
    ap.add_argument("--model", default=os.path.join(ROOT, "models", "layout-seg", "seg.safetensors"))
    a = ap.parse_args()
    img = np.array(Image.open(a.image).convert("RGB"))
    h, w = 41, 73   # odd: the stride-2 path and the cropped upsampling are exercised
    y0, x0 = (img.shape[0] - h) // 2, (img.shape[1] - w) // 2
    rgb = np.ascontiguousarray(img[y0:y0 + h, x0:x0 + w])
    net = layout_seg.load(a.model)
    with torch.no_grad():
        logits = net(layout_seg.to_input(torch.from_numpy(rgb)[None]))[0].numpy()
    name = "layout_seg_case.safetensors"
    # safetensors.numpy writes a non-contiguous array's buffer as it lies in memory: make every tensor contiguous
    save_file({"rgb": rgb, "logits": np.ascontiguousarray(logits, np.float32),
               "classes": np.ascontiguousarray(logits.argmax(0), np.uint8)},
              os.path.join(GOLDEN, name))
    man_path = os.path.join(GOLDEN, "manifest.json")
    with open(man_path) as f:
        manifest = json.load(f)
    manifest["files"][name] = "layout segmenter (models/layout-seg) logits on a 41x73 world crop, PyTorch fp32"
    with open(man_path, "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
    print(f"wrote {name}: classes present {sorted(set(logits.argmax(0).ravel().tolist()))}")


if __name__ == "__main__":
    main()
