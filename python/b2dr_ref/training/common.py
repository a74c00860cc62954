"""What every accelerate recipe of the renderer shares (docs/training.md "At the paper's scale").

The shape follows diffusers' examples/controlnet/train_controlnet.py: a recipe script parses its arguments with
``parse_args`` (built by ``add_training_args`` from the recipe's defaults) and runs ``main(args)``; this module
holds the parts that do not depend on where the weights come from:

- arguments (``add_training_args``: diffusers' names, ``--train_batch_size`` etc., each also with dashes);
- the Accelerator (``make_accelerator``: gradient accumulation, mixed precision, DDP with unused parameters
  allowed: a batch whose rows all drop their references does not use the reference encoder; a seeded shuffle);
- checkpoints (``save_checkpoint``: ``accelerator.save_state`` into ``checkpoint-{step}``, written as
  ``checkpoint-{step}.tmp`` and renamed when complete, the oldest pruned to ``--checkpoints_total_limit``;
  ``resume_path``: ``--resume_from_checkpoint latest`` or a path);
- trackers (TensorBoard when importable, else a printed message; always ``log.csv``);
- EMA (diffusers' EMAModel over the trainable parameters, saved in each checkpoint);
- data (``CameraSamples``: one (frame, camera) per item, read and PETR-encoded in DataLoader workers, its
  ``set_epoch`` passed to the source (a shard folder re-draws its references each epoch); ``collate_fn``;
  ``encode_batch``: batched VAE encoding on the device, blur of the previous frame there);
- the per-sample noise (``per_sample_draws``: every random draw of a sample comes from a generator seeded by
  (seed, micro-batch number, sample index), so the update does not depend on how the batch is split over
  processes or accumulation steps);
- validation grids (``log_validation``: ground truth | rendered, PNG + TensorBoard);
- the package export (``export_package``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch

from ..controlnet import B2DRControlNetModel
from ..frame import gaussian_blur
from ..pe import PeConfig, location_sizes
from .data import open_source, sample_pe
from .loss import denoise, draw_noise

CHECKPOINT_PREFIX = "checkpoint-"
RUN_JSON = "run.json"
CONTEXT_FILE = "context.safetensors"
EMA_FILE = "ema.pt"
REFERENCE_BINS = [[2.0, 5.0, 0.1], [5.0, 10.0, 0.3], [10.0, 15.0, 0.6]]    # renderer.md 3g (the export's rule)


# ---------------------------------------------------------------------------------------------------------------
# Arguments
# ---------------------------------------------------------------------------------------------------------------


def parse_size(s: str) -> List[int]:
    h, w = (int(v) for v in str(s).lower().split("x"))
    if h <= 0 or w <= 0 or h % 8 or w % 8:
        raise argparse.ArgumentTypeError(f"resolution {s}: HxW, positive multiples of 8")
    return [h, w]


def add_training_args(p: argparse.ArgumentParser, recipe: Dict[str, Any]):
    """The arguments every recipe shares, with the recipe's values as defaults. Names as diffusers' examples
    (``--train_batch_size``); each is accepted with dashes too (``--train-batch-size``)."""
    def opt(name, **kw):
        names = ["--" + name] + (["--" + name.replace("_", "-")] if "_" in name else [])
        if name in recipe and "default" not in kw:
            kw["default"] = recipe[name]
        p.add_argument(*names, dest=name, **kw)

    opt("data", required=True, help="an exported training set (b2dr export-training), a shard folder of one "
        "(python -m b2dr_ref.training.shards pack), or synthetic[:N]")
    opt("output_dir", required=True, help="run folder: checkpoint-{step}/, run.json, context.safetensors, logs/")
    opt("resolution", type=parse_size, help="render size HxW (multiples of 8; the data's size)")
    opt("seed", type=int, default=0)
    opt("train_batch_size", type=int, help="camera samples per process and micro-batch")
    opt("gradient_accumulation_steps", type=int, default=1)
    opt("max_train_steps", type=int, help="optimizer steps of the whole run (the schedule spans them)")
    opt("stop_after_steps", type=int, default=0,
        help="stop (with a checkpoint) after this many optimizer steps of this invocation: time-sliced jobs")
    opt("learning_rate", type=float)
    opt("lr_scheduler", help="diffusers.optimization.get_scheduler name: cosine, linear, constant_with_warmup, ...")
    opt("lr_warmup_steps", type=int)
    opt("adam_beta1", type=float, default=0.9)
    opt("adam_beta2", type=float, default=0.999)
    opt("adam_weight_decay", type=float, default=1e-2)
    opt("adam_epsilon", type=float, default=1e-8)
    opt("max_grad_norm", type=float, default=1.0)
    opt("mixed_precision", choices=["no", "fp16", "bf16"], default=None,
        help="autocast dtype (default: accelerate's config / launch flag)")
    opt("gradient_checkpointing", action="store_true", help="recompute the UNet / ControlNet blocks in backward")
    opt("attention", choices=["sdpa", "math"], default="sdpa",
        help="diffusers attention processor: sdpa (AttnProcessor2_0, torch's fused kernels) or math (AttnProcessor)")
    opt("allow_tf32", action="store_true", help="TF32 matmuls on Ampere and later")
    opt("use_ema", action="store_true", help="keep an EMA of the trainable weights (export and validation use it)")
    opt("ema_decay", type=float, default=0.9999)
    opt("checkpointing_steps", type=int, default=500)
    opt("checkpoints_total_limit", type=int, default=None, help="checkpoints kept (the oldest are removed)")
    opt("resume_from_checkpoint", default=None, help="'latest' or a checkpoint-{step} folder")
    opt("report_to", choices=["tensorboard", "none"], default="tensorboard")
    opt("logging_dir", default="logs", help="TensorBoard folder, relative to --output_dir")
    opt("tracker_project_name", default="b2dr")
    opt("validation_steps", type=int, default=500, help="write a validation grid every N steps (0 = never)")
    opt("num_validation_images", type=int, default=4, help="camera samples in the grid (the data's first ones)")
    opt("validation_sampling_steps", type=int, default=20, help="UniPC steps of the validation renders")
    opt("dataloader_num_workers", type=int, default=0)
    opt("dataloader_prefetch_factor", type=int, default=2)
    # the B2D-R recipe (renderer.md 3b-3g)
    opt("ref_dropout", type=float, help="probability that a sample drops its references (reference CFG)")
    opt("p_noprev", type=float, help="probability of 'no previous frame' (z = 0, n = 999)")
    opt("prev_noise_max", type=int, help="noise modulation: n ~ U{0..N_max} on the previous frame's latent")
    opt("prev_noise_level", type=int, help="the fixed n at inference (stored in controlnet/config.json)")
    opt("prev_blur_sigma", type=float, help="Gaussian blur of the previous frame (px)")
    opt("pe_depth_num", type=int, help="PETR depth bins")
    opt("conditioning_embedding_out_channels", type=lambda s: [int(v) for v in s.split(",")],
        help="the ControlNet's mask embedding channels, comma-separated")
    opt("reference_bins", type=json.loads,
        help="JSON [[lo, hi, p], ...]: the reference distance bins (a shard folder draws its references from "
             "them each epoch; a raw export must have been exported with them)")


def checked_args(args):
    if args.train_batch_size < 1 or args.gradient_accumulation_steps < 1:
        raise SystemExit("--train_batch_size and --gradient_accumulation_steps must be >= 1")
    if args.checkpoints_total_limit is not None and args.checkpoints_total_limit < 1:
        raise SystemExit("--checkpoints_total_limit must be >= 1")
    return args


# ---------------------------------------------------------------------------------------------------------------
# Accelerator, trackers
# ---------------------------------------------------------------------------------------------------------------


def tensorboard_available() -> bool:
    try:
        import tensorboard  # noqa: F401
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
        return True
    except Exception:
        return False


def make_accelerator(args):
    from accelerate import Accelerator
    from accelerate.utils import DataLoaderConfiguration, DistributedDataParallelKwargs, ProjectConfiguration

    log_with = None
    if args.report_to == "tensorboard":
        if tensorboard_available():
            log_with = "tensorboard"
        else:
            print("--report_to tensorboard: the tensorboard package is not installed (pip install tensorboard); "
                  f"the losses go to {os.path.join(args.output_dir, 'log.csv')} only", flush=True)
    project = ProjectConfiguration(project_dir=args.output_dir,
                                   logging_dir=os.path.join(args.output_dir, args.logging_dir))
    acc = Accelerator(gradient_accumulation_steps=args.gradient_accumulation_steps,
                       mixed_precision=args.mixed_precision, log_with=log_with, project_config=project,
                       # the shuffle order: a permutation seeded by (seed, epoch), the same for any number of
                       # processes (each takes every N-th batch of it); its epoch is saved with the checkpoint
                       dataloader_config=DataLoaderConfiguration(use_seedable_sampler=True, data_seed=args.seed),
                       kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=True)])
    if acc.mixed_precision == "fp16" and acc.device.type == "cpu":
        # accelerate applies fp16 autocast and its GradScaler only on an accelerator: on the CPU the run would train
        # in f32 while the frozen models were cast to fp16
        raise SystemExit("--mixed_precision fp16 on the CPU: accelerate applies neither fp16 autocast nor a "
                         "gradient scaler there; use --mixed_precision bf16 (or no) on the CPU, fp16 on a GPU")
    return acc


def weight_dtype_of(accelerator) -> torch.dtype:
    """The dtype of the frozen models (diffusers' examples: fp16 / bf16 under mixed precision)."""
    return {"fp16": torch.float16, "bf16": torch.bfloat16}.get(accelerator.mixed_precision, torch.float32)


def init_trackers(accelerator, args):
    if accelerator.is_main_process and accelerator.log_with:
        cfg = {k: v for k, v in vars(args).items() if isinstance(v, (int, float, str, bool))}
        accelerator.init_trackers(args.tracker_project_name, config=cfg)


def tensorboard_writer(accelerator):
    for t in getattr(accelerator, "trackers", []):
        if t.name == "tensorboard":
            return t.writer
    return None


# ---------------------------------------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------------------------------------


def checkpoints(output_dir: str) -> List[str]:
    """The complete ``checkpoint-{step}`` folders, oldest first (``.tmp`` folders of a killed save are not)."""
    if not os.path.isdir(output_dir):
        return []
    out = []
    for d in os.listdir(output_dir):
        if d.startswith(CHECKPOINT_PREFIX) and d[len(CHECKPOINT_PREFIX):].isdigit():
            out.append(d)
    return [os.path.join(output_dir, d) for d in sorted(out, key=checkpoint_step)]


def checkpoint_step(path: str) -> int:
    return int(os.path.basename(os.path.normpath(path))[len(CHECKPOINT_PREFIX):])


def save_checkpoint(accelerator, output_dir: str, step: int, limit: Optional[int]) -> str:
    """accelerator.save_state into checkpoint-{step} (all processes: each writes its RNG state), written as
    checkpoint-{step}.tmp and renamed once every process is done; then the oldest are removed beyond ``limit``."""
    final = os.path.join(output_dir, f"{CHECKPOINT_PREFIX}{step}")
    tmp = final + ".tmp"
    if accelerator.is_main_process:
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
    accelerator.wait_for_everyone()
    accelerator.save_state(tmp)
    accelerator.wait_for_everyone()
    if accelerator.is_main_process:
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        if limit is not None:
            for old in checkpoints(output_dir)[:-limit]:
                shutil.rmtree(old)
    accelerator.wait_for_everyone()
    return final


def resume_path(arg: Optional[str], output_dir: str) -> Optional[str]:
    """``latest`` -> the newest complete checkpoint of output_dir (None when there is none: a new run); a path ->
    that folder (it must exist)."""
    if not arg:
        return None
    if arg == "latest":
        cks = checkpoints(output_dir)
        return cks[-1] if cks else None
    path = arg if os.path.isabs(arg) or os.path.isdir(arg) else os.path.join(output_dir, arg)
    if not os.path.isdir(path):
        raise SystemExit(f"--resume_from_checkpoint {arg}: no such checkpoint folder")
    return path


# ---------------------------------------------------------------------------------------------------------------
# The model the optimizer trains: UNet + B2D-R ControlNet as one module (one DDP wrapper, one autocast)
# ---------------------------------------------------------------------------------------------------------------


class ControlledUNet(torch.nn.Module):
    """UNet + B2D-R ControlNet; forward = b2dr_ref.train.denoise (references, ControlNet residuals, UNet)."""

    def __init__(self, unet, controlnet: B2DRControlNetModel):
        super().__init__()
        self.unet = unet
        self.controlnet = controlnet

    def forward(self, x_t, t, ctx, masks, z, n, ref_latents, pe_cur, pe_ref, ref_mask):
        return denoise(self.unet, self.controlnet, x_t, t, ctx, masks, z, n, ref_latents, pe_cur, pe_ref, ref_mask)


def set_attention(model: torch.nn.Module, kind: str):
    from diffusers.models.attention_processor import AttnProcessor, AttnProcessor2_0

    proc = AttnProcessor2_0() if kind == "sdpa" else AttnProcessor()
    for m in (model.unet, model.controlnet):
        m.set_attn_processor(proc)


def make_ema(model: ControlledUNet, decay: float):
    from diffusers.training_utils import EMAModel

    return EMAModel([p for p in model.parameters() if p.requires_grad], decay=decay)


def register_checkpoint_hooks(accelerator, ema, train_unet: bool):
    """save_state / load_state write and read the models as diffusers folders (checkpoint-N/controlnet, and
    checkpoint-N/unet when the UNet trains), plus checkpoint-N/ema.pt (diffusers' hook convention)."""
    from diffusers import UNet2DConditionModel

    def save_hook(models, weights, output_dir):
        if accelerator.is_main_process:
            for m in models:
                m = accelerator.unwrap_model(m)
                m.controlnet.save_pretrained(os.path.join(output_dir, "controlnet"))
                if train_unet:
                    m.unet.save_pretrained(os.path.join(output_dir, "unet"), safe_serialization=True)
            if ema is not None:
                torch.save(ema.state_dict(), os.path.join(output_dir, EMA_FILE))
        while weights:
            weights.pop()

    def load_hook(models, input_dir):
        while models:
            m = accelerator.unwrap_model(models.pop())
            c = B2DRControlNetModel.from_pretrained(input_dir, subfolder="controlnet")
            m.controlnet.load_state_dict(c.state_dict())
            if train_unet:
                u = UNet2DConditionModel.from_pretrained(input_dir, subfolder="unet")
                m.unet.load_state_dict(u.state_dict())
        if ema is not None:
            ema.load_state_dict(torch.load(os.path.join(input_dir, EMA_FILE), map_location="cpu", weights_only=False))

    accelerator.register_save_state_pre_hook(save_hook)
    accelerator.register_load_state_pre_hook(load_hook)


# ---------------------------------------------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------------------------------------------


class CameraSamples(torch.utils.data.Dataset):
    """One item per (frame, camera) of the data (b2dr_ref.train's sources), read and PETR-encoded where the
    DataLoader runs it (its workers). Images stay uint8 here; the device blurs, scales and VAE-encodes them."""

    def __init__(self, data: str, render_size, controlnet_config, seed: int = 0, reference_bins=None):
        import multiprocessing

        self.data = data
        self.seed, self.reference_bins = int(seed), reference_bins
        # the epoch, shared with the DataLoader's (persistent) workers: set_epoch in the main process, read by the
        # worker for each item (open_clip's SharedEpoch does the same for its WebDataset pipeline)
        self._epoch = multiprocessing.Value("i", 0, lock=False)
        self.render_size = tuple(int(v) for v in render_size)
        self.pe_cfg = PeConfig.from_controlnet_config(controlnet_config)
        h, w = self.render_size
        self.sizes = location_sizes(controlnet_config.ref_attn, len(controlnet_config.block_out_channels),
                                    (h // 8, w // 8))
        self._source = None
        src = self.source()
        if tuple(src.render_size) != self.render_size:
            raise SystemExit(f"{data}: render size {tuple(src.render_size)} != --resolution {self.render_size}")
        self.cameras = list(src.cameras)
        self.n = len(src)
        self.redraws = hasattr(src, "set_epoch")      # references drawn per epoch (a shard folder)
        self.index = {}
        if os.path.isdir(data):
            with open(os.path.join(data, "index.json")) as f:
                self.index = {k: v for k, v in json.load(f).items() if k != "samples"}
        self._source = None         # each worker opens its own (file handles are not shared across processes)

    def source(self):
        if self._source is None:
            self._source = open_source(self.data, self.render_size, seed=self.seed, reference_bins=self.reference_bins)
        return self._source

    def set_epoch(self, epoch: int):
        """The trainer's epoch: a source that re-draws its references draws them for this epoch."""
        self._epoch.value = int(epoch)

    def __len__(self):
        return self.n

    def __getitem__(self, i: int) -> Dict[str, Any]:
        src = self.source()
        if self.redraws:
            src.set_epoch(self._epoch.value)
        s = src[int(i)]
        pc, pr = sample_pe(s, self.pe_cfg, self.sizes, self.render_size)
        return dict(index=int(i), cam=self.cameras.index(s.camera),
                    target=torch.from_numpy(np.ascontiguousarray(s.target)),
                    prev=torch.from_numpy(np.ascontiguousarray(s.prev)),
                    refs=torch.from_numpy(np.ascontiguousarray(s.refs)),
                    masks=torch.from_numpy(np.ascontiguousarray(s.masks)),
                    pe_cur=[torch.from_numpy(a) for a in pc], pe_ref=[torch.from_numpy(a) for a in pr])


def worker_init_fn(_worker_id: int):
    """Each DataLoader worker opens the data itself (no file handle inherited from the parent)."""
    info = torch.utils.data.get_worker_info()
    info.dataset._source = None
    torch.set_num_threads(1)


def collate_fn(items: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    nl = len(items[0]["pe_cur"])
    return dict(index=torch.tensor([it["index"] for it in items], dtype=torch.int64),
                cams=torch.tensor([it["cam"] for it in items], dtype=torch.int64),
                target=torch.stack([it["target"] for it in items]), prev=torch.stack([it["prev"] for it in items]),
                refs=torch.stack([it["refs"] for it in items]), masks=torch.stack([it["masks"] for it in items]),
                pe_cur=[torch.stack([it["pe_cur"][j] for it in items]) for j in range(nl)],
                pe_ref=[torch.stack([it["pe_ref"][j] for it in items]) for j in range(nl)])


def check_reference_bins(dataset: CameraSamples, bins):
    """A raw export's references were drawn at export time: its bins must be the recipe's. (A shard folder draws
    them each epoch with the recipe's bins.)"""
    if dataset.redraws:
        return
    have = dataset.index.get("reference_intervals")
    if have is not None and bins is not None and \
            not np.allclose(np.asarray(have, np.float64), np.asarray(bins, np.float64)):
        raise SystemExit(f"{dataset.data}: exported with reference bins {have}, the recipe asks for {bins}")


@torch.no_grad()
def encode_batch(vae, batch: Dict[str, Any], blur_sigma: float, device, dtype) -> Dict[str, Any]:
    """The loss's batch (b2dr_ref.train's layout): VAE mean x scaling of the target, of the blurred previous frame
    and of both references, in one encoder call on the device; masks as float; PE on the device."""
    B = batch["target"].shape[0]
    def u8(x):
        return x.to(device, non_blocking=True).float().div_(255.0)
    prev = gaussian_blur(u8(batch["prev"]), blur_sigma)
    refs = u8(batch["refs"]).flatten(0, 1)
    imgs = torch.cat([u8(batch["target"]), prev, refs])
    z = vae.encode((2.0 * imgs - 1.0).to(dtype)).latent_dist.mean.float() * float(vae.config.scaling_factor)
    return dict(index=batch["index"], cams=batch["cams"].to(device), x0=z[:B], z_prev=z[B:2 * B],
                ref_latents=z[2 * B:].reshape(B, 2, *z.shape[1:]), masks=batch["masks"].to(device).float(),
                pe_cur=[p.to(device, non_blocking=True) for p in batch["pe_cur"]],
                pe_ref=[p.to(device, non_blocking=True) for p in batch["pe_ref"]])


def sample_seed(seed: int, stream: int, index: int) -> int:
    return (int(seed) * 1_000_003 + int(stream) * 7_919 + int(index) * 104_729 + 17) % (2 ** 62)


def per_sample_draws(b, seed: int, stream: int, prev_noise_max: int, p_noprev: float, ref_dropout: float) -> Dict:
    """draw_noise for each sample from its own generator (seed, stream = micro-batch number, dataset index)."""
    parts = []
    for k, i in enumerate(b["index"].tolist()):
        g = torch.Generator().manual_seed(sample_seed(seed, stream, i))
        parts.append(draw_noise({"x0": b["x0"][k:k + 1], "z_prev": b["z_prev"][k:k + 1]}, g, prev_noise_max,
                                p_noprev, ref_dropout))
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


# ---------------------------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------------------------


@torch.no_grad()
def log_validation(accelerator, model: ControlledUNet, vae, context: torch.Tensor, dataset: CameraSamples, args,
                   step: int, ema=None) -> str:
    """Renders the first ``num_validation_images`` samples with the PyTorch reference frame (frame.render_frame:
    UniPC, reference guidance 2) and writes one grid, each row ground truth | rendered: PNG under
    output_dir/validation/ and an image in TensorBoard."""
    from PIL import Image

    from ..frame import render_frame

    n = min(int(args.num_validation_images), len(dataset))
    b = collate_fn([dataset[i] for i in range(n)])
    dev = accelerator.device
    params = [p for p in model.parameters() if p.requires_grad]
    if ema is not None:
        ema.store(params)
        ema.copy_to(params)
    g = torch.Generator().manual_seed(int(args.seed))
    h, w = dataset.render_size
    lc = int(model.unet.config.in_channels)
    x_T = torch.randn((n, lc, h // 8, w // 8), generator=g).to(dev)
    eps_prev = torch.randn((n, lc, h // 8, w // 8), generator=g).to(dev)
    was_training = model.training
    model.eval()
    try:
        with accelerator.autocast():
            res = render_frame(model.unet, model.controlnet, vae, x_T, context.to(dev)[b["cams"].to(dev)],
                               b["masks"].to(dev).float(), b["prev"].to(dev).float() / 255, eps_prev,
                               ref_images=b["refs"].to(dev).float() / 255,
                               pe_cur=[p.to(dev) for p in b["pe_cur"]], pe_ref=[p.to(dev) for p in b["pe_ref"]],
                               steps=int(args.validation_sampling_steps))
    finally:
        model.train(was_training)
        if ema is not None:
            ema.restore(params)
    truth = b["target"].float() / 255
    grid = torch.cat([torch.cat([truth[i], res.image[i].float().cpu()], dim=2) for i in range(n)], dim=1)
    folder = os.path.join(args.output_dir, "validation")
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, f"step-{step:07d}.png")
    arr = (grid.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    Image.fromarray(arr).save(path)
    writer = tensorboard_writer(accelerator)
    if writer is not None:
        writer.add_image("validation/ground_truth|rendered", grid.clamp(0, 1), step)
        writer.flush()
    return path


# ---------------------------------------------------------------------------------------------------------------
# Run metadata, CSV log, export
# ---------------------------------------------------------------------------------------------------------------


def write_run_json(args, cameras: Sequence[str], extra: Dict[str, Any]):
    meta = dict(extra, cameras=list(cameras), resolution=list(args.resolution),
                args={k: v for k, v in vars(args).items() if isinstance(v, (int, float, str, bool, list, type(None)))})
    with open(os.path.join(args.output_dir, RUN_JSON), "w") as f:
        json.dump(meta, f, indent=2)


class CsvLog:
    """log.csv: one row per step; on a resume the rows up to the resumed step are kept."""

    def __init__(self, path: str, fields: Sequence[str], resume_step: int):
        rows = []
        if resume_step > 0 and os.path.exists(path):
            with open(path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        self.f = open(path, "w", newline="")
        self.w = csv.DictWriter(self.f, fieldnames=list(fields))
        self.w.writeheader()
        for r in rows:
            self.w.writerow(r)
        self.f.flush()

    def write(self, row):
        self.w.writerow(row)
        self.f.flush()

    def close(self):
        self.f.close()


def open_csv_log(args, resume_step: int) -> CsvLog:
    return CsvLog(os.path.join(args.output_dir, "log.csv"), ["step", "loss", "lr", "grad_norm", "sec"], resume_step)


def export_package(run_dir: str, out: str, checkpoint: str = "latest", dtype: str = "f16", use_ema: bool = True,
                   steps: int = 20, ref_guidance: float = 2.0) -> Dict[str, Any]:
    """A run's checkpoint -> the model package (renderer.md 3b): unet/ (the checkpoint's, or the pretrained one when
    the UNet was frozen), controlnet/, the pretrained vae/, context.safetensors (the CLIP per-camera context),
    b2dr.json. With an EMA in the checkpoint and ``use_ema``, the EMA weights."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from safetensors.torch import load_file

    from ..package import make_meta, save_package

    with open(os.path.join(run_dir, RUN_JSON)) as f:
        run = json.load(f)
    ck = resume_path(checkpoint, run_dir)
    if ck is None:
        raise SystemExit(f"{run_dir}: no checkpoint to export")
    pre = run["pretrained"]
    unet_dir = os.path.join(ck, "unet") if os.path.isdir(os.path.join(ck, "unet")) else os.path.join(pre, "unet")
    unet = UNet2DConditionModel.from_pretrained(unet_dir, torch_dtype=torch.float32)
    controlnet = B2DRControlNetModel.from_pretrained(ck, subfolder="controlnet")
    vae = AutoencoderKL.from_pretrained(pre, subfolder="vae", torch_dtype=torch.float32)
    model = ControlledUNet(unet, controlnet)
    unet.requires_grad_(not run["freeze_unet"])
    controlnet.requires_grad_(True)
    ema_path = os.path.join(ck, EMA_FILE)
    used_ema = use_ema and os.path.exists(ema_path)
    if used_ema:
        ema = make_ema(model, 0.0)
        ema.load_state_dict(torch.load(ema_path, map_location="cpu", weights_only=False))
        ema.copy_to([p for p in model.parameters() if p.requires_grad])
    context = load_file(os.path.join(run_dir, CONTEXT_FILE))["cond"].float()
    meta = make_meta(run["resolution"], run["cameras"], sampler="unipc", steps=steps, ref_guidance=ref_guidance,
                     dtype=dtype, prediction_type=run.get("prediction_type", "epsilon"))
    save_package(out, unet.eval(), controlnet.eval(), vae.eval(), context, meta)
    return dict(checkpoint=ck, step=checkpoint_step(ck), ema=used_ema, out=out)


def epochs_for(max_steps: int, batches_per_epoch: int, accumulation: int) -> int:
    per_epoch = max(1, math.ceil(batches_per_epoch / accumulation))
    return math.ceil(max_steps / per_epoch)
