"""The ``sd15`` recipe: the B2D-R renderer from a diffusers Stable Diffusion 1.5 folder (issue #33; the paper's
recipe, docs/training.md "At the paper's scale").

    accelerate launch [--num_processes N] [--mixed_precision fp16|bf16] -m b2dr_ref.training.sd15 \\
        --pretrained SD15_DIR --data EXPORT --output_dir RUN [--train_batch_size B] \\
        [--gradient_accumulation_steps K] [--gradient_checkpointing] [--use_ema] [--freeze_unet] \\
        [--resume_from_checkpoint latest]
    python -m b2dr_ref.training.sd15 export --run RUN --out MODEL_DIR [--checkpoint latest] [--dtype f16]

Set-up order of diffusers' examples/controlnet/train_controlnet.py: Accelerator; the folder's noise scheduler,
VAE (frozen) and UNet (``from_pretrained(subfolder=...)``); the B2D-R ControlNet ``from_unet`` (the UNet's encoder;
the B2D-R parts fresh, their outputs zero); the per-camera context (the folder's CLIP on one prompt per camera,
encoded once, kept in RUN/context.safetensors and exported as the package's context); optimizer; DataLoader;
lr scheduler; ``accelerator.prepare``. Each step runs inside ``accelerator.accumulate``; ``global_step`` counts
optimizer steps; gradients are clipped when they sync.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import sys
import time

import torch

from ..controlnet import B2DRControlNetModel
from ..frame import SD15_SCHEDULE
from .loss import noised_inputs, prediction_loss
from . import common

# The paper's recipe (Bench2Drive-R; renderer.md 3, world.md 3): the defaults of every argument it names.
RECIPE = dict(
    resolution=[224, 400],
    train_batch_size=4,
    max_train_steps=50_000,
    learning_rate=1e-4,
    lr_scheduler="cosine",
    lr_warmup_steps=3_000,
    ref_dropout=0.2,
    p_noprev=0.1,
    prev_noise_max=400,
    prev_noise_level=200,
    prev_blur_sigma=1.0,
    pe_depth_num=64,
    conditioning_embedding_out_channels=[16, 32, 96, 256],
    reference_bins=common.REFERENCE_BINS,
)
PROMPT = "a driving scene photographed by the {camera} camera of a car"


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.training.sd15", description=__doc__.split("\n\n")[0])
    p.add_argument("--pretrained", "--pretrained_model_name_or_path", dest="pretrained", required=True,
                   help="a diffusers SD1.5 folder: unet/, vae/, text_encoder/, tokenizer/, scheduler/")
    p.add_argument("--freeze_unet", "--freeze-unet", dest="freeze_unet", action="store_true",
                   help="train the ControlNet only (MagicDrive); the UNet stays the pretrained one")
    p.add_argument("--prompt", default=PROMPT, help="per-camera prompt; {camera} = e.g. 'front left'")
    common.add_training_args(p, RECIPE)
    return common.checked_args(p.parse_args(argv))


def camera_prompt(template: str, camera: str) -> str:
    words = camera.lower().replace("cam_", "").replace("_", " ")
    return template.format(camera=words)


@torch.no_grad()
def encode_prompts(pretrained: str, prompts) -> torch.Tensor:
    """The folder's CLIP text model on the prompts: (n, 77, D) last hidden states (SD1.5's context)."""
    from transformers import CLIPTextModel, CLIPTokenizer

    tok = CLIPTokenizer.from_pretrained(pretrained, subfolder="tokenizer")
    enc = CLIPTextModel.from_pretrained(pretrained, subfolder="text_encoder").eval()
    ids = tok(list(prompts), padding="max_length", max_length=tok.model_max_length, truncation=True,
              return_tensors="pt").input_ids
    return enc(ids)[0].float()


def camera_context(accelerator, args, cameras) -> torch.Tensor:
    """RUN/context.safetensors (written once, by the main process first; a resume reads it back)."""
    from safetensors.torch import load_file, save_file

    path = os.path.join(args.output_dir, common.CONTEXT_FILE)
    with accelerator.main_process_first():
        if not os.path.exists(path) and accelerator.is_main_process:
            ctx = encode_prompts(args.pretrained, [camera_prompt(args.prompt, c) for c in cameras])
            save_file({"cond": ctx.contiguous()}, path + ".tmp")
            os.replace(path + ".tmp", path)
    return load_file(path)["cond"].float()


def check_schedule(noise_scheduler):
    """The engine samples with SD1.5's schedule and epsilon prediction: the folder's must be the same."""
    from diffusers import DDPMScheduler

    ref = DDPMScheduler(**SD15_SCHEDULE).alphas_cumprod
    if noise_scheduler.alphas_cumprod.shape != ref.shape or \
            not torch.allclose(noise_scheduler.alphas_cumprod.float(), ref.float(), atol=1e-6):
        raise SystemExit("--pretrained: its scheduler's noise schedule is not SD1.5's (the engine samples with it)")
    if noise_scheduler.config.prediction_type != "epsilon":
        raise SystemExit(f"--pretrained: prediction_type {noise_scheduler.config.prediction_type} (epsilon only)")


def main(args):
    t_main = time.perf_counter()
    from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
    from diffusers.optimization import get_scheduler

    os.makedirs(args.output_dir, exist_ok=True)
    accelerator = common.make_accelerator(args)
    from accelerate.utils import set_seed

    set_seed(args.seed)
    if args.allow_tf32:
        torch.backends.cuda.matmul.allow_tf32 = True

    # frozen and pretrained models (diffusers' subfolders)
    noise_scheduler = DDPMScheduler.from_pretrained(args.pretrained, subfolder="scheduler")
    check_schedule(noise_scheduler)
    vae = AutoencoderKL.from_pretrained(args.pretrained, subfolder="vae")
    unet = UNet2DConditionModel.from_pretrained(args.pretrained, subfolder="unet")
    controlnet = B2DRControlNetModel.from_unet(
        unet, conditioning_embedding_out_channels=tuple(args.conditioning_embedding_out_channels),
        prev_noise_level=args.prev_noise_level, prev_noise_max=args.prev_noise_max,
        prev_blur_sigma=args.prev_blur_sigma, pe_depth_num=args.pe_depth_num, ref_dropout=args.ref_dropout)
    vae.requires_grad_(False).eval()
    unet.requires_grad_(not args.freeze_unet)
    controlnet.train()
    model = common.ControlledUNet(unet, controlnet)
    common.set_attention(model, args.attention)
    if args.gradient_checkpointing:
        controlnet.enable_gradient_checkpointing()
        unet.enable_gradient_checkpointing()
    ema = common.make_ema(model, args.ema_decay) if args.use_ema else None
    common.register_checkpoint_hooks(accelerator, ema, train_unet=not args.freeze_unet)

    dataset = common.CameraSamples(args.data, args.resolution, controlnet.config, seed=args.seed,
                                   reference_bins=args.reference_bins)
    common.check_reference_bins(dataset, args.reference_bins)
    context = camera_context(accelerator, args, dataset.cameras)

    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=args.learning_rate, betas=(args.adam_beta1, args.adam_beta2),
                                  weight_decay=args.adam_weight_decay, eps=args.adam_epsilon)
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=args.train_batch_size, shuffle=True, collate_fn=common.collate_fn,
        num_workers=args.dataloader_num_workers, worker_init_fn=common.worker_init_fn,
        prefetch_factor=args.dataloader_prefetch_factor if args.dataloader_num_workers > 0 else None,
        persistent_workers=args.dataloader_num_workers > 0, drop_last=True)
    # the schedule counts optimizer steps whatever the number of processes (it is stepped here once per optimizer
    # step, not by accelerate once per process), so a run resumes on another number of GPUs with the same lr
    lr_scheduler = get_scheduler(args.lr_scheduler, optimizer=optimizer, num_warmup_steps=args.lr_warmup_steps,
                                 num_training_steps=args.max_train_steps)
    model, optimizer, loader = accelerator.prepare(model, optimizer, loader)
    accelerator.register_for_checkpointing(lr_scheduler)

    weight_dtype = common.weight_dtype_of(accelerator)
    vae.to(accelerator.device, dtype=weight_dtype)
    if args.freeze_unet:
        accelerator.unwrap_model(model).unet.to(dtype=weight_dtype)
    if ema is not None:
        ema.to(accelerator.device)
    context = context.to(accelerator.device)
    abar = noise_scheduler.alphas_cumprod.to(torch.float32)
    if accelerator.is_main_process:
        common.write_run_json(args, dataset.cameras, dict(pretrained=os.path.abspath(args.pretrained),
                                                          freeze_unet=bool(args.freeze_unet),
                                                          prediction_type="epsilon", recipe="sd15"))
    common.init_trackers(accelerator, args)

    # resume (diffusers: --resume_from_checkpoint latest | path)
    global_step = 0
    ck = common.resume_path(args.resume_from_checkpoint, args.output_dir)
    if args.resume_from_checkpoint and ck is None:
        accelerator.print(f"--resume_from_checkpoint {args.resume_from_checkpoint}: no checkpoint yet; a new run")
    if ck is not None:
        accelerator.print(f"resuming from {ck}")
        accelerator.load_state(ck)
        global_step = common.checkpoint_step(ck)
    batches = len(loader)
    if batches == 0:
        raise SystemExit(f"{args.data}: {len(dataset)} camera samples do not fill one batch of "
                         f"{args.train_batch_size} per process x {accelerator.num_processes} processes")
    per_epoch = max(1, math.ceil(batches / args.gradient_accumulation_steps))
    first_epoch, skip = divmod(global_step, per_epoch)
    epochs = common.epochs_for(args.max_train_steps, batches, args.gradient_accumulation_steps)
    stop_at = args.max_train_steps
    if args.stop_after_steps:
        stop_at = min(stop_at, global_step + args.stop_after_steps)
    log = common.open_csv_log(args, global_step) if accelerator.is_main_process else None
    accelerator.print(f"sd15: {len(dataset)} camera samples, {accelerator.num_processes} processes x batch "
                      f"{args.train_batch_size} x accumulation {args.gradient_accumulation_steps} = "
                      f"{accelerator.num_processes * args.train_batch_size * args.gradient_accumulation_steps} "
                      f"per step; steps {global_step} -> {stop_at} of {args.max_train_steps}; "
                      f"mixed precision {accelerator.mixed_precision}")

    accelerator.print(f"sd15: set-up {time.perf_counter() - t_main:.1f} s")
    if args.dataloader_num_workers > 0:
        # the set-up's objects out of the cyclic GC before the DataLoader forks its workers: a worker's collections
        # would write to them and so copy the parent's pages into every worker, the group's memory growing over an
        # epoch (Python's gc.freeze docs; measured: docs/training.md "The data pipeline")
        gc.collect()
        gc.freeze()
    micro = global_step * args.gradient_accumulation_steps       # micro-batch number: the noise stream
    saved_at = global_step
    t0 = time.perf_counter()
    done = global_step >= stop_at
    for epoch in range(first_epoch, epochs):
        if done:
            break
        if hasattr(loader, "set_epoch"):
            loader.set_epoch(epoch)
        # accelerate passes the epoch to the sampler, not also to the data set: the references of a shard folder
        # are drawn for this epoch (the same on every process, and again after a resume)
        dataset.set_epoch(epoch)
        it = loader
        if epoch == first_epoch and skip:
            it = accelerator.skip_first_batches(loader, skip * args.gradient_accumulation_steps)
        for batch in it:
            with accelerator.accumulate(model):
                b = common.encode_batch(vae, batch, args.prev_blur_sigma, accelerator.device, weight_dtype)
                d = common.per_sample_draws(b, args.seed, micro, args.prev_noise_max, args.p_noprev, args.ref_dropout)
                x_t, z, n, at = noised_inputs(b, d, abar)
                pred = model(x_t, d["t"].to(accelerator.device), context[b["cams"]], b["masks"], z, n,
                             b["ref_latents"], b["pe_cur"], b["pe_ref"], d["ref_mask"].to(accelerator.device))
                loss = prediction_loss(pred, b, d, at)
                accelerator.backward(loss)
                gn = torch.zeros(())
                if accelerator.sync_gradients:
                    gn = accelerator.clip_grad_norm_(params, args.max_grad_norm)
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            micro += 1
            if not accelerator.sync_gradients:
                continue
            lr_scheduler.step()
            global_step += 1
            if ema is not None:
                ema.step(params)
            lv = float(accelerator.gather(loss.detach().reshape(1)).mean())
            lr = lr_scheduler.get_last_lr()[0]
            scalars = {"loss": lv, "lr": lr, "grad_norm": float(gn)}
            if accelerator.scaler is not None:
                # fp16 on a GPU: accelerate's GradScaler; an overflowing step is skipped and the scale halves
                scalars["loss_scale"] = accelerator.scaler.get_scale()
                if accelerator.optimizer_step_was_skipped:
                    accelerator.print(f"step {global_step}: fp16 gradients overflowed, update skipped (loss scale "
                                      f"now {scalars['loss_scale']:g})")
            accelerator.log(scalars, step=global_step)
            if log is not None:
                log.write(dict(step=global_step, loss=f"{lv:.6f}", lr=f"{lr:.3e}", grad_norm=f"{float(gn):.4f}",
                               sec=f"{time.perf_counter() - t0:.3f}"))
            t0 = time.perf_counter()
            if global_step % args.checkpointing_steps == 0 or global_step >= stop_at:
                common.save_checkpoint(accelerator, args.output_dir, global_step, args.checkpoints_total_limit)
                saved_at = global_step
            if args.validation_steps and global_step % args.validation_steps == 0 and accelerator.is_main_process:
                path = common.log_validation(accelerator, accelerator.unwrap_model(model), vae, context, dataset,
                                             args, global_step, ema)
                accelerator.print(f"validation grid: {path}")
            if global_step >= stop_at:
                done = True
                break
    if saved_at != global_step:
        common.save_checkpoint(accelerator, args.output_dir, global_step, args.checkpoints_total_limit)
    if log is not None:
        log.close()
    accelerator.print(f"sd15: stopped at step {global_step} of {args.max_train_steps}")
    accelerator.end_training()
    return global_step


def export_main(argv):
    p = argparse.ArgumentParser(prog="python -m b2dr_ref.training.sd15 export")
    p.add_argument("--run", required=True, help="the run folder (--output_dir of the training)")
    p.add_argument("--out", required=True, help="the model package folder")
    p.add_argument("--checkpoint", default="latest", help="'latest' or a checkpoint-{step} folder")
    p.add_argument("--dtype", default="f16", choices=["f16", "f32"])
    p.add_argument("--no-ema", "--no_ema", dest="no_ema", action="store_true")
    a = p.parse_args(argv)
    r = common.export_package(a.run, a.out, checkpoint=a.checkpoint, dtype=a.dtype, use_ema=not a.no_ema)
    print(f"exported step {r['step']}{' (EMA)' if r['ema'] else ''} of {a.run} to {a.out}")
    return r


if __name__ == "__main__":
    argv = sys.argv[1:]
    if argv and argv[0] == "export":
        export_main(argv[1:])
    else:
        main(parse_args(argv))
