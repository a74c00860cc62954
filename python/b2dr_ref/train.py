"""Training recipe of the B2D-R renderer (docs/training.md; world.md section 3): the diffusion stage (UNet from scratch
+ B2D-R ControlNet, frozen VAE) and the export to the model package. The VAE stage is vae_train.py.

    python -m b2dr_ref.train --data DIR --vae VAE_RUN/vae --out RUN [--config nano] [--steps N] [--batch B]
                             [--device cpu|cuda] [--resume]
    python -m b2dr_ref.train export --run RUN --out MODEL_DIR [--dtype f16]

``--data synthetic[:N]`` trains on the random synthetic source (tests, smoke runs).

Per step (batch of B camera samples):
- x_0 = VAE mean x scaling of the target; t ~ U{0..999}; eps ~ N(0, 1); x_t = DDPM add_noise (SD1.5 schedule);
- previous frame: blur sigma 1 -> VAE mean x scaling -> z = sqrt(abar_n) z_prev + sqrt(1 - abar_n) eps_p with
  n ~ U{0..N_max}; with probability p_noprev (0.1) z = 0 and n = 999 (the engine's "no previous frame");
- with --self-prev P: a row's previous latent is, with probability P, that of the model's own one-step render
  of its frame (training/selfprev.py); with --self-prev-pose chain, of its previous frame rendered from the frame
  before it (data exported with --prev-chain);
- references: VAE latents of both references, PETR encodings (pe.py formulas, vectorised here) of the Ref-Attn
  locations from the sample's matrices; with probability ref_dropout (0.2) a row skips Ref-Attn (ref_mask, 2e);
- loss = MSE(UNet(x_t, t, ctx, ControlNet residuals), eps); AdamW, linear warm-up then cosine, clip 1.0.
All randomness comes from one seeded torch.Generator whose state the checkpoint holds (bit-for-bit resume).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from . import nano
from .controlnet import B2DR_DEFAULTS, MAX_WARP_DEPTH, PREV_SOURCES, B2DRControlNetModel, MASK_CHANNELS
from .fastpath import AUTOCASTS, PLAIN, FastPath, Prefetcher
from .frame import SD15_SCHEDULE, gaussian_blur
from .package import X0_BASES
from .pe import PeConfig, location_sizes
from .warp import ground_warp_grid, warp_image

# The data (Sample, its sources, the PETR geometry), the loss pieces and the CSV log live in b2dr_ref.training,
# shared with the sd15 recipe; their names stay importable from here.
from .training.common import CsvLog  # noqa: E402,F401
from .training.data import (DatasetSource, Sample, SampleSource, SyntheticSource, _rot_z,  # noqa: E402,F401
                            open_source, position_encoding_np, sample_pe)
from .training.single import (CKPT, add_common, end_at_anneal, load_vae, lr_lambda,  # noqa: E402,F401
                              save_checkpoint, set_threads)
from .training.selfprev import draw_self, own_previous, pose_partners  # noqa: E402
from .training.loss import (LOSS_WEIGHTS, NO_PREV_NOISE_LEVEL, OBJECT_CHANNELS, PREDICTIONS,  # noqa: E402,F401
                            denoise, draw_noise, layout_loss_weight, loss_weight, noised_inputs, object_loss_weight,
                            prediction_loss)


# ---------------------------------------------------------------------------------------------------------------
# Models, schedule, checkpoints
# ---------------------------------------------------------------------------------------------------------------


def make_noise_scheduler():
    from diffusers import DDPMScheduler

    return DDPMScheduler(**SD15_SCHEDULE)


def build_diffusion_models(cfg, seed: int = 0):
    from diffusers import UNet2DConditionModel

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(**cfg["unet"])
    controlnet = B2DRControlNetModel.from_config(cfg["controlnet"])
    return unet, controlnet


def make_context(cfg, cameras: Sequence[str], seed: int = 0) -> torch.Tensor:
    """The fixed per-camera context (n_cams, 77, D): N(0, 1) from a seeded generator (not trained)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randn((len(cameras), 77, int(cfg["context_dim"])), generator=g)


class Ema:
    def __init__(self, models, decay: float):
        self.decay = decay
        self.shadow = {f"{i}.{k}": v.detach().clone() for i, m in enumerate(models)
                       for k, v in m.state_dict().items()}

    @torch.no_grad()
    def update(self, models):
        for i, m in enumerate(models):
            for k, v in m.state_dict().items():
                s = self.shadow[f"{i}.{k}"]
                if v.dtype.is_floating_point:
                    s.mul_(self.decay).add_(v.detach(), alpha=1 - self.decay)
                else:
                    s.copy_(v)

    def state_for(self, i: int) -> Dict[str, torch.Tensor]:
        p = f"{i}."
        return {k[len(p):]: v for k, v in self.shadow.items() if k.startswith(p)}


# ---------------------------------------------------------------------------------------------------------------
# The diffusion stage
# ---------------------------------------------------------------------------------------------------------------


def pack_masks(masks: np.ndarray) -> torch.Tensor:
    """(C <= 16, H, W) {0,1} -> (H, W) int16 bit planes (the cache keeps 2 bytes per pixel, not C)."""
    m = np.asarray(masks)
    if m.shape[0] > 16:
        raise ValueError(f"pack_masks: {m.shape[0]} channels (at most 16)")
    bits = (m.astype(np.uint16) & 1) << np.arange(m.shape[0], dtype=np.uint16)[:, None, None]
    return torch.from_numpy(bits.sum(0, dtype=np.uint16).view(np.int16).copy())


def unpack_masks(packed: torch.Tensor, channels: int = len(MASK_CHANNELS)) -> torch.Tensor:
    """pack_masks' inverse: (H, W) int16 -> (channels, H, W) uint8."""
    p = packed.to(torch.int32) & 0xFFFF
    bits = torch.arange(channels, dtype=torch.int32)[:, None, None]
    return ((p[None] >> bits) & 1).to(torch.uint8)


LATENTS_FILE = "latents.pt"
LATENTS_FORMAT = 1


def latent_cache_key(data: str, vae_path: str, sigma: float, warp: float = 0.0) -> str:
    """What the cached latents depend on: the data (its index and the names and sizes of its files; or the
    ``synthetic:N`` source), the VAE's files (bytes), the previous frame's blur and its warp (depth cap; 0 = no
    warp, the key of a file written before the warp existed). A mismatch discards the file."""
    import hashlib

    h = hashlib.sha256(f"b2dr-latents/{LATENTS_FORMAT}/{sigma!r}/".encode())
    if warp:
        h.update(f"warp/{float(warp)!r}/".encode())
    if os.path.isdir(data):
        for name in sorted(os.listdir(data)):
            f = os.path.join(data, name)
            h.update(f"{name}:{os.path.getsize(f)};".encode())
            if name.endswith(".json"):
                with open(f, "rb") as fh:
                    h.update(fh.read())
    else:
        h.update(data.encode())
    for name in sorted(os.listdir(vae_path)):
        if name != "config.json" and not name.endswith((".safetensors", ".bin")):
            continue        # what diffusers reads; not a README beside it
        with open(os.path.join(vae_path, name), "rb") as fh:
            h.update(name.encode() + hashlib.sha256(fh.read()).digest())
    return h.hexdigest()


def geometry(s: Sample) -> Tuple:
    """What a sample's previous-frame warp needs: intrinsics, cam2ego, the current and the previous ego pose."""
    return (s.k, s.cam2ego, s.ego2global, s.prev_ego2global)


class Batcher:
    """Turns sample indices into model inputs; caches the frozen-VAE latents and the PE per sample index (they are
    deterministic), up to ``cache`` samples. With ``latents`` = (path, key) the VAE latents (the costly part: four
    encodes per sample) also live in that file between runs: loaded here when its key matches, written by
    ``save_latents`` (at each checkpoint), so a resumed run does not encode the data again. ``chain`` (a
    --prev-chain export; train --self-prev-pose chain): also the blurred latent of each sample's ``prev2`` and its
    ``prev_masks``; the batch then holds ``z_prev2`` and ``masks_prev``."""

    def __init__(self, source, vae, controlnet: B2DRControlNetModel, device, cache: int = 100000,
                 latents: Optional[Tuple[str, str]] = None, chain: bool = False):
        self.source, self.vae, self.device = source, vae, device
        self.chain = chain
        if chain and not getattr(source, "prev_chain", False):
            raise ValueError("chain: the data is not a --prev-chain export (b2dr export-training --prev-chain)")
        cfg = controlnet.config
        self.pe_cfg = PeConfig.from_controlnet_config(cfg)
        self.render_hw = tuple(source.render_size)
        H, W = self.render_hw
        self.sizes = location_sizes(cfg.ref_attn, len(cfg.block_out_channels), (H // 8, W // 8))
        self.sigma = float(cfg.prev_blur_sigma)
        # > 0: the previous frame is warped to the current pose before the blur (b2dr_ref/warp.py); the batch
        # then holds each row's grid (``prev_grid``) for the self-prev chain's own previous frame
        self.warp = float(getattr(cfg, "prev_warp_max_depth", 0.0) or 0.0)
        self.cam_index = {c: i for i, c in enumerate(source.cameras)}
        self.hop1_unwarped_said = False
        self.cache_max = cache
        self.cache: Dict[int, Tuple] = {}
        self.latents = latents
        # index -> (x0, z_prev, z_refs[, z_prev2]) from / for the latents file
        self.disk: Dict[int, Tuple] = {}
        self.disk_saved = 0
        if latents and os.path.exists(latents[0]):
            d = torch.load(latents[0], weights_only=True)
            if d.get("key") != latents[1]:
                print(f"{latents[0]}: made from other data or another VAE; encoding again", flush=True)
            elif chain and "z_prev2" not in d:
                print(f"{latents[0]}: holds no prev2 latents (made without --self-prev-pose chain); encoding again",
                      flush=True)
            else:
                for n, i in enumerate(d["index"].tolist()):
                    self.disk[i] = (d["x0"][n], d["z_prev"][n], d["z_refs"][n]) + \
                        ((d["z_prev2"][n],) if chain else ())
                self.disk_saved = len(self.disk)
                print(f"{latents[0]}: the latents of {len(self.disk)} samples", flush=True)

    def precache(self, chunk: int = 64):
        """Encode every sample of the source now (the latents file and, up to ``cache``, the memory cache), with
        progress: on a GPU the first pass over the data is otherwise spread over the first epoch's steps and
        makes their time (what a wall-clock budget is sized from) unrepresentative. Same values as lazy encoding
        (one image at a time)."""
        n, t0, shown = len(self.source), time.perf_counter(), 0
        for a in range(0, n, chunk):
            self._prepare(range(a, min(n, a + chunk)))
            done = min(n, a + chunk)
            if done * 10 // n > shown or done == n:
                shown = done * 10 // n
                print(f"precache: {done} / {n} samples ({time.perf_counter() - t0:.0f} s)", flush=True)
        self.save_latents()

    def save_latents(self):
        """Write the latents file (atomically) when samples were encoded since the last write."""
        if not self.latents or len(self.disk) == self.disk_saved:
            return
        idx = sorted(self.disk)
        d = dict(key=self.latents[1], index=torch.tensor(idx, dtype=torch.int64),
                 x0=torch.stack([self.disk[i][0] for i in idx]), z_prev=torch.stack([self.disk[i][1] for i in idx]),
                 z_refs=torch.stack([self.disk[i][2] for i in idx]))
        if self.chain:
            d["z_prev2"] = torch.stack([self.disk[i][3] for i in idx])
        save_checkpoint(self.latents[0], d)
        self.disk_saved = len(idx)

    @torch.no_grad()
    def _encode(self, imgs_u8: np.ndarray, blur: bool, grids: Optional[Sequence[np.ndarray]] = None) -> torch.Tensor:
        """One image at a time, so a latent does not depend on which batch it was first seen in (exact resume).
        ``grids``: per image a warp grid applied before the blur (b2dr_ref/warp.py)."""
        out = []
        for n, img in enumerate(imgs_u8):
            x = torch.from_numpy(np.ascontiguousarray(img[None])).float().div(255.0)
            if grids is not None:
                x = warp_image(x, torch.from_numpy(grids[n])[None])
            if blur:
                x = gaussian_blur(x, self.sigma)        # on the CPU (frame.gaussian_blur builds its taps there)
            x = x.to(self.device)
            out.append((self.vae.encode(2.0 * x - 1.0).latent_dist.mean * self.vae.config.scaling_factor).cpu())
        return torch.cat(out)

    def _prepare(self, idx: Sequence[int]):
        todo = sorted(set(i for i in idx if i not in self.cache))
        local = {}
        if todo:
            ss = [self.source[i] for i in todo]
            lat = {i: self.disk[i] for i in todo if i in self.disk}       # (x0, z_prev, z_refs)
            new = [(i, s) for i, s in zip(todo, ss) if i not in lat]
            if new:
                es = [s for _, s in new]
                x0 = self._encode(np.stack([s.target for s in es]), False)
                zp = self._encode(np.stack([s.prev for s in es]), True,
                                  [self.grid(geometry(s)) for s in es] if self.warp else None)
                zr = self._encode(np.concatenate([s.refs for s in es]), False).reshape(len(es), 2, *x0.shape[-3:])
                zp2 = self._encode(np.stack([s.prev2 for s in es]), True, self._hop1_grids(es)) if self.chain \
                    else None
                for m, (i, _) in enumerate(new):
                    lat[i] = (x0[m], zp[m], zr[m]) + ((zp2[m],) if self.chain else ())
                    if self.latents:
                        self.disk[i] = lat[i]
            for i, s in zip(todo, ss):
                pc, pr = sample_pe(s, self.pe_cfg, self.sizes, self.render_hw)
                chain = (lat[i][3], pack_masks(s.prev_masks)) if self.chain else None
                local[i] = (*lat[i][:3], pack_masks(s.masks),
                            self.cam_index[s.camera], [torch.from_numpy(a) for a in pc],
                            [torch.from_numpy(a) for a in pr], chain,
                            geometry(s) if self.warp else None)
                if len(self.cache) < self.cache_max:
                    self.cache[i] = local[i]
        return [self.cache[i] if i in self.cache else local[i] for i in idx]

    def _hop1_grids(self, es: Sequence[Sample]) -> Optional[List[np.ndarray]]:
        """The warp of each chain sample's ``prev2`` to its previous frame's pose (the chain's first hop, as the loop
        warps every frame it carries); None (unwarped) without the warp, or for an export that lacks the pose of
        ``prev2`` (written before session 41: the first hop then trains unwarped, said once)."""
        if not self.warp:
            return None
        if any(s.prev2_ego2global is None for s in es):
            if not self.hop1_unwarped_said:
                print("chain: the export holds no prev2_ego2global (written before session 41): the chain's first "
                      "hop trains on an UNwarped previous frame; export again for the warped chain", flush=True)
                self.hop1_unwarped_said = True
            return None
        return [self.grid((s.k, s.cam2ego, s.prev_ego2global, s.prev2_ego2global)) for s in es]

    def grid(self, geom: Tuple) -> np.ndarray:
        """(H, W, 2) the warp of a sample's previous frame to its pose (b2dr_ref/warp.py); ``geom``: geometry(s)."""
        return ground_warp_grid(*geom, self.render_hw, self.warp)

    def batch(self, idx: Sequence[int], other: Optional[Sequence[int]] = None):
        """The model inputs of samples ``idx``; with ``other`` (one index per sample), ``masks_other``: the masks of
        those samples (train --self-prev-pose other)."""
        items = self._prepare(idx)
        nl = len(self.sizes)
        dev = self.device
        extra = {}
        if other is not None:
            extra["masks_other"] = torch.stack([unpack_masks(it[3]) for it in self._prepare(other)]).float().to(dev)
        if self.chain:
            extra["z_prev2"] = torch.stack([it[7][0] for it in items]).to(dev)
            extra["masks_prev"] = torch.stack([unpack_masks(it[7][1]) for it in items]).float().to(dev)
        if self.warp:
            extra["prev_grid"] = torch.stack([torch.from_numpy(self.grid(it[8])) for it in items])
        return dict(extra, x0=torch.stack([it[0] for it in items]).to(dev), z_prev=torch.stack([it[1] for it in items]).to(dev),
                    ref_latents=torch.stack([it[2] for it in items]).to(dev),
                    masks=torch.stack([unpack_masks(it[3]) for it in items]).float().to(dev),
                    cams=torch.tensor([it[4] for it in items], dtype=torch.int64),
                    pe_cur=[torch.stack([it[5][j] for it in items]).to(dev) for j in range(nl)],
                    pe_ref=[torch.stack([it[6][j] for it in items]).to(dev) for j in range(nl)])


def diffusion_loss(unet, controlnet, context, b, gen: torch.Generator, abar: torch.Tensor, p_noprev: float = 0.1,
                   ref_dropout: Optional[float] = None, weighting: str = "eps", max_weight: float = 0.0,
                   prediction: str = "epsilon", object_weight: float = 0.0, fast: FastPath = PLAIN,
                   marking_weight: float = 0.0, x0_base: str = "none", self_prev: float = 0.0, vae=None):
    """One batch's (weighted) MSE of the model's prediction (all random draws from ``gen``, on the CPU, then moved to
    the device). ``prediction``: the model predicts epsilon, or v = sqrt(abar) eps - sqrt(1 - abar) x_0
    (diffusers' v_prediction; the sampler then reads x_0 = sqrt(abar) x_t - sqrt(1 - abar) v).
    ``object_weight`` W > 0: latent pixels whose 8x8 image cell holds an object (mask channels car .. bicycle)
    weigh 1 + W in the MSE (small vehicles cover ~5 % of the pixels and otherwise barely move the loss);
    ``marking_weight`` the same for lane dividers and crosswalks (the two add up in a cell holding both).
    ``fast`` (fastpath.py): memory format and autocast of the forward; ``unet`` / ``controlnet`` may then be the
    compiled wrappers of ``FastPath.prepare``. The random draws and the loss are the same in every mode.
    ``x0_base`` "prev": the diffusion runs on the residual x_0 - z_prev (the clean blurred previous latent; 0 for
    the rows drawn as "no previous frame"), and the sampler adds z_prev back (b2dr.json x0_base).
    ``self_prev`` P > 0 (with ``vae``): after the draws above, a row with a previous frame takes, with probability
    P, the model's own one-step render of its frame as the previous frame (training/selfprev.py).
    The pieces (draw_noise, noised_inputs, denoise, prediction_loss) are shared with b2dr_ref.training."""
    cfg = controlnet.config
    dev = b["x0"].device
    rd = float(cfg.ref_dropout) if ref_dropout is None else ref_dropout
    d = draw_noise(b, gen, int(cfg.prev_noise_max), p_noprev, rd)
    ctx = context.to(dev)[b["cams"].to(dev)]
    if self_prev > 0:
        if vae is None:
            raise ValueError("self_prev needs the VAE (the previous-frame path decodes and encodes)")
        s = draw_self(b, gen, self_prev)
        b = dict(b, z_prev=own_previous(unet, controlnet, vae, ctx, b, s, s["rows"] & ~d["noprev"], abar,
                                        prediction, x0_base, fast))
    if x0_base == "prev":
        keep = (~d["noprev"]).to(dev).float().reshape(-1, 1, 1, 1)
        b = dict(b, x0=b["x0"] - keep * b["z_prev"])
    elif x0_base != "none":
        raise ValueError(f"x0_base {x0_base!r} (none or prev)")
    x_t, z, n, at = noised_inputs(b, d, abar)
    # (a batch may leave the references out when every row drops them: ref_mask all False)
    pred = denoise(unet, controlnet, x_t, d["t"].to(dev), ctx, b["masks"], z, n, b.get("ref_latents"),
                   b.get("pe_cur"), b.get("pe_ref"), d["ref_mask"], fast=fast)
    return prediction_loss(pred, b, d, at, weighting=weighting, max_weight=max_weight, prediction=prediction,
                           object_weight=object_weight, marking_weight=marking_weight)


def run_config(args) -> Dict:
    cfg = nano.get_config(args.config)
    nano.check_config(cfg)
    return cfg


def load_matching(model: torch.nn.Module, sd: Dict[str, torch.Tensor]) -> List[str]:
    """Loads the tensors of ``sd`` whose names and shapes match the model's (every name must exist); returns the
    names left at the model's own initialisation because their shapes differ."""
    own = model.state_dict()
    missing = sorted(set(own) ^ set(sd))
    if missing:
        raise SystemExit(f"--init-from: the package's {type(model).__name__} differs in its tensors: {missing[:6]}")
    fresh = [k for k, v in sd.items() if own[k].shape != v.shape]
    model.load_state_dict({k: v for k, v in sd.items() if k not in fresh}, strict=False)
    return fresh


def package_context_rows(pkg) -> Dict[str, torch.Tensor]:
    """A package's context row (77, D) per camera (a (77, D) context serves every camera)."""
    cams, ctx = list(pkg.meta["cameras"]), pkg.context
    return {c: ctx if ctx.dim() == 2 else ctx[i] for i, c in enumerate(cams)}


def init_context(init: str, pkg, cameras: Sequence[str], extra: Optional[str]) -> torch.Tensor:
    """The starting context (n_cams, 77, D) in the data's camera order: the --init-from package's rows, and for the
    cameras it lacks (e.g. a one-camera gate denoiser started on six-camera data) the --init-context-from
    package's rows."""
    rows = package_context_rows(pkg)
    if extra:
        from .package import load_package

        for c, r in package_context_rows(load_package(extra)).items():
            if r.shape != next(iter(rows.values())).shape:
                raise SystemExit(f"--init-context-from {extra}: its context rows {tuple(r.shape)} differ from "
                                 f"--init-from's {tuple(next(iter(rows.values())).shape)}")
            rows.setdefault(c, r)
    lacking = [c for c in cameras if c not in rows]
    if lacking:
        hint = (" nor among --init-context-from's" if extra else
                "; --init-context-from PKG takes the missing cameras' context rows from another package")
        raise SystemExit(f"--init-from {init}: the data's cameras {lacking} are not among the package's "
                         f"{list(pkg.meta['cameras'])}{hint}")
    return torch.stack([rows[c] for c in cameras]).clone()


PREV_NOISE_KEYS = ("prev_noise_max", "prev_noise_level")
PREV_KEYS = PREV_NOISE_KEYS + ("prev_blur_sigma", "prev_warp_max_depth")
MAX_PREV_BLUR = 4.0


def prev_overrides(cfg: Dict, args) -> Dict:
    """The config with --prev-noise-max / --prev-noise-level (the previous frame's noise levels: training draws n ~
    U{0..max}, the package's sampler uses level; checked to lie in 0..998) and --prev-blur-sigma (the Gaussian blur,
    in pixels, of the previous frame before it is encoded, in training and in the package's sampler; in
    (0, 4]) in place of the design's."""
    over = {k: int(getattr(args, k)) for k in PREV_NOISE_KEYS if getattr(args, k, None) is not None}
    for k, v in over.items():
        if not 0 <= v <= NO_PREV_NOISE_LEVEL - 1:
            raise SystemExit(f"--{k.replace('_', '-')} {v}: a noise level in 0..{NO_PREV_NOISE_LEVEL - 1}")
    blur = getattr(args, "prev_blur_sigma", None)
    if blur is not None:
        if not 0 < float(blur) <= MAX_PREV_BLUR:
            raise SystemExit(f"--prev-blur-sigma {blur}: pixels in (0, {MAX_PREV_BLUR:g}]")
        over["prev_blur_sigma"] = float(blur)
    warp = getattr(args, "prev_warp_max_depth", None)
    if warp is not None:
        if not 0 <= float(warp) <= MAX_WARP_DEPTH:
            raise SystemExit(f"--prev-warp-max-depth {warp}: metres in [0, {MAX_WARP_DEPTH:g}] (0: no warp)")
        over["prev_warp_max_depth"] = float(warp)
    return dict(cfg, controlnet=dict(cfg["controlnet"], **over)) if over else cfg


def train(args):
    device = torch.device(args.device)
    set_threads(args.device, args.threads)
    if not 0 <= args.self_prev <= 1:
        raise SystemExit(f"--self-prev {args.self_prev}: a probability in [0, 1]")
    os.makedirs(args.out, exist_ok=True)
    ck_path = os.path.join(args.out, CKPT)
    resume = args.resume and os.path.exists(ck_path)
    ck = torch.load(ck_path, map_location="cpu", weights_only=False) if resume else None
    cfg = ck["cfg"] if ck else prev_overrides(run_config(args), args)
    if ck:
        for k in PREV_KEYS:
            v = getattr(args, k, None)
            have = cfg["controlnet"].get(k, B2DR_DEFAULTS[k])
            if v is not None and float(v) != float(have):
                raise SystemExit(f"--resume: the run's {k} is {have}, not --{k.replace('_', '-')} {v}")
    source = open_source(args.data, cfg["render_size"])
    if list(source.render_size) != list(cfg["render_size"]):
        raise SystemExit(f"data render size {source.render_size} != config {cfg['render_size']}")
    init = getattr(args, "init_from", None) if not ck else None
    if getattr(args, "init_context_from", None) and not getattr(args, "init_from", None):
        raise SystemExit("--init-context-from fills the context rows an --init-from package lacks: give --init-from")
    vae_path = ck["vae_path"] if ck and not args.vae else args.vae
    if not vae_path and init:
        vae_path = os.path.join(init, "vae")
    if not vae_path:
        raise SystemExit("--vae VAE_DIR (the trained VAE: vae_train's RUN/vae) is required")
    vae = load_vae(vae_path).to(device)
    unet, controlnet = build_diffusion_models(cfg, seed=args.seed)
    cameras = ck["cameras"] if ck else list(source.cameras)
    context = ck["context"] if ck else make_context(cfg, cameras, seed=args.seed)
    if init:
        # continue training from an exported package (e.g. the committed models/b2dr-nano, f16 weights widened
        # to f32): its UNet, ControlNet, per-camera context and (unless --vae) VAE; a fresh optimizer and schedule
        from .package import load_package

        pkg = load_package(init)
        fresh = load_matching(unet, pkg.unet.state_dict()) + load_matching(controlnet, pkg.controlnet.state_dict())
        if fresh:
            # a design with another latent width: the tensors that touch the latent start fresh
            print(f"--init-from {init}: fresh (other shapes): {', '.join(fresh)}", flush=True)
        context = init_context(init, pkg, cameras, getattr(args, "init_context_from", None))
    unet.to(device).train()
    controlnet.to(device).train()
    params = list(unet.parameters()) + list(controlnet.parameters())
    opt = torch.optim.AdamW(params, lr=args.lr, weight_decay=args.weight_decay)
    total = ck["total_steps"] if ck else args.steps
    if args.end_at is not None and not ck:
        raise SystemExit("--end-at shortens a resumed run's schedule: use it with --resume (a new run: --steps)")
    anneal = end_at_anneal(args.warmup, total, ck.get("anneal") if ck else None, ck["step"] if ck else 0,
                           args.end_at)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda(args.warmup, total, anneal=anneal))
    gen = torch.Generator().manual_seed(args.seed)
    ema = Ema([unet, controlnet], args.ema) if args.ema > 0 else None
    step = 0
    if ck:
        unet.load_state_dict(ck["unet"])
        controlnet.load_state_dict(ck["controlnet"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["lr_scheduler"])
        gen.set_state(ck["generator"])
        torch.set_rng_state(ck["torch_rng"])
        if ema is not None and ck.get("ema") is not None:
            ema.shadow = {k: v.to(device) for k, v in ck["ema"].items()}
        step = ck["step"]
    steps = args.steps if not ck else max(args.steps, step)
    if anneal is not None:
        steps = anneal[1]
    if args.stop_after:
        steps = min(steps, step + args.stop_after)
    abar = make_noise_scheduler().alphas_cumprod.to(torch.float32)
    latents = None
    if not args.no_latents_file:
        latents = (os.path.join(args.out, LATENTS_FILE),
                   latent_cache_key(args.data, vae_path, float(controlnet.config.prev_blur_sigma),
                                    float(controlnet.config.prev_warp_max_depth)))
    if args.self_prev_pose == "chain":
        if args.self_prev <= 0:
            raise SystemExit("--self-prev-pose chain: give --self-prev P > 0")
        if not getattr(source, "prev_chain", False):
            raise SystemExit(f"--self-prev-pose chain: {args.data} is not an export with the previous frame's "
                             "inputs (b2dr export-training --prev-chain)")
    if float(controlnet.config.prev_warp_max_depth) > 0 and args.self_prev > 0 and args.self_prev_pose != "chain":
        raise SystemExit(f"--self-prev-pose {args.self_prev_pose} with a warped previous frame: the own render "
                         "would be warped from a pose it was not drawn at; use --self-prev-pose chain")
    batcher = Batcher(source, vae, controlnet, device, cache=args.cache, latents=latents,
                      chain=args.self_prev_pose == "chain")
    prediction = ck.get("prediction", "epsilon") if ck else args.prediction
    if ck and prediction != args.prediction:
        raise SystemExit(f"--resume: the run predicts {prediction}, not --prediction {args.prediction}")
    x0_base = ck.get("x0_base", "none") if ck else args.x0_base
    if ck and x0_base != args.x0_base:
        raise SystemExit(f"--resume: the run's x_0 base is {x0_base}, not --x0-base {args.x0_base}")
    if prediction == "v_prediction" and args.loss_weight == "v":
        raise SystemExit("--loss-weight v with --prediction v_prediction would weight the v loss twice "
                         "(the v MSE already is the epsilon MSE x (1 + 1/SNR)): use --loss-weight eps")
    run_meta = dict(cfg=cfg, cameras=cameras, vae_path=os.path.abspath(vae_path), total_steps=total, anneal=anneal, prediction=prediction,
                    x0_base=x0_base,
                    args={k: v for k, v in vars(args).items() if k != "func"})
    with open(os.path.join(args.out, "run.json"), "w") as f:
        json.dump(run_meta, f, indent=2)
    log = CsvLog(os.path.join(args.out, "log.csv"), ["step", "loss", "lr", "grad_norm", "sec"], step)
    losses = []

    fast = FastPath(channels_last=args.channels_last, compile=args.compile, autocast=args.autocast)
    unet_f, controlnet_f = fast.prepare(unet, controlnet)     # state_dict from the originals
    # fp16 autocast: gradients of fp16 activations underflow without loss scaling (bf16 has f32's range and needs none)
    scaler = torch.amp.GradScaler(device.type) if fast.autocast == "fp16" else None
    if scaler is not None and ck is not None and ck.get("grad_scaler"):
        scaler.load_state_dict(ck["grad_scaler"])
    partners = None
    if args.self_prev_pose == "other":
        if args.self_prev <= 0:
            raise SystemExit("--self-prev-pose other: give --self-prev P > 0")
        partners = pose_partners(source)
        if partners is None:
            raise SystemExit(f"--self-prev-pose other: {args.data} is not an exported dataset with several ego "
                             "offsets per frame (b2dr export-training --offsets)")
    prefetch = Prefetcher(lambda a: batcher.batch(*a)) if args.prefetch else None
    pending = dict(gen_state=None, batch=None)   # the prefetched step: gen state before its index draw, its batch

    def checkpoint():
        if prefetch is not None and prefetch.busy:     # the batcher (latents file) must be idle
            pending["batch"] = prefetch.take()
        # with a prefetched step, the generator as it was before that step's index draw: a resume draws it again
        g_state = pending["gen_state"] if pending["gen_state"] is not None else gen.get_state()
        save_checkpoint(ck_path, dict(
            run_meta, step=step, unet=unet.state_dict(), controlnet=controlnet.state_dict(),
            optimizer=opt.state_dict(), lr_scheduler=sched.state_dict(), generator=g_state,
            torch_rng=torch.get_rng_state(), ema=ema.shadow if ema is not None else None, context=context,
            grad_scaler=scaler.state_dict() if scaler is not None else None))
        batcher.save_latents()

    def keep():
        # the weights alone (no optimizer): what export --step needs to package this step later
        os.makedirs(os.path.join(args.out, "keep"), exist_ok=True)
        save_checkpoint(keep_path(args.out, step), dict(
            run_meta, step=step, unet=unet.state_dict(), controlnet=controlnet.state_dict(),
            ema=ema.shadow if ema is not None else None, context=context))

    def draw_idx():
        """The batch's sample indices and, with --self-prev-pose other, each one's partner (drawn after them)."""
        idx = list(range(args.batch)) if args.fixed_batch else \
            torch.randint(0, len(source), (args.batch,), generator=gen).tolist()
        if partners is None:
            return idx, None
        return idx, [partners[i][int(torch.randint(0, len(partners[i]), (1,), generator=gen))] for i in idx]

    if args.precache:
        batcher.precache()
    if not fast.plain:
        print(f"fast path: {fast.describe()}", flush=True)
    t_start = time.perf_counter()
    try:
        while step < steps:
            t0 = time.perf_counter()
            if prefetch is not None and prefetch.busy:
                b = prefetch.take()
            elif pending["batch"] is not None:
                b, pending["batch"] = pending["batch"], None
            else:
                b = batcher.batch(*draw_idx())
            loss = diffusion_loss(unet_f, controlnet_f, context, b, gen, abar, p_noprev=args.p_noprev,
                                  weighting=args.loss_weight, max_weight=args.max_weight, prediction=prediction,
                                  object_weight=args.object_weight, fast=fast,
                                  marking_weight=args.marking_weight, x0_base=x0_base,
                                  self_prev=args.self_prev, vae=vae)
            pending["gen_state"] = None
            if prefetch is not None and step + 1 < steps:
                # the next step's indices are drawn now, after this step's noise: the generator's sequence is
                # that of a run without prefetch
                pending["gen_state"] = gen.get_state()
                prefetch.submit(draw_idx())
            gn, skipped = optimizer_step(loss, params, opt, args.clip, scaler)
            if skipped:
                print(f"step {step + 1}: fp16 gradients overflowed, update skipped (loss scale now "
                      f"{scaler.get_scale():g})", flush=True)
            sched.step()
            if ema is not None:
                ema.update([unet, controlnet])
            step += 1
            lv = float(loss.detach())
            losses.append(lv)
            log.write(dict(step=step, loss=f"{lv:.6f}", lr=f"{sched.get_last_lr()[0]:.3e}", grad_norm=f"{float(gn):.4f}",
                           sec=f"{time.perf_counter() - t0:.3f}"))
            if step % args.log_every == 0:
                print(f"step {step} loss {lv:.4f} ({time.perf_counter() - t0:.2f} s)", flush=True)
            if args.keep_every and step % args.keep_every == 0:
                keep()
            if step % args.ckpt_every == 0 or step == steps:
                checkpoint()
            elif args.time_limit and time.perf_counter() - t_start > args.time_limit:
                checkpoint()
                print(f"--time-limit {args.time_limit:g} s reached at step {step} of {steps} (checkpoint written; "
                      f"lr {sched.get_last_lr()[0]:.3e}: the schedule did not end)", flush=True)
                break
    finally:
        if prefetch is not None and prefetch.busy:
            prefetch.take()
        log.close()
    return losses


def optimizer_step(loss, params, opt, clip: float, scaler=None):
    """Backward, gradient clipping and the optimizer step; with ``scaler`` (a torch.amp.GradScaler, fp16 autocast)
    the loss is scaled before backward, the gradients unscaled before clipping, and a step whose gradients hold an
    inf or NaN is skipped (the scale halves; it doubles after 2,000 clean steps). Returns (gradient norm,
    skipped)."""
    opt.zero_grad(set_to_none=True)
    if scaler is None:
        loss.backward()
        gn = torch.nn.utils.clip_grad_norm_(params, clip)
        opt.step()
        return gn, False
    scaler.scale(loss).backward()
    scaler.unscale_(opt)
    gn = torch.nn.utils.clip_grad_norm_(params, clip)
    before = scaler.get_scale()
    scaler.step(opt)
    scaler.update()
    return gn, scaler.get_scale() < before


# ---------------------------------------------------------------------------------------------------------------
# Export
# ---------------------------------------------------------------------------------------------------------------


def checkpoint_models(ck, ema: bool = True):
    """The UNet and ControlNet of a loaded checkpoint: its EMA weights when it kept an EMA and ``ema``, else the raw
    weights. Returns (unet, controlnet, used_ema)."""
    unet, controlnet = build_diffusion_models(ck["cfg"])
    use_ema = ema and ck.get("ema") is not None
    if use_ema:
        sh = ck["ema"]
        unet.load_state_dict({k[2:]: v for k, v in sh.items() if k.startswith("0.")})
        controlnet.load_state_dict({k[2:]: v for k, v in sh.items() if k.startswith("1.")})
    else:
        unet.load_state_dict(ck["unet"])
        controlnet.load_state_dict(ck["controlnet"])
    return unet, controlnet, use_ema


def keep_path(run: str, step: int) -> str:
    return os.path.join(run, "keep", f"step_{step:07d}.pt")


def check_same_latent_space(vae, run_vae_path: str, given: str, what: str = "export --vae"):
    """export --vae, replace-vae: the denoiser samples in the latent space of the VAE it trained with, so another
    VAE must share its encoder side (encoder, quant_conv) and scaling factor: a decoder trained alone (vae_train
    --decoder-only) does, a VAE trained again does not and would decode the samples into garbage. Refused when
    they differ; a note when the run's VAE folder is not here to compare."""
    if not os.path.isdir(run_vae_path):
        print(f"{what} {given}: the run's VAE {run_vae_path} is not here; its latent space is not checked",
              flush=True)
        return
    own = load_vae(run_vae_path)
    a, b = own.state_dict(), vae.state_dict()
    enc = [k for k in a if k.startswith(("encoder.", "quant_conv."))]
    differ = [k for k in enc if k not in b or b[k].shape != a[k].shape or
              not torch.equal(b[k].float(), a[k].float())]
    if differ or float(vae.config.scaling_factor) != float(own.config.scaling_factor):
        raise SystemExit(f"{what} {given}: not the latent space the denoiser trained in ({run_vae_path}): "
                         + (f"{len(differ)} encoder-side tensors differ" if differ else "another scaling factor")
                         + "; only a decoder trained alone (vae_train --decoder-only --init-from that VAE) fits")


def export(args):
    from .package import make_meta, save_package

    if not args.sampler_steps >= 1:
        raise SystemExit(f"export: --sampler-steps {args.sampler_steps}: at least 1")
    path = os.path.join(args.run, CKPT) if args.step is None else keep_path(args.run, args.step)
    if not os.path.exists(path):
        kdir = os.path.join(args.run, "keep")
        kept = sorted(os.listdir(kdir)) if os.path.isdir(kdir) else []
        raise SystemExit(f"export: {path} does not exist" + (f" (kept: {', '.join(kept) or 'none'})"
                                                               if args.step is not None else ""))
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if args.prev_noise_level is not None:
        # the inference-time level only (training's n ~ U{0..max} is history): what the package's sampler uses
        ck["cfg"] = prev_overrides(ck["cfg"], args)
    if getattr(args, "prev_source", None):
        # an inference choice of the package (the weights are the same): a rollout's previous-frame input
        if args.prev_source != "previous" and not float(ck["cfg"]["controlnet"].get("prev_warp_max_depth", 0)) > 0:
            raise SystemExit(f"export --prev-source {args.prev_source}: the run does not warp its previous frame "
                             "(--prev-warp-max-depth); an unwarped reference would not line up with the frame")
        ck["cfg"] = dict(ck["cfg"], controlnet=dict(ck["cfg"]["controlnet"], prev_source=args.prev_source))
    cfg = ck["cfg"]
    unet, controlnet, use_ema = checkpoint_models(ck, ema=not args.no_ema)
    vae = load_vae(args.vae or ck["vae_path"])
    if args.vae:
        check_same_latent_space(vae, ck["vae_path"], args.vae)
    meta = make_meta(cfg["render_size"], ck["cameras"], sampler="unipc", steps=args.sampler_steps, ref_guidance=2.0,
                     dtype=args.dtype,
                     prediction_type=ck.get("prediction", "epsilon"), x0_base=ck.get("x0_base", "none"))
    save_package(args.out, unet.eval(), controlnet.eval(), vae, ck["context"], meta)
    size = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(args.out) for f in fs)
    print(f"exported step {ck['step']}{' (EMA)' if use_ema else ''} to {args.out}: {size / 1e6:.1f} MB")
    return size


def replace_vae(args):
    """``train replace-vae``: a copy of a package with another VAE of the same latent space (a decoder trained
    alone on it), the denoiser, ControlNet, context and b2dr.json unchanged; refused when the encoder side or the
    scaling factor differ from the package's own VAE."""
    from .package import load_package, save_package

    if os.path.abspath(args.out) == os.path.abspath(args.package):
        raise SystemExit(f"replace-vae: --out {args.out} is the package itself; write a copy")
    if os.path.exists(args.out) and os.listdir(args.out):
        raise SystemExit(f"replace-vae: --out {args.out} exists and is not empty")
    vae = load_vae(args.vae)
    check_same_latent_space(vae, os.path.join(args.package, "vae"), args.vae, what="replace-vae")
    pkg = load_package(args.package)
    save_package(args.out, pkg.unet, pkg.controlnet, vae, pkg.context, pkg.meta)
    print(f"wrote {args.out}: {args.package} with the VAE {args.vae}", flush=True)


# ---------------------------------------------------------------------------------------------------------------


def bench(args):
    """``train bench``: b2dr_ref.train_bench (throughput per setting, sweep, profile, data preparation)."""
    from .train_bench import bench as run_bench

    return run_bench(args)


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "export":
        p = argparse.ArgumentParser(prog="python -m b2dr_ref.train export")
        p.add_argument("--run", required=True)
        p.add_argument("--out", required=True)
        p.add_argument("--dtype", default="f16", choices=["f16", "f32"])
        p.add_argument("--vae", default=None, help="VAE folder (default: the one the run trained with)")
        p.add_argument("--no-ema", action="store_true", help="export the raw weights even when the run kept an EMA")
        p.add_argument("--step", type=int, default=None,
                       help="export the weights kept at this step (a run trained with --keep-every), not the last")
        p.add_argument("--sampler-steps", type=int, default=20,
                       help="the package's UniPC steps per frame (b2dr.json `steps`; eval-render --steps overrides)")
        p.add_argument("--prev-noise-level", type=int, default=None,
                       help="the previous frame's noise level at inference in the package's ControlNet config "
                            "(default: the run's)")
        p.add_argument("--prev-source", default=None, choices=PREV_SOURCES,
                       help="the package's ControlNet key prev_source (default: the run's, \"previous\"): in a "
                            "rollout the previous-frame input is the frame rendered before, or (\"reference\", a "
                            "warping run only) a retrieved reference warped to the current pose, or "
                            "(\"composite\") that reference with the agents' pixels from the frame rendered before")
        return export(p.parse_args(argv[1:]))
    if argv and argv[0] == "replace-vae":
        p = argparse.ArgumentParser(prog="python -m b2dr_ref.train replace-vae")
        p.add_argument("--package", required=True, help="the model package to copy")
        p.add_argument("--vae", required=True, help="the VAE folder to put in (vae_train --decoder-only on its VAE)")
        p.add_argument("--out", required=True, help="the new package folder (absent or empty)")
        return replace_vae(p.parse_args(argv[1:]))
    if argv and argv[0] == "bench":
        p = argparse.ArgumentParser(prog="python -m b2dr_ref.train bench")
        p.add_argument("--config", default="nano")
        p.add_argument("--batch", type=int, default=8)
        p.add_argument("--steps", type=int, default=6)
        p.add_argument("--threads", type=int, default=None)
        p.add_argument("--device", default="cpu")
        p.add_argument("--ref-dropout", type=float, default=0.0, help="0 = every row uses references (worst case)")
        p.add_argument("--channels-last", action="store_true")
        p.add_argument("--compile", action="store_true")
        p.add_argument("--autocast", default="none", choices=AUTOCASTS)
        p.add_argument("--sweep", action="store_true",
                       help="the documented set-up, eager f32 at --batch / --threads and each fast path, in one run")
        p.add_argument("--profile", action="store_true", help="CPU self time per op class of each setting")
        p.add_argument("--data-prep", action="store_true", help="also time the per-sample data preparation")
        p.add_argument("--json", default=None, help="write the results here")
        return bench(p.parse_args(argv[1:]))
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.train")
    add_common(p)
    p.add_argument("--vae", default=None, help="the trained VAE folder (vae_train's RUN/vae)")
    p.add_argument("--end-at", type=int, default=None,
                   help="with --resume: end the run at this step instead: the lr falls from its current value to 0 "
                        "along a cosine between the resume step and this one (kept by later resumes)")
    p.add_argument("--init-from", default=None,
                   help="start a new run from an exported model package (weights, context, VAE unless --vae)")
    p.add_argument("--init-context-from", default=None,
                   help="with --init-from: a package whose per-camera context rows serve the data's cameras that "
                        "the --init-from package lacks (e.g. b2dr-nano's six rows around a one-camera denoiser)")
    p.add_argument("--keep-every", type=int, default=0,
                   help="also keep the weights of every N-th step in RUN/keep/ (export --step N packages one): the "
                        "points of a learning curve scored after the run")
    p.add_argument("--ema", type=float, default=0.0, help="EMA decay (0 = off); export uses the EMA when kept")
    p.add_argument("--self-prev", type=float, default=0.0,
                   help="probability that a row's previous frame is the model's own one-step render of its frame "
                        "(decoded, blurred, encoded again) instead of the true one: it learns to correct its own "
                        "output, as the closed loop needs (training/selfprev.py; 0 = off)")
    p.add_argument("--self-prev-pose", default="same", choices=("same", "other", "chain"),
                   help="the pose of --self-prev's own render: the row's own (same), or another ego offset of the "
                        "same frame (other: the render is displaced against the target, as a previous frame is; "
                        "needs data exported with several --offsets), or the previous frame itself rendered from "
                        "the frame before it (chain: the closed loop's input one step earlier; needs data "
                        "exported with --prev-chain)")
    p.add_argument("--p-noprev", type=float, default=0.1, help="probability of 'no previous frame' (z = 0, n = 999)")
    p.add_argument("--cache", type=int, default=100000, help="samples whose latents + PE are kept in memory")
    p.add_argument("--precache", action="store_true",
                   help="encode every sample before the first step (progress printed; same values as lazy encoding)")
    p.add_argument("--time-limit", type=float, default=0.0,
                   help="stop (with a checkpoint) once the steps have run this many seconds (0 = no limit); the "
                        "schedule still spans --steps, so size --steps to the time")
    p.add_argument("--no-latents-file", action="store_true",
                   help="do not keep the VAE latents of the data in RUN/latents.pt (a resume then encodes them again)")
    p.add_argument("--loss-weight", default="eps", choices=LOSS_WEIGHTS,
                   help="per-noise-level weight of the MSE: eps (1), v (1 + 1/SNR: with --prediction epsilon, the "
                        "v-prediction loss), "
                        "min-snr (Min-SNR-5)")
    p.add_argument("--max-weight", type=float, default=0.0, help="cap of the loss weight (0 = none)")
    p.add_argument("--object-weight", type=float, default=0.0,
                   help="extra MSE weight on latent cells holding an object (vehicles, pedestrians, two-wheelers): "
                        "1 + this there (0 = plain)")
    p.add_argument("--marking-weight", type=float, default=0.0,
                   help="extra MSE weight on latent cells holding a lane divider or crosswalk pixel (0 = plain)")
    p.add_argument("--channels-last", action="store_true", help="NHWC memory format (fastpath.py)")
    p.add_argument("--compile", action="store_true", help="torch.compile the UNet and ControlNet forward")
    p.add_argument("--autocast", default="none", choices=AUTOCASTS, help="autocast dtype of the forward")
    p.add_argument("--prefetch", action="store_true",
                   help="prepare the next batch on a background thread during backward + optimizer")
    p.add_argument("--prev-noise-max", type=int, default=None,
                   help="training draws the previous frame's noise level n ~ U{0..N} (default: the config's, 400)")
    p.add_argument("--prev-noise-level", type=int, default=None,
                   help="the noise level of the previous frame at inference, exported in the ControlNet config "
                        "(default: the config's, 200)")
    p.add_argument("--prev-blur-sigma", type=float, default=None,
                   help="Gaussian blur (pixels) of the previous frame before it is encoded, in training and in the "
                        "exported ControlNet config (default: the config's, 1)")
    p.add_argument("--prev-warp-max-depth", type=float, default=None,
                   help="metres: warp the previous frame to the current pose over the flat ground, rays capped at "
                        "this depth (b2dr_ref/warp.py), in training and in the exported ControlNet config; 0 = no "
                        "warp (default: the config's, 0)")
    p.add_argument("--x0-base", default="none", choices=X0_BASES,
                   help="prev: diffuse the residual against the previous frame's clean latent (exported as "
                        "b2dr.json x0_base; the sampler adds the base back)")
    p.add_argument("--prediction", default="epsilon", choices=PREDICTIONS,
                   help="what the UNet predicts: epsilon, or v (exported as b2dr.json prediction_type)")
    return train(p.parse_args(argv))


if __name__ == "__main__":
    main()
