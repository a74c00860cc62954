"""The sd15 recipe (python/b2dr_ref/training; issue #33) on a tiny SD1.5-shaped diffusers folder.

- a nuScenes-fixture export (b2dr export-training nuscenes:...; the recorded images are the targets) when the
  b2dr binary and the shared nuScenes data are there, else the synthetic source (printed);
- run A: ``accelerate launch --multi_gpu --num_processes 2`` on the CPU (gloo; ACCELERATE_USE_CPU) with bf16
  autocast, gradient accumulation 2, gradient checkpointing, EMA and a checkpoint every step kept to 2; it stops
  after 2 of its 3 steps (``--stop_after_steps``), and a half-written ``checkpoint-3.tmp`` is left as a kill
  mid-save would leave it;
- run B resumes it (``--resume_from_checkpoint latest``) with 2 processes x batch 1 in f32 for one step (forked
  from this process as accelerate's debug_launcher does: a second `accelerate launch` would cost ~20 s of imports);
  the same step from the same checkpoint with 1 process x batch 2 (in this process) gives the same weights
  (UPDATE_TOL);
- the package exported from run B loads (b2dr_ref.package), carries the CLIP per-camera context, and the engine
  computes its UNet as diffusers does and renders its whole frame (`b2dr forward --component frame` on named inputs)
  as b2dr_ref.frame.render_frame does, also with its ControlNet made visible (its zero-initialised layers drawn at
  random).

Budget: the module's tests take <= 60 s on the 2-core machine (docs/training.md "At the paper's scale").
"""
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

HERE = Path(__file__).resolve().parent
PY = HERE.parent
SHARED = HERE.parents[1] / ".." / "shared" / "data" / "nuscenes-mini"
if not SHARED.exists():
    SHARED = Path("/work/shared/data/nuscenes-mini")

import accelerate  # noqa: E402,F401  (tools/ensure-python.sh installs accelerate and transformers: no skip)
import transformers  # noqa: E402,F401

from b2dr_ref.training import common  # noqa: E402
from b2dr_ref.training.tiny_sd15 import write_tiny_sd15  # noqa: E402

SIZE = "32x56"
# f32, 2 processes x batch 1 against 1 process x batch 2, one AdamW step (lr 1e-4) from the same checkpoint: the
# largest weight difference measured 1.5e-8 against a largest update of 2.5e-5 (0.06 %; float summation order)
UPDATE_TOL = 1e-7
# the engine's whole frame against render_frame: tests/nn_b2dr_golden.rs fn tol (f32), normalised MSE
FRAME_TOL = 1e-5
MODEL_ARGS = ["--resolution", SIZE, "--pe_depth_num", "4", "--conditioning_embedding_out_channels", "8,16,16,32",
              "--max_train_steps", "3", "--lr_warmup_steps", "1", "--validation_sampling_steps", "2",
              "--num_validation_images", "2", "--use_ema", "--ema_decay", "0.9"]


def b2dr_binary():
    sys.path.insert(0, str(HERE))
    from scale_helpers import b2dr_binary as find

    try:
        return find()
    except pytest.skip.Exception:
        return None


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    return write_tiny_sd15(str(tmp_path_factory.mktemp("sd15")))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    exe = b2dr_binary()
    if exe is None or not (SHARED / "scenes" / "scene-0061.json").exists():
        print("test_train_sd15: no b2dr binary or shared nuScenes data: training on synthetic:8")
        return "synthetic:8"
    from b2dr_ref import nuscenes_fixture as nf

    root = tmp_path_factory.mktemp("nus")
    nf.write_fixture(SHARED, root)
    out = str(tmp_path_factory.mktemp("export"))
    subprocess.run([exe, "export-training", "--scenario", f"nuscenes:{root}:scene-0061", "--out", out, "--size", SIZE,
                    "--samples-per-scenario", "4", "--cameras", "CAM_FRONT,CAM_BACK", "--quiet"], check=True,
                   cwd=str(root))
    return out


def launch(args, processes=2, precision="no"):
    env = dict(os.environ, ACCELERATE_USE_CPU="true", OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1",
               TRANSFORMERS_OFFLINE="1", PYTHONPATH=str(PY))
    exe = Path(sys.executable).with_name("accelerate")
    cmd = [str(exe), "launch", "--multi_gpu", "--num_processes", str(processes), "--num_machines", "1",
           "--mixed_precision", precision, "--dynamo_backend", "no", "--main_process_port", str(free_port()),
           "-m", "b2dr_ref.training.sd15"] + [str(a) for a in args]
    t = time.perf_counter()
    r = subprocess.run(cmd, env=env, cwd=str(PY), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout + r.stderr, time.perf_counter() - t


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _main(argv):
    from b2dr_ref.training import sd15

    torch.set_num_threads(1)
    sd15.main(sd15.parse_args(argv))


def fork_launch(args, processes=2):
    """accelerate's debug_launcher (its own multi-process CPU tests: gloo, fork, no re-import), on a free port:
    the processes start from this one's imports (an `accelerate launch` costs ~10 s of imports per process)."""
    import tempfile

    from accelerate.state import AcceleratorState, GradientState
    from accelerate.utils import PrepareForLaunch, patch_environment
    from torch.multiprocessing import start_processes

    AcceleratorState._reset_state(True)
    GradientState._reset_state()
    t = time.perf_counter()
    with tempfile.NamedTemporaryFile() as rdv, patch_environment(
            world_size=processes, master_addr="127.0.0.1", master_port=str(free_port()),
            accelerate_mixed_precision="no", accelerate_debug_rdv_file=rdv.name, accelerate_use_cpu="yes",
            gloo_socket_ifname="lo", omp_num_threads="1"):
        start_processes(PrepareForLaunch(_main, debug=True), args=([str(a) for a in args],), nprocs=processes,
                        start_method="fork")
    return time.perf_counter() - t


def in_process(args):
    """main(args) in this process, one CPU process (accelerate's state reset first)."""
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


def read_log(run):
    with open(os.path.join(run, "log.csv")) as f:
        return [line.split(",") for line in f.read().split()[1:]]


@pytest.fixture(scope="module")
def run_a(pretrained, data, tmp_path_factory):
    out = str(tmp_path_factory.mktemp("run") / "sd15")
    text, sec = launch(["--pretrained", pretrained, "--data", data, "--output_dir", out, *MODEL_ARGS,
                        "--train_batch_size", "1", "--gradient_accumulation_steps", "2", "--gradient_checkpointing",
                        "--checkpointing_steps", "1", "--checkpoints_total_limit", "2", "--stop_after_steps", "2",
                        "--validation_steps", "2", "--dataloader_num_workers", "1"], precision="bf16")
    print(f"run A (2 processes, bf16): {sec:.1f} s")
    return out, text


def test_two_process_bf16_run_keeps_its_checkpoints(run_a):
    out, text = run_a
    assert "2 processes x batch 1 x accumulation 2 = 4 per step" in text
    assert "mixed precision bf16" in text
    cks = [os.path.basename(c) for c in common.checkpoints(out)]
    assert cks == ["checkpoint-1", "checkpoint-2"], cks             # every step saved (run B prunes)
    ck = os.path.join(out, "checkpoint-2")
    for f in ("controlnet/config.json", "controlnet/diffusion_pytorch_model.safetensors", "unet/config.json",
              "ema.pt", "optimizer.bin", "random_states_0.pkl", "random_states_1.pkl", "custom_checkpoint_0.pkl"):
        assert os.path.exists(os.path.join(ck, f)), f
    rows = read_log(out)
    assert [int(r[0]) for r in rows] == [1, 2]
    assert all(torch.isfinite(torch.tensor(float(r[1]))) for r in rows)
    assert os.path.exists(os.path.join(out, "validation", "step-0000002.png"))
    if common.tensorboard_available():
        events = [f for _, _, fs in os.walk(os.path.join(out, "logs")) for f in fs if f.startswith("events.")]
        assert events, "TensorBoard event files"
    else:
        assert "tensorboard package is not installed" in text
    with open(os.path.join(out, "run.json")) as f:
        run = json.load(f)
    assert run["cameras"] == ["CAM_FRONT", "CAM_BACK"] and run["resolution"] == [32, 56]


@pytest.fixture(scope="module")
def run_b(run_a, pretrained, data, tmp_path_factory):
    """Run A resumed (latest; a half-written checkpoint-4.tmp as a kill mid-save leaves it), one f32 step with 2
    processes x batch 1; and the same step in this process with 1 process x batch 2 from a copy of run A."""
    out, _ = run_a
    ref = str(tmp_path_factory.mktemp("ref") / "sd15")
    shutil.copytree(out, ref)
    os.makedirs(os.path.join(out, "checkpoint-3.tmp", "controlnet"))
    common_args = ["--pretrained", pretrained, "--data", data, *MODEL_ARGS, "--gradient_accumulation_steps", "1",
                   "--checkpointing_steps", "1", "--checkpoints_total_limit", "2", "--stop_after_steps", "1",
                   "--validation_steps", "0", "--resume_from_checkpoint", "latest"]
    sec = fork_launch(["--output_dir", out, "--train_batch_size", "1", *common_args])
    print(f"run B (2 processes, resumed): {sec:.1f} s")
    t = time.perf_counter()
    step = in_process(["--output_dir", ref, "--train_batch_size", "2", *common_args])
    print(f"reference (1 process, batch 2): {time.perf_counter() - t:.1f} s")
    assert step == 3
    return out, ref


def weights(ck):
    from safetensors.torch import load_file

    return {f"{part}.{k}": v for part in ("unet", "controlnet")
            for k, v in load_file(os.path.join(ck, part, "diffusion_pytorch_model.safetensors")).items()}


def test_resume_continues_from_the_latest_complete_checkpoint(run_b):
    out, _ = run_b
    # checkpoint-2 (not the half-written checkpoint-3.tmp) resumed; checkpoint-3 written, checkpoint-1 pruned
    assert [os.path.basename(c) for c in common.checkpoints(out)] == ["checkpoint-2", "checkpoint-3"]
    assert [int(r[0]) for r in read_log(out)] == [1, 2, 3]
    before, after = weights(os.path.join(out, "checkpoint-2")), weights(os.path.join(out, "checkpoint-3"))
    assert max(float((after[k] - before[k]).abs().max()) for k in after) > 1e-6, "the step changed the weights"


def test_two_processes_equal_one_process(run_b):
    """2 processes x batch 1 and 1 process x batch 2: the same samples, the same per-sample noise, the same update."""
    out, ref = run_b
    a, b = weights(os.path.join(out, "checkpoint-3")), weights(os.path.join(ref, "checkpoint-3"))
    before = weights(os.path.join(out, "checkpoint-2"))
    assert a.keys() == b.keys()
    diff = max(float((a[k] - b[k]).abs().max()) for k in a)
    step = max(float((a[k] - before[k]).abs().max()) for k in a)
    print(f"2 x 1 vs 1 x 2: largest weight difference {diff:.3e} (largest update {step:.3e})")
    assert diff <= UPDATE_TOL, diff
    # and the loss each logged for the step
    la, lb = float(read_log(out)[-1][1]), float(read_log(ref)[-1][1])
    assert abs(la - lb) <= 1e-5 * max(1.0, abs(lb)), (la, lb)


@pytest.fixture(scope="module")
def exported(run_b, tmp_path_factory):
    """The package exported from run B (EMA weights, f32)."""
    out, _ = run_b
    model = tmp_path_factory.mktemp("package") / "model"
    r = common.export_package(out, str(model), dtype="f32")
    return model, r


def test_export_package_loads_and_the_engine_computes_its_unet(run_b, exported, pretrained, tmp_path):
    """The package exported from run B (EMA weights) loads with b2dr_ref.package, carries the CLIP per-camera
    context; the engine (`b2dr forward --component unet`, Vulkan) computes its trained UNet, fed the B2D-R
    ControlNet's residuals from PyTorch, equal to diffusers within the golden tests' f32 tolerance (normalised
    MSE 1e-5); and `b2dr render` renders a frame of a keyframe with it (a smoke test: the whole frame against
    PyTorch is test_engine_frame_equals_the_pytorch_frame)."""
    from safetensors.torch import load_file, save_file

    from b2dr_ref.package import load_package
    from b2dr_ref.training.sd15 import PROMPT, camera_prompt, encode_prompts

    out, _ = run_b
    model, r = exported
    assert r["step"] == 3 and r["ema"]
    pkg = load_package(str(model))
    assert pkg.meta["render_size"] == [32, 56] and pkg.meta["cameras"] == ["CAM_FRONT", "CAM_BACK"]
    want = encode_prompts(pretrained, [camera_prompt(PROMPT, c) for c in pkg.meta["cameras"]])
    torch.testing.assert_close(pkg.context, want)
    assert pkg.controlnet.config.pe_depth_num == 4 and pkg.controlnet.config.ref_dropout == 0.2
    # the EMA weights (decay 0.9 over 3 steps) differ from the raw ones the checkpoint also holds
    raw = weights(os.path.join(out, "checkpoint-3"))
    k = "controlnet.controlnet_cond_embedding.conv_in.weight"
    assert not torch.equal(pkg.controlnet.state_dict()[k[len("controlnet."):]], raw[k])

    exe = b2dr_binary()
    if exe is None:
        pytest.skip("no b2dr binary for the engine half (cargo build, or B2DR_BIN)")
    g = torch.Generator().manual_seed(0)
    x, t = torch.randn((2, 4, 4, 7), generator=g), torch.tensor([500, 20])
    with torch.no_grad():
        down, mid = pkg.controlnet(x, t, pkg.context, (torch.rand((2, 15, 32, 56), generator=g) > 0.7).float(),
                                   torch.randn((2, 4, 4, 7), generator=g), torch.tensor([200, 200]))
        # the zero convs have moved by 3 steps only: add noise so that the residual inputs matter
        down = [d + 0.1 * torch.randn(d.shape, generator=g) for d in down]
        mid = mid + 0.1 * torch.randn(mid.shape, generator=g)
        ref = pkg.unet(x, t, pkg.context, down_block_additional_residuals=down,
                       mid_block_additional_residual=mid).sample
    inputs = {"sample": x, "timestep": t.float(), "encoder_hidden_states": pkg.context, "mid_residual": mid}
    inputs.update({f"down_residual_{i}": d for i, d in enumerate(down)})
    save_file({k: v.float().contiguous() for k, v in inputs.items()}, str(tmp_path / "in.safetensors"))
    subprocess.run([exe, "forward", "--component", "unet", "--config", str(model / "unet" / "config.json"),
                    "--weights", str(model / "unet" / "diffusion_pytorch_model.safetensors"),
                    "--inputs", str(tmp_path / "in.safetensors"), "--out", str(tmp_path / "out.safetensors")],
                   check=True, capture_output=True)
    got = load_file(str(tmp_path / "out.safetensors"))["sample"]
    nmse = float(((got - ref) ** 2).mean() / (ref ** 2).mean())
    print(f"engine UNet vs diffusers on the exported package: normalised MSE {nmse:.2e}")
    assert nmse <= 1e-5, nmse
    # and the engine renders a whole B2D-R frame of both cameras with the package (2 UniPC steps)
    frame = SHARED / "keyframe-scene-0061" / "frame.json"
    if frame.exists():
        subprocess.run([exe, "render", "--model", str(model), "--frame", str(frame), "--steps", "2",
                        "--out", str(tmp_path / "render")], check=True, capture_output=True)
        with open(tmp_path / "render" / "render.json") as f:
            assert json.load(f)
        assert (tmp_path / "render" / "CAM_FRONT.png").exists() and (tmp_path / "render" / "CAM_BACK.png").exists()


def nmse(got, want) -> float:
    """Normalised MSE sum((got - want)^2) / sum(want^2): the measure of tests/golden/common.rs nmse."""
    got, want = got.double(), want.double()
    return float(((got - want) ** 2).sum() / (want ** 2).sum().clamp_min(1e-30))


def frame_inputs(pkg, seed):
    """Named frame inputs (as the golden files name them) for the package's cameras at its render size: random
    masks, images, noise and position encodings at the ControlNet's Ref-Attn locations (helpers.frame_inputs)."""
    sys.path.insert(0, str(HERE))
    from helpers import frame_inputs as random_inputs

    h, w = pkg.meta["render_size"]
    x = random_inputs(pkg.controlnet, n=len(pkg.meta["cameras"]), h=h // 8, w=w // 8, seed=seed)
    named = {"in.x_T": x["x_T"], "in.eps_prev": x["eps_prev"], "in.masks": x["masks"], "in.prev_image": x["prev"],
             "in.ref_images": x["ref_images"]}
    for j, (c, r) in enumerate(zip(x["pe_cur"], x["pe_ref"])):
        named[f"in.pe_cur.{j}"], named[f"in.pe_ref.{j}"] = c, r
    return named


def pytorch_frame(pkg, x, steps, ref_guidance):
    from b2dr_ref.frame import render_frame

    nl = sum(k.startswith("in.pe_cur.") for k in x)
    return render_frame(pkg.unet, pkg.controlnet, pkg.vae, x["in.x_T"], pkg.context, x["in.masks"],
                        x["in.prev_image"], x["in.eps_prev"], ref_images=x["in.ref_images"],
                        pe_cur=[x[f"in.pe_cur.{j}"] for j in range(nl)],
                        pe_ref=[x[f"in.pe_ref.{j}"] for j in range(nl)], steps=steps, ref_guidance=ref_guidance,
                        sampler=pkg.meta["sampler"], prediction_type=pkg.meta.get("prediction_type", "epsilon"))


def engine_frame(exe, model, x, tmp, steps, ref_guidance):
    from safetensors.torch import load_file, save_file

    save_file({k: v.float().contiguous() for k, v in x.items()}, str(tmp / "frame_in.safetensors"))
    r = subprocess.run([exe, "forward", "--component", "frame", "--model", str(model), "--steps", str(steps),
                        "--ref-guidance", str(ref_guidance), "--inputs", str(tmp / "frame_in.safetensors"),
                        "--out", str(tmp / "frame_out.safetensors")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    return load_file(str(tmp / "frame_out.safetensors"))


def sensitized(model, out):
    """A copy of the package whose ControlNet the frame sees. Three training steps moved its zero-initialised layers
    (zero convs, conditioning-embedding conv_out, noise-embedding linear_2, Ref-Attn output projections, conv_in's
    previous-latent channels) by ~1e-4 only, so the exported package's frame does not see its ControlNet (w 1 against
    w 2: ~1e-14): here they are drawn at random (seeded; the Ref-Attn projections x 100), and the conditioning
    embedding's other convs are scaled by 3 (at PyTorch's initialisation they shrink the masks' signal ~3x per
    layer: another draw of the masks would move the frame by ~1e-9)."""
    from b2dr_ref.package import load_package

    pkg = load_package(str(model))
    g = torch.Generator().manual_seed(0)
    sd = pkg.controlnet.state_dict()
    new = {}
    for k, v in sd.items():
        ref_out = k.startswith("ref_attn.") and ".to_out." in k
        if k.endswith(".weight") and (ref_out or k.startswith((
                "controlnet_cond_embedding.conv_out.", "controlnet_down_blocks.", "controlnet_mid_block.",
                "noise_embedding.linear_2."))):
            assert float(v.abs().max()) < 1e-3, k
            new[k] = torch.randn(v.shape, generator=g) * (100.0 if ref_out else 1.0) / v[0].numel() ** 0.5
        elif k.startswith("controlnet_cond_embedding.") and k.endswith(".weight"):
            new[k] = 3.0 * v
    w = sd["conv_in.weight"].clone()
    assert float(w[:, 4:].abs().max()) < 1e-3
    w[:, 4:] = torch.randn(w[:, 4:].shape, generator=g) / w[0].numel() ** 0.5
    new["conv_in.weight"] = w
    pkg.controlnet.load_state_dict(new, strict=False)
    shutil.copytree(model, out)
    pkg.controlnet.save_pretrained(str(out / "controlnet"), dtype=torch.float32)
    return pkg


def compare_frames(exe, model, pkg, x, tmp, steps, w):
    """The engine's frame against render_frame's: normalised MSE of image, latent and previous-frame latent, and
    the two frames."""
    ref = pytorch_frame(pkg, x, steps, w)
    got = engine_frame(exe, model, x, tmp, steps, w)
    errs = {"image": nmse(got["image"], ref.image), "latent": nmse(got["latent"], ref.latent),
            "prev_latent": nmse(got["prev_latent"], ref.prev.z)}
    return errs, ref


def test_engine_frame_equals_the_pytorch_frame(exported, tmp_path):
    """The engine renders a whole B2D-R frame of the exported package (`b2dr forward --component frame`: both
    cameras, 2 UniPC steps, reference guidance 2, f32) equal to b2dr_ref.frame.render_frame on the same named inputs
    (noise, masks, previous frame, references, position encodings at the Ref-Attn locations; the package's
    per-camera context) within tests/nn_b2dr_golden.rs's f32 tolerance (normalised MSE 1e-5) for the image, the
    final latent and the noised previous-frame latent; and so it does for the package with its ControlNet made
    visible (`sensitized`). The comparison can fail: another seed's noise moves the frame far beyond the tolerance,
    and on the sensitized package so do its ControlNet, reference guidance 1 instead of 2, and another draw of the
    masks, of the previous latent's noise or of the reference images (all printed)."""
    from b2dr_ref.package import load_package

    exe = b2dr_binary()
    if exe is None:
        pytest.skip("no b2dr binary for the engine half (cargo build, or B2DR_BIN)")
    model, _ = exported
    pkg = load_package(str(model))
    steps, w = 2, 2.0
    x = frame_inputs(pkg, seed=1)
    t = time.perf_counter()
    errs, ref = compare_frames(exe, model, pkg, x, tmp_path, steps, w)
    other_seed = nmse(pytorch_frame(pkg, dict(x, **{"in.x_T": frame_inputs(pkg, seed=2)["in.x_T"]}), steps, w).image,
                      ref.image)
    unguided = nmse(pytorch_frame(pkg, x, steps, 1.0).latent, ref.latent)
    print(f"engine vs PyTorch frame of the exported package ({steps} UniPC steps, w {w}): normalised MSE "
          + ", ".join(f"{k} {v:.2e}" for k, v in errs.items()) + f" (tol {FRAME_TOL:.0e}); PyTorch image with "
          f"another seed's x_T: {other_seed:.2e}; latent with w 1: {unguided:.2e} (the ControlNet is not seen)")
    for k, e in errs.items():
        assert e <= FRAME_TOL, (k, e)
    assert other_seed > 1e3 * FRAME_TOL, other_seed

    visible = tmp_path / "sensitized"
    spkg = sensitized(model, visible)
    serrs, sref = compare_frames(exe, visible, spkg, x, tmp_path, steps, w)
    # what the sensitized frame's latent moves by when one thing changes: were the engine to miss it, it would
    # differ from PyTorch by about as much
    other = frame_inputs(pkg, seed=2)
    moves = {"its ControlNet (the exported package's frame)": nmse(ref.latent, sref.latent),
             "w 1": nmse(pytorch_frame(spkg, x, steps, 1.0).latent, sref.latent)}
    for k in ("in.masks", "in.eps_prev", "in.ref_images"):
        moves[k] = nmse(pytorch_frame(spkg, dict(x, **{k: other[k]}), steps, w).latent, sref.latent)
    print("engine vs PyTorch frame of the sensitized package: normalised MSE "
          + ", ".join(f"{k} {v:.2e}" for k, v in serrs.items()) + "; its PyTorch latent moves with "
          + ", ".join(f"{k}: {v:.2e}" for k, v in moves.items()) + f"; {time.perf_counter() - t:.1f} s")
    for k, e in serrs.items():
        assert e <= FRAME_TOL, ("sensitized", k, e)
    for k, m in moves.items():
        assert m > 30 * FRAME_TOL, (k, m)


def test_controlnet_starts_as_the_unet_encoder_with_zero_outputs(pretrained):
    """from_unet: the UNet's encoder weights; the B2D-R parts' outputs and every zero conv are zero, so the first
    step's prediction is the pretrained UNet's own."""
    from diffusers import UNet2DConditionModel

    from b2dr_ref.controlnet import B2DRControlNetModel

    unet = UNet2DConditionModel.from_pretrained(pretrained, subfolder="unet").eval()
    c = B2DRControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 16, 16, 32), pe_depth_num=4).eval()
    us = unet.state_dict()
    for k, v in c.state_dict().items():
        if k.startswith(("down_blocks.", "mid_block.", "time_embedding.")):
            torch.testing.assert_close(v, us[k])
    torch.testing.assert_close(c.conv_in.weight[:, :4], us["conv_in.weight"])
    assert float(c.conv_in.weight.detach()[:, 4:].abs().max()) == 0.0
    g = torch.Generator().manual_seed(1)
    x = torch.randn((2, 4, 4, 7), generator=g)
    ctx = torch.randn((2, 77, 32), generator=g)
    model = common.ControlledUNet(unet, c)
    sizes = [(2, 4), (1, 2), (1, 2), (1, 2)]
    with torch.no_grad():
        pred = model(x, torch.tensor([10, 500]), ctx, torch.ones((2, 15, 32, 56)), torch.randn((2, 4, 4, 7), generator=g),
                     torch.tensor([5, 300]), torch.randn((2, 2, 4, 4, 7), generator=g),
                     [torch.randn((2, 12) + s, generator=g) for s in sizes],
                     [torch.randn((2, 2, 12) + s, generator=g) for s in sizes], torch.tensor([True, False]))
        plain = unet(x, torch.tensor([10, 500]), ctx).sample
    torch.testing.assert_close(pred, plain)


def test_freeze_unet_trains_the_controlnet_only(pretrained, data, tmp_path):
    """--freeze_unet (MagicDrive): one step in this process with bf16 autocast; the checkpoint holds no unet/, the
    ControlNet moved, and the export's UNet is the pretrained one."""
    from diffusers import UNet2DConditionModel

    from b2dr_ref.package import load_package

    out = str(tmp_path / "frozen")
    in_process(["--pretrained", pretrained, "--data", data, "--output_dir", out, *MODEL_ARGS, "--freeze_unet",
                "--mixed_precision", "bf16", "--train_batch_size", "2", "--stop_after_steps", "1",
                "--validation_steps", "0", "--report_to", "none"])
    ck = os.path.join(out, "checkpoint-1")
    assert os.path.isdir(os.path.join(ck, "controlnet")) and not os.path.exists(os.path.join(ck, "unet"))
    r = common.export_package(out, str(tmp_path / "model"), dtype="f32", use_ema=False)
    pkg = load_package(str(tmp_path / "model"))
    want = UNet2DConditionModel.from_pretrained(pretrained, subfolder="unet").state_dict()
    for k, v in pkg.unet.state_dict().items():
        assert torch.equal(v, want[k]), k
    from b2dr_ref.controlnet import B2DRControlNetModel

    fresh = B2DRControlNetModel.from_unet(UNet2DConditionModel.from_pretrained(pretrained, subfolder="unet"),
                                          conditioning_embedding_out_channels=(8, 16, 16, 32), pe_depth_num=4)
    moved = [k for k, v in pkg.controlnet.state_dict().items() if not torch.equal(v, fresh.state_dict()[k])]
    assert len(moved) > 10 and r["step"] == 1


def test_fp16_on_the_cpu_is_refused_by_name(pretrained, data, tmp_path):
    """accelerate would run fp16 on the CPU without autocast or a gradient scaler (f32 training, fp16 frozen
    models): the recipe says so instead of training something else."""
    with pytest.raises(SystemExit, match="fp16 on the CPU"):
        in_process(["--pretrained", pretrained, "--data", data, "--output_dir", str(tmp_path / "fp16"), *MODEL_ARGS,
                    "--mixed_precision", "fp16", "--train_batch_size", "2", "--stop_after_steps", "1",
                    "--validation_steps", "0", "--report_to", "none"])
    assert not os.path.exists(tmp_path / "fp16" / "checkpoint-1")


def test_checkpoint_rotation_and_resume_path(tmp_path):
    for s in (10, 2, 30):
        os.makedirs(tmp_path / f"checkpoint-{s}")
    os.makedirs(tmp_path / "checkpoint-40.tmp")        # a save that did not finish
    assert [os.path.basename(c) for c in common.checkpoints(str(tmp_path))] == \
        ["checkpoint-2", "checkpoint-10", "checkpoint-30"]
    assert common.resume_path("latest", str(tmp_path)) == str(tmp_path / "checkpoint-30")
    assert common.resume_path("latest", str(tmp_path / "none")) is None
    assert common.resume_path("checkpoint-10", str(tmp_path)) == str(tmp_path / "checkpoint-10")
    with pytest.raises(SystemExit):
        common.resume_path("checkpoint-11", str(tmp_path))
