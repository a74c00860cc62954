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
  computes its UNet as diffusers does.

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


def test_export_package_loads_and_the_engine_computes_its_unet(run_b, pretrained, tmp_path):
    """The package exported from run B (EMA weights) loads with b2dr_ref.package, carries the CLIP per-camera
    context; the engine (`b2dr forward --component unet`, Vulkan) computes its trained UNet, fed the B2D-R
    ControlNet's residuals from PyTorch, equal to diffusers within the golden tests' f32 tolerance (normalised
    MSE 1e-5). (A whole engine frame against frame.render_frame needs the engine's seeded noise and projected
    inputs on the Python side: not done here; the validation grid of run A renders frames in PyTorch.)"""
    from safetensors.torch import load_file, save_file

    from b2dr_ref.package import load_package
    from b2dr_ref.training.sd15 import PROMPT, camera_prompt, encode_prompts

    out, _ = run_b
    model = tmp_path / "model"
    r = common.export_package(out, str(model), dtype="f32")
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
