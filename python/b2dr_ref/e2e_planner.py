"""A small end-to-end planner that READS IMAGES (docs/e2e_planner.md): the front camera, the ego speed and
acceleration and the navigation command in; the 8 rear-axle poses at 0.5 s of protocol v2 out. It never sees
boxes or the map. Trained by imitation on `b2dr export-planner` data (ground-truth cameras of the synthetic
world's expert logs, with displaced-ego samples whose targets return to the log).

    python -m b2dr_ref.e2e_planner train --data DIR [--val DIR] --out RUN [--epochs N] [--threads T] [--resume]
    python -m b2dr_ref.e2e_planner export --run RUN --out ../models/e2e-planner
    python -m b2dr_ref.e2e_planner serve --weights ../models/e2e-planner    (b2dr run --planner cmd:...)

Images are the renderer's size (112 x 200 for b2dr-nano); `pool2` averages them 2 x 2 to uint8 (half the size,
a quarter of the memory) both when the data is loaded and when a request is served, so the closed loop and the
training data take the same path from the same pixels.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

# the torch-free parts, shared with the numpy forward (b2dr_ref.e2e_numpy)
from .e2e_common import (COMMANDS, CONFIG, POSE_SCALE, POSES, WEIGHTS, pool2,  # noqa: F401 (re-exported)
                         read_config, reply_poses, request_inputs, serve_planner, state_vector)

CKPT = "checkpoint.pt"


class E2EPlanner(nn.Module):
    """(B, 3, H/2, W/2) pooled (`pool2`) uint8-range float image, (B, 5) state [speed / 10, accel / 3,
    one-hot command] -> (B, 8, 3) poses (x, y, heading) in the ego rear-axle frame."""

    def __init__(self, image_size: Tuple[int, int] = (112, 200), width: int = 32):
        super().__init__()
        self.image_size = tuple(image_size)
        c = width
        self.convs = nn.Sequential(                                       # input (3, H/2, W/2) after pooling
            nn.Conv2d(3, c, 5, stride=2, padding=2), nn.GroupNorm(8, c), nn.SiLU(),
            nn.Conv2d(c, c, 3, stride=2, padding=1), nn.GroupNorm(8, c), nn.SiLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.GroupNorm(8, 2 * c), nn.SiLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=1, padding=1), nn.GroupNorm(8, 2 * c), nn.SiLU(),
            nn.Conv2d(2 * c, 16, 1),                                       # (16, H/16, W/16): where things are
        )
        h, w = (image_size[0] // 2), (image_size[1] // 2)
        for _ in range(3):
            h, w = (h + 1) // 2, (w + 1) // 2
        self.feat = 16 * h * w
        self.head = nn.Sequential(
            nn.Linear(self.feat + 5, 256), nn.SiLU(),
            nn.Linear(256, 256), nn.SiLU(),
            nn.Linear(256, POSES * 3),
        )
        self.register_buffer("scale", torch.tensor(POSE_SCALE, dtype=torch.float32), persistent=False)

    def forward(self, image: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        f = self.convs(image / 127.5 - 1.0).flatten(1)
        out = self.head(torch.cat([f, state], 1)).view(-1, POSES, 3)
        return out * self.scale


def load_data(folder: str) -> Dict[str, np.ndarray]:
    """Every file of a `b2dr export-planner` folder: image (N, 3, H/2, W/2) uint8 (first camera, `pool2`),
    state (N, 5), target (N, 8, 3)."""
    from safetensors.numpy import load_file

    idx = json.loads((Path(folder) / "index.json").read_text())
    if idx.get("format") != "b2dr-planner-data":
        raise ValueError(f"{folder}/index.json: format {idx.get('format')!r}, expected 'b2dr-planner-data'")
    imgs, states, targets = [], [], []
    for f in idx["files"]:
        d = load_file(str(Path(folder) / f["file"]))
        imgs.append(pool2(d["image"][:, 0].transpose(0, 3, 1, 2)))
        states.append(state_vector(d["speed"], d["accel"], d["command"]))
        targets.append(d["target"])
    if not imgs:
        raise ValueError(f"{folder}: no samples")
    return {
        "image": np.concatenate(imgs),
        "state": np.concatenate(states),
        "target": np.concatenate(targets).astype(np.float32),
        "size": tuple(idx["size"]),
    }


def _loss(model: E2EPlanner, img, state, target) -> torch.Tensor:
    return ((model(img, state) - target).abs() / model.scale).mean()


def evaluate(model: E2EPlanner, data: Dict[str, np.ndarray], batch: int = 256) -> Dict[str, float]:
    """Mean normalised L1, and the L2 error (m) of the last pose (the usual open-loop L2 @ 4 s)."""
    model.eval()
    tot, l2, n = 0.0, 0.0, 0
    with torch.no_grad():
        for i in range(0, len(data["image"]), batch):
            img = torch.from_numpy(data["image"][i:i + batch]).float()
            st = torch.from_numpy(data["state"][i:i + batch])
            tg = torch.from_numpy(data["target"][i:i + batch])
            p = model(img, st)
            tot += float(((p - tg).abs() / model.scale).mean()) * len(img)
            l2 += float((p[:, -1, :2] - tg[:, -1, :2]).norm(dim=1).sum())
            n += len(img)
    model.train()
    return {"l1": tot / n, "l2_4s_m": l2 / n}


def train(a) -> None:
    torch.manual_seed(a.seed)
    if a.threads:
        torch.set_num_threads(a.threads)
    data = load_data(a.data)
    val = load_data(a.val) if a.val else None
    size = data["size"]
    run = Path(a.out)
    run.mkdir(parents=True, exist_ok=True)
    model = E2EPlanner(size, a.width)
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=1e-4)
    n = len(data["image"])
    steps_per_epoch = max(1, n // a.batch)
    total = a.epochs * steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / 100) * 0.5 * (1 + math.cos(math.pi * min(s, total) / total)))
    gen = torch.Generator().manual_seed(a.seed)
    epoch = 0
    if a.resume and (run / CKPT).exists():
        ck = torch.load(run / CKPT, weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        gen.set_state(ck["gen"])
        epoch = ck["epoch"]
        print(f"resumed at epoch {epoch}", file=sys.stderr)
    (run / "run.json").write_text(json.dumps({**vars(a), "samples": n, "size": list(size)}, indent=1) + "\n")
    log_path = run / "log.csv"
    if epoch == 0:
        with open(log_path, "w", newline="") as f:
            csv.writer(f).writerow(["epoch", "train_l1", "val_l1", "val_l2_4s_m", "lr", "seconds"])
    img_all = torch.from_numpy(data["image"])
    st_all = torch.from_numpy(data["state"])
    tg_all = torch.from_numpy(data["target"])
    while epoch < a.epochs:
        t0 = time.time()
        perm = torch.randperm(n, generator=gen)
        run_loss = 0.0
        for b in range(steps_per_epoch):
            idx = perm[b * a.batch:(b + 1) * a.batch]
            img = img_all[idx].float()
            # brightness / contrast jitter (+-15 %): the only augmentation; geometry stays as rendered
            g = 1.0 + 0.15 * (2 * torch.rand(len(idx), 1, 1, 1, generator=gen) - 1)
            o = 20.0 * (2 * torch.rand(len(idx), 1, 1, 1, generator=gen) - 1)
            img = (img * g + o).clamp(0, 255)
            loss = _loss(model, img, st_all[idx], tg_all[idx])
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            run_loss += loss.item()
        epoch += 1
        v = evaluate(model, val) if val else {"l1": float("nan"), "l2_4s_m": float("nan")}
        dt = time.time() - t0
        with open(log_path, "a", newline="") as f:
            csv.writer(f).writerow([epoch, f"{run_loss / steps_per_epoch:.5f}", f"{v['l1']:.5f}",
                                    f"{v['l2_4s_m']:.4f}", f"{sched.get_last_lr()[0]:.3e}", f"{dt:.1f}"])
        print(f"epoch {epoch}/{a.epochs} train {run_loss / steps_per_epoch:.4f} val {v['l1']:.4f} "
              f"L2@4s {v['l2_4s_m']:.2f} m ({dt:.1f} s)", file=sys.stderr)
        torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                    "gen": gen.get_state(), "epoch": epoch, "size": list(size), "width": a.width}, run / CKPT)


def export(a) -> None:
    from safetensors.torch import save_file

    ck = torch.load(Path(a.run) / CKPT, weights_only=False)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    sd = {k: v.to(torch.float16 if a.dtype == "f16" else torch.float32).contiguous()
          for k, v in ck["model"].items()}
    save_file(sd, str(out / WEIGHTS))
    (out / CONFIG).write_text(json.dumps({"format": "b2dr-e2e-planner", "version": 1, "image_size": ck["size"],
                                          "width": ck["width"], "epochs": ck["epoch"],
                                          "camera": "CAM_FRONT"}, indent=1) + "\n")
    print(f"exported epoch {ck['epoch']} -> {out}", file=sys.stderr)


def load_planner(folder: str) -> E2EPlanner:
    from safetensors.torch import load_file

    cfg = read_config(folder)
    m = E2EPlanner(tuple(cfg["image_size"]), cfg["width"])
    m.load_state_dict({k: v.float() for k, v in load_file(str(Path(folder) / WEIGHTS)).items()})
    return m.eval()


def plan_request(model: E2EPlanner, image_hwc: np.ndarray, ego: dict, command: str) -> List[List[float]]:
    """One protocol-v2 request -> 8 poses (the image must be the model's size)."""
    img, st = request_inputs(model.image_size, image_hwc, ego, command)
    with torch.no_grad():
        p = model(torch.from_numpy(img).float(), torch.from_numpy(st))[0].double().numpy()
    return reply_poses(p)


def serve(a) -> None:
    torch.set_num_threads(1)
    model = load_planner(a.weights)
    serve_planner(lambda img, ego, command: plan_request(model, img, ego, command), model.image_size, a.camera)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.e2e_planner")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--data", required=True, help="b2dr export-planner folder")
    t.add_argument("--val", default=None, help="held-out export-planner folder (validation curve only)")
    t.add_argument("--out", required=True)
    t.add_argument("--epochs", type=int, default=30)
    t.add_argument("--batch", type=int, default=64)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--width", type=int, default=32)
    t.add_argument("--threads", type=int, default=None)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--resume", action="store_true")
    e = sub.add_parser("export")
    e.add_argument("--run", required=True)
    e.add_argument("--out", required=True)
    e.add_argument("--dtype", default="f16", choices=["f16", "f32"])
    s = sub.add_parser("serve")
    s.add_argument("--weights", required=True, help="exported planner folder")
    s.add_argument("--camera", default="CAM_FRONT")
    a = p.parse_args(argv)
    {"train": train, "export": export, "serve": serve}[a.cmd](a)


if __name__ == "__main__":
    main()
