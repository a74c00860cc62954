"""Where a trained B2D-R renderer loses fidelity, in PyTorch, on an export of held-out frames (docs/training.md,
"Diagnosis"). Run with the project's environment from the repository root:

    ~/.cache/b2dr-venv/bin/python tools/diagnose_renderer.py --model models/b2dr-nano --data HELD_OUT_EXPORT \
        [--camera CAM_FRONT] [--frames 12] [--strip out.png]

--model is a model package folder or a training run folder (checkpoint.pt: its EMA weights unless --raw).
It prints, averaged over the chosen camera of up to --frames samples:
- the ceilings: the VAE's reconstruction of the target (decode(encode(target))), the copy of the previous frame;
- one-shot x_0 predictions from the TRUE x_t at t = 200 .. 999 (decoded, PSNR): what the model knows at each
  noise level when it is on the data's trajectory;
- the sampled frame (the package's sampler, steps and reference guidance; previous frame = the recorded one at
  the model's noise level), and the sampled latent's per-channel means vs the truth's: a model that cannot make
  the latent's channel offsets from zero-mean noise draws washed-out colour fields;
- the prediction loss on --data at fixed t (t = 100, 300, 500, 700, 900; the prediction type's MSE, unweighted, fixed
  noise, previous frame at the model's noise level, references on): a validation curve beside the training loss;
- with --from-prev T0[,T0...]: the frame sampled by DDIM (the package's steps) from the previous frame's latent
  noised to T0 (SDEdit) instead of pure noise at T, same conditioning: does the previous frame as the start keep
  what the full trajectory loses? (docs/training.md session 27: +1.9 dB at T0 = 401, still under the copy);
- the per-channel mean / std of the target latents (a VAE whose latents are far from zero-mean leaks the offset
  into x_T during training; `python -m b2dr_ref.vae_train centre` fixes that without changing the VAE's function).
All noise is seeded: reruns print the same figures.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))

from b2dr_ref.frame import decode_image, render_frame, vae_encode_mean  # noqa: E402
from b2dr_ref.training.loss import prediction_loss  # noqa: E402
from b2dr_ref.train import CKPT, Batcher, DatasetSource, checkpoint_models, load_vae, make_noise_scheduler  # noqa: E402


def load(path: str, raw: bool):
    if os.path.isdir(os.path.join(path, "unet")):
        from b2dr_ref.package import load_package

        p = load_package(path)
        return p.unet, p.controlnet, p.vae, p.context, p.meta
    ck = torch.load(os.path.join(path, CKPT), map_location="cpu", weights_only=False)
    unet, cn, _ = checkpoint_models(ck, ema=not raw)
    meta = dict(sampler="unipc", steps=20, ref_guidance=2.0, prediction_type=ck.get("prediction", "epsilon"),
                x0_base=ck.get("x0_base", "none"))
    return unet, cn, load_vae(ck["vae_path"]), ck["context"], meta


def psnr(img: torch.Tensor, tgt: torch.Tensor) -> float:
    return float(np.mean([10 * math.log10(1 / max(float(((a - b) ** 2).mean()), 1e-12)) for a, b in zip(img, tgt)]))


@torch.no_grad()
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True, help="a b2dr export-training folder of held-out scenarios")
    ap.add_argument("--camera", default="CAM_FRONT")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--raw", action="store_true", help="a run's raw weights instead of its EMA")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--strip", default=None, help="write truth | sampled pairs of every frame to this PNG")
    ap.add_argument("--json", default=None, help="also write the figures as JSON")
    ap.add_argument("--from-prev", default=None,
                    help="T0[,T0...]: also sample (DDIM) from the previous frame's latent noised to T0 (SDEdit)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    unet, cn, vae, ctx, meta = load(a.model, a.raw)
    unet.eval()
    cn.eval()
    src = DatasetSource(a.data)
    if a.camera not in src.cameras:
        raise SystemExit(f"--camera {a.camera}: the export has {src.cameras}")
    c_i = src.cameras.index(a.camera)
    idx = [f * len(src.cameras) + c_i for f in range(len(src) // len(src.cameras))][: a.frames]
    if not idx:
        raise SystemExit(f"{a.data}: no samples")
    bt = Batcher(src, vae, cn, "cpu").batch(idx)
    ss = [src[i] for i in idx]
    u8 = lambda arr: torch.from_numpy(np.stack(arr)).float() / 255.0   # noqa: E731
    tgt, prev = u8([s.target for s in ss]), u8([s.prev for s in ss])
    abar = make_noise_scheduler().alphas_cumprod.float()
    n = len(idx)
    nl = int(cn.config.prev_noise_level)
    prediction = meta.get("prediction_type", "epsilon")
    x0_base = meta.get("x0_base", "none")
    if a.from_prev and x0_base != "none":
        # a residual model already starts from the previous frame: its SDEdit would start the residual at 0
        raise SystemExit(f"--from-prev: for models without an x0 base (this one diffuses against {x0_base!r})")
    out = dict(model=a.model, data=a.data, camera=a.camera, frames=n, prediction_type=meta.get("prediction_type", "epsilon"),
               x0_base=x0_base)
    # the diffused variable: x_0, or its residual against the previous frame's clean latent (b2dr.json x0_base)
    base = bt["z_prev"] if x0_base == "prev" else torch.zeros_like(bt["x0"])
    bt_r = dict(bt, x0=bt["x0"] - base)
    out["vae_ceiling_psnr"] = psnr(decode_image(vae, bt["x0"]), tgt)
    out["copy_prev_psnr"] = psnr(prev, tgt)
    z = abar[nl].sqrt() * bt["z_prev"] + (1 - abar[nl]).sqrt() * torch.randn(bt["z_prev"].shape,
                                                                              generator=torch.Generator().manual_seed(1))
    refs = cn.prepare_references(bt["ref_latents"], bt["pe_cur"], bt["pe_ref"])
    c = ctx[bt["cams"]] if ctx.dim() == 3 else ctx[None].expand(n, -1, -1)
    one_shot = {}
    for t in (200, 400, 600, 800, 950, 999):
        at = abar[t]
        x_t = at.sqrt() * bt_r["x0"] + (1 - at).sqrt() * torch.randn(bt["x0"].shape, generator=torch.Generator().manual_seed(t))
        down, mid = cn(x_t, torch.full((n,), t), c, bt["masks"], z, torch.full((n,), nl), refs=refs)
        out_t = unet(x_t, t, c, down_block_additional_residuals=down, mid_block_additional_residual=mid).sample
        if prediction == "v_prediction":
            x0 = at.sqrt() * x_t - (1 - at).sqrt() * out_t
        else:
            x0 = (x_t - (1 - at).sqrt() * out_t) / at.sqrt()
        one_shot[t] = psnr(decode_image(vae, x0 + base), tgt)
    out["one_shot_x0_psnr"] = one_shot
    val = {}
    for t in (100, 300, 500, 700, 900):
        at = abar[t]
        eps = torch.randn(bt["x0"].shape, generator=torch.Generator().manual_seed(1000 + t))
        x_t = at.sqrt() * bt_r["x0"] + (1 - at).sqrt() * eps
        down, mid = cn(x_t, torch.full((n,), t), c, bt["masks"], z, torch.full((n,), nl), refs=refs)
        out_t = unet(x_t, t, c, down_block_additional_residuals=down, mid_block_additional_residual=mid).sample
        val[t] = float(prediction_loss(out_t, bt_r, dict(eps=eps), at, prediction=prediction))
    out["val_loss"] = val
    out["val_loss_mean"] = float(np.mean(list(val.values())))
    g = torch.Generator().manual_seed(0)
    x_T = torch.randn(bt["x0"].shape, generator=g)
    eps_prev = torch.randn(bt["x0"].shape, generator=g)
    res = render_frame(unet, cn, vae, x_T, c, bt["masks"], prev, eps_prev, ref_images=u8([s.refs for s in ss]),
                       pe_cur=bt["pe_cur"], pe_ref=bt["pe_ref"], steps=int(meta["steps"]),
                       ref_guidance=float(meta["ref_guidance"]), sampler=meta["sampler"], prediction_type=prediction,
                       x0_base=x0_base)
    out["sampled_psnr"] = psnr(res.image, tgt)
    out["sampled_latent_channel_means"] = res.latent.mean((0, 2, 3)).tolist()
    out["target_latent_channel_means"] = bt["x0"].mean((0, 2, 3)).tolist()
    out["target_latent_channel_stds"] = bt["x0"].transpose(0, 1).reshape(bt["x0"].shape[1], -1).std(1).tolist()
    print(f"{a.model} ({out['prediction_type']}, x0 base {x0_base}) on {n} x {a.camera} of {a.data}")
    print(f"  ceilings: VAE reconstruction {out['vae_ceiling_psnr']:.2f} dB, copy the previous frame "
          f"{out['copy_prev_psnr']:.2f} dB")
    print("  one-shot x0 from the true x_t: " + ", ".join(f"t={t} {v:.2f}" for t, v in one_shot.items()) + " dB")
    print(f"  {prediction} MSE at fixed t (unweighted): " + ", ".join(f"t={t} {v:.4f}" for t, v in val.items())
          + f"; mean {out['val_loss_mean']:.4f}")
    print(f"  sampled ({meta['sampler']}, {meta['steps']} steps, w {meta['ref_guidance']}): {out['sampled_psnr']:.2f} dB")
    fmt = lambda v: "[" + ", ".join(f"{x:+.2f}" for x in v) + "]"   # noqa: E731
    print(f"  latent channel means: target {fmt(out['target_latent_channel_means'])}, sampled "
          f"{fmt(out['sampled_latent_channel_means'])}; target stds {fmt(out['target_latent_channel_stds'])}")
    if a.from_prev:
        out["from_prev_psnr"] = {}
        for t0 in (int(v) for v in a.from_prev.split(",")):
            r = render_frame(unet, cn, vae, x_T, c, bt["masks"], prev, eps_prev, ref_images=u8([s.refs for s in ss]),
                             pe_cur=bt["pe_cur"], pe_ref=bt["pe_ref"], steps=int(meta["steps"]),
                             ref_guidance=float(meta["ref_guidance"]), sampler="ddim", prediction_type=prediction,
                             sdedit=(t0, vae_encode_mean(vae, prev)))
            out["from_prev_psnr"][t0] = psnr(r.image, tgt)
            print(f"  sampled (ddim, {meta['steps']} steps) from the previous frame noised to t = {t0}: "
                  f"{out['from_prev_psnr'][t0]:.2f} dB")
    if a.strip:
        from PIL import Image

        im = torch.cat([torch.cat([tgt[j], res.image[j]], 1) for j in range(n)], 2)
        Image.fromarray((im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(a.strip)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
