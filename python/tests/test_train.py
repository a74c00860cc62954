"""Smoke tests of the training recipe (b2dr_ref.train, b2dr_ref.vae_train) on the synthetic source, test config."""

import csv
import json
import math
import os

import numpy as np
import pytest
import torch

from b2dr_ref import nano, pe
from b2dr_ref import train as T
from b2dr_ref import vae_train as V

COMMON = ["--config", "test", "--threads", "1", "--log-every", "1000"]


def read_log(run):
    with open(os.path.join(run, "log.csv")) as f:
        return [float(r["loss"]) for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def vae_run(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("vae"))
    losses = V.main(["--data", "synthetic:4", "--out", out, "--steps", "20", "--batch", "2", "--lr", "2e-3",
                     "--warmup", "2", "--fixed-batch", "--ckpt-every", "1000"] + COMMON)
    return out, losses


def test_vae_stage_overfits(vae_run):
    out, losses = vae_run
    assert all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    with open(os.path.join(out, "vae", "config.json")) as f:
        cfg = json.load(f)
    assert len(cfg["block_out_channels"]) == 4 and cfg["latent_channels"] == 4
    assert cfg["scaling_factor"] > 0
    # the saved VAE is centred (vae_train.centre_latents): its latent means are zero-mean, unit-std per channel on
    # the measured images, and the scaling factor (measured after centring) is then about 1
    from b2dr_ref.train import load_vae

    vae = load_vae(os.path.join(out, "vae"))
    src = T.open_source("synthetic:4", nano.get_config("test")["render_size"])
    mu, sd = V.latent_channel_stats(vae, src, "cpu")
    assert mu.abs().max() < 1e-4 and (sd - 1).abs().max() < 1e-4, (mu, sd)
    assert abs(cfg["scaling_factor"] - 1.0) < 1e-2    # pooled vs per-channel std estimators differ by O(1/n)


def test_centre_latents_keeps_the_function():
    """Folding the channel statistics into quant_conv / post_quant_conv changes the latent space, not the function:
    decode(mean(x)) is unchanged, the latent means become (mean - mu) / sigma, the posterior std std / sigma."""
    vae = V.build_vae(nano.get_config("test"), seed=3).eval()
    # a VAE whose latents have large channel offsets, as the trained one had
    with torch.no_grad():
        vae.quant_conv.bias[:4] += torch.tensor([2.5, -1.0, 4.0, 0.5])
    src = T.open_source("synthetic:5", nano.get_config("test")["render_size"])
    x = V.images(src, [0, 1, 2, 3, 4], "cpu")
    with torch.no_grad():
        before = vae.encode(x).latent_dist
        rec_before = vae.decode(before.mean).sample
        mu, sigma = V.centre_latents(vae, src, "cpu")
        after = vae.encode(x).latent_dist
        rec_after = vae.decode(after.mean).sample
    assert abs(float(mu[2]) - float(before.mean[:, 2].mean())) < 1e-4 and float(mu[2]) > 3.0
    torch.testing.assert_close(after.mean, (before.mean - mu.float()[None, :, None, None])
                               / sigma.float()[None, :, None, None], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(after.std, before.std / sigma.float()[None, :, None, None], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(rec_after, rec_before, rtol=1e-4, atol=1e-4)
    m = after.mean.transpose(0, 1).reshape(4, -1)
    assert m.mean(1).abs().max() < 1e-4 and (m.std(1) - 1).abs().max() < 1e-4


def test_v_loss_weight_is_the_v_prediction_loss():
    """eps MSE x (1 + 1/SNR) == ||v - v_hat||^2 with v_hat from the predicted epsilon (train.loss_weight 'v')."""
    g = torch.Generator().manual_seed(0)
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float64)
    t = torch.tensor([0, 10, 300, 700, 999])
    a = abar[t].reshape(-1, 1, 1, 1)
    x0, eps = torch.randn((5, 4, 3, 3), generator=g, dtype=torch.float64), torch.randn((5, 4, 3, 3), generator=g,
                                                                                      dtype=torch.float64)
    eps_hat = eps + 0.1 * torch.randn((5, 4, 3, 3), generator=g, dtype=torch.float64)
    x_t = a.sqrt() * x0 + (1 - a).sqrt() * eps
    x0_hat = (x_t - (1 - a).sqrt() * eps_hat) / a.sqrt()
    v, v_hat = a.sqrt() * eps - (1 - a).sqrt() * x0, a.sqrt() * eps_hat - (1 - a).sqrt() * x0_hat
    w = T.loss_weight("v", abar[t])
    torch.testing.assert_close(w * ((eps - eps_hat) ** 2).mean((1, 2, 3)), ((v - v_hat) ** 2).mean((1, 2, 3)))
    assert torch.equal(T.loss_weight("eps", abar[t]), torch.ones(5, dtype=torch.float64))
    assert float(T.loss_weight("v", abar[t], max_weight=50.0).max()) == 50.0
    ms = T.loss_weight("min-snr", abar[t])
    assert float(ms[0]) < 0.1 and float(ms[-1]) == 1.0
    with pytest.raises(ValueError):
        T.loss_weight("x0", abar[t])


def test_mask_packing_round_trips():
    m = (np.random.default_rng(0).random((15, 7, 9)) < 0.4).astype(np.uint8)
    p = T.pack_masks(m)
    assert p.dtype == torch.int16 and tuple(p.shape) == (7, 9)
    assert np.array_equal(T.unpack_masks(p).numpy(), m)


def diffusion(vae_dir, out, *extra):
    return T.main(["--data", "synthetic:6", "--vae", vae_dir, "--out", out, "--batch", "3", "--warmup", "2",
                   "--ckpt-every", "1000"] + COMMON + list(extra))


def test_v_prediction_target_and_export(vae_run, tmp_path):
    """--prediction v_prediction: the loss is the MSE to v = sqrt(abar) eps - sqrt(1 - abar) x_0 (checked against
    the epsilon loss with the 'v' weight on the same draws: the two are the same objective in different
    parameterisations only when the model's output is converted, so here the target itself is checked), it
    trains, and the export says prediction_type v_prediction; the double weighting is refused."""
    gen_state = torch.Generator().manual_seed(5).get_state()
    b = dict(x0=torch.randn(3, 4, 7, 13))
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)

    class Zero(torch.nn.Module):      # a model that predicts 0: its loss is the target's mean square
        def forward(self, x, *a, **k):
            return type("O", (), {"sample": torch.zeros_like(x)})()

    g = torch.Generator()
    g.set_state(gen_state)
    t = torch.randint(0, 1000, (3,), generator=g)
    eps = torch.randn(b["x0"].shape, generator=g)
    a = abar[t].reshape(3, 1, 1, 1)
    v = a.sqrt() * eps - (1 - a).sqrt() * b["x0"]

    class NoCn:
        config = type("C", (), {"prev_noise_max": 400, "ref_dropout": 0.0})()

        def __call__(self, *a, **k):
            return None, None

    b.update(z_prev=torch.zeros(3, 4, 7, 13), masks=None, cams=torch.zeros(3, dtype=torch.int64))
    g.set_state(gen_state)
    lv = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.0, ref_dropout=1.0,
                          prediction="v_prediction")
    torch.testing.assert_close(lv, (v ** 2).mean())
    g.set_state(gen_state)
    le = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.0, ref_dropout=1.0)
    torch.testing.assert_close(le, (eps ** 2).mean())
    # --object-weight: the latent cells over an object weigh 1 + w (latent 7 x 13 <- image 56 x 104)
    masks = torch.zeros(3, 15, 56, 104)
    masks[1, 0, 8:16, 16:24] = 1                       # one car filling latent cell (1, 2) of sample 1
    b["masks"] = masks
    g.set_state(gen_state)
    lo = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.0, ref_dropout=1.0,
                          prediction="v_prediction", object_weight=3.0)
    w = torch.ones(3, 1, 7, 13)
    w[1, 0, 1, 2] = 4.0
    torch.testing.assert_close(lo, (w * v ** 2).mean())
    # --marking-weight: a lane-divider pixel adds its weight to its cell, on top of the object's
    masks[2, 13, 50, 100] = 1                          # latent cell (6, 12) of sample 2
    masks[1, 13, 9, 17] = 1                            # the car's cell (1, 2) of sample 1 too
    g.set_state(gen_state)
    lm = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.0, ref_dropout=1.0,
                          prediction="v_prediction", object_weight=3.0, marking_weight=2.0)
    w[1, 0, 1, 2] = 6.0
    w[2, 0, 6, 12] = 3.0
    torch.testing.assert_close(lm, (w * v ** 2).mean())
    b["masks"] = None

    run = str(tmp_path / "run")
    losses = diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "3", "--prediction", "v_prediction",
                       "--object-weight", "2", "--marking-weight", "2")
    assert all(np.isfinite(losses))
    T.main(["export", "--run", run, "--out", str(tmp_path / "model")])
    with open(tmp_path / "model" / "b2dr.json") as f:
        assert json.load(f)["prediction_type"] == "v_prediction"
    with pytest.raises(SystemExit, match="twice"):
        diffusion(os.path.join(vae_run[0], "vae"), str(tmp_path / "r2"), "--steps", "1", "--prediction",
                  "v_prediction", "--loss-weight", "v")
    with pytest.raises(SystemExit, match="predicts v_prediction"):
        diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "4", "--resume")


def test_diffusion_stage_overfits(vae_run, tmp_path):
    losses = diffusion(os.path.join(vae_run[0], "vae"), str(tmp_path / "run"), "--steps", "20", "--lr", "2e-3",
                       "--fixed-batch")
    assert len(losses) == 20 and all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.85 * np.mean(losses[:5])
    assert read_log(str(tmp_path / "run")) == pytest.approx(losses, abs=1e-6)


def test_resume_continues_exactly(vae_run, tmp_path):
    vae = os.path.join(vae_run[0], "vae")
    full = diffusion(vae, str(tmp_path / "a"), "--steps", "4", "--ema", "0.9")
    first = diffusion(vae, str(tmp_path / "b"), "--steps", "4", "--stop-after", "2", "--ema", "0.9")
    rest = diffusion(vae, str(tmp_path / "b"), "--steps", "4", "--resume", "--ema", "0.9")
    assert len(first) == 2 and len(rest) == 2
    assert first + rest == pytest.approx(full, rel=1e-6, abs=1e-7)
    assert read_log(str(tmp_path / "b")) == pytest.approx(full, rel=1e-6, abs=1e-6)
    a = torch.load(str(tmp_path / "a" / T.CKPT), weights_only=False)
    b = torch.load(str(tmp_path / "b" / T.CKPT), weights_only=False)
    assert a["step"] == b["step"] == 4
    for k in a["controlnet"]:
        torch.testing.assert_close(a["controlnet"][k], b["controlnet"][k], rtol=1e-5, atol=1e-6)


def read_lrs(run):
    with open(os.path.join(run, "log.csv")) as f:
        return [float(r["lr"]) for r in csv.DictReader(f)]


def test_end_at_shortens_a_resumed_schedule(vae_run, tmp_path):
    """--end-at on a resume: the lr goes on from where the run's own schedule was (no jump) and falls along a
    cosine to 0 at the new end; a later resume keeps that schedule; without --resume, or at/behind the current
    step, it is refused."""
    vae = os.path.join(vae_run[0], "vae")
    run = str(tmp_path / "r")
    diffusion(vae, run, "--steps", "20", "--stop-after", "4")
    orig = T.lr_lambda(2, 20)
    diffusion(vae, run, "--steps", "20", "--resume", "--end-at", "10", "--stop-after", "3")
    assert torch.load(os.path.join(run, T.CKPT), weights_only=False)["anneal"] == [4, 10, pytest.approx(orig(4))]
    diffusion(vae, run, "--steps", "20", "--resume", "--end-at", "10")
    lrs = read_lrs(run)
    assert len(lrs) == 10
    base = 1e-4
    # log row i is step i + 1; its lr is the one the scheduler set for the next step (get_last_lr after step())
    want = [base * orig(s) for s in range(1, 5)] + \
        [base * orig(4) * 0.5 * (1 + math.cos(math.pi * (s - 4) / 6)) for s in range(5, 11)]
    assert lrs == pytest.approx(want, rel=1e-3, abs=1e-12)
    assert lrs[-1] == 0.0
    with pytest.raises(SystemExit, match="--end-at"):
        diffusion(vae, str(tmp_path / "new"), "--steps", "20", "--end-at", "10")
    with pytest.raises(SystemExit, match="already at step 10"):
        diffusion(vae, run, "--steps", "20", "--resume", "--end-at", "8")


def test_latents_file_spares_a_resume_the_encoding(vae_run, tmp_path, monkeypatch, capsys):
    """RUN/latents.pt keeps the VAE latents between runs: what it holds equals a fresh encode, a resume that reads
    it encodes fewer images and gives the same losses as one that encodes everything again (--no-latents-file),
    and a file made with another key (other data / VAE / blur) is ignored with a message."""
    import shutil

    vae = os.path.join(vae_run[0], "vae")
    run, run2 = str(tmp_path / "r"), str(tmp_path / "r2")
    diffusion(vae, run, "--steps", "4", "--stop-after", "2")
    f = os.path.join(run, T.LATENTS_FILE)
    d = torch.load(f, weights_only=True)
    assert 0 < len(d["index"]) <= 6 and d["x0"].shape[1:] == (4, 7, 13) and d["z_refs"].shape[1:3] == (2, 4)
    src = T.open_source("synthetic:6", nano.TEST["render_size"])
    _, cn = T.build_diffusion_models(nano.TEST)
    fresh = T.Batcher(src, T.load_vae(vae), cn, "cpu")._prepare([int(d["index"][0])])[0]
    for a, b in zip(fresh[:3], (d["x0"][0], d["z_prev"][0], d["z_refs"][0])):
        assert torch.equal(a, b)
    shutil.copytree(run, run2)
    os.remove(os.path.join(run2, T.LATENTS_FILE))
    encoded = []
    orig = T.Batcher._encode
    monkeypatch.setattr(T.Batcher, "_encode", lambda self, imgs, *a: encoded.append(len(imgs)) or orig(self, imgs, *a))
    rest = diffusion(vae, run, "--steps", "4", "--resume")
    with_file = sum(encoded)
    encoded.clear()
    rest2 = diffusion(vae, run2, "--steps", "4", "--resume", "--no-latents-file")
    assert rest == rest2 and len(rest) == 2
    assert with_file < sum(encoded)
    assert T.latent_cache_key("synthetic:6", vae, 1.0) != T.latent_cache_key("synthetic:6", vae, 2.0)
    assert T.latent_cache_key("synthetic:6", vae, 1.0) != T.latent_cache_key("synthetic:7", vae, 1.0)
    # the key follows the VAE's weights and config, not a README beside them (models/b2dr-z16-vae has one)
    import shutil
    vae2 = str(tmp_path / "vae_copy")
    shutil.copytree(vae, vae2)
    with open(os.path.join(vae2, "README.md"), "w") as fh:
        fh.write("notes\n")
    assert T.latent_cache_key("synthetic:6", vae2, 1.0) == T.latent_cache_key("synthetic:6", vae, 1.0)
    w = [n for n in os.listdir(vae2) if n.endswith(".safetensors")][0]
    with open(os.path.join(vae2, w), "ab") as fh:
        fh.write(b"\0")
    assert T.latent_cache_key("synthetic:6", vae2, 1.0) != T.latent_cache_key("synthetic:6", vae, 1.0)
    capsys.readouterr()
    b = T.Batcher(src, T.load_vae(vae), cn, "cpu", latents=(f, "another key"))
    assert not b.disk and "encoding again" in capsys.readouterr().out


def test_precache_encodes_every_sample_once_and_changes_no_loss(vae_run, tmp_path, monkeypatch, capsys):
    """--precache encodes each of the 6 samples exactly once (4 images each: target, previous, two references)
    before the first step, writes them all to the latents file, prints progress, and trains to the same losses
    as lazy encoding."""
    vae = os.path.join(vae_run[0], "vae")
    lazy = diffusion(vae, str(tmp_path / "a"), "--steps", "3", "--no-latents-file")
    encoded = []
    orig = T.Batcher._encode
    monkeypatch.setattr(T.Batcher, "_encode", lambda self, imgs, *a: encoded.append(len(imgs)) or orig(self, imgs, *a))
    capsys.readouterr()
    pre = diffusion(vae, str(tmp_path / "b"), "--steps", "3", "--precache")
    assert pre == lazy
    assert sum(encoded) == 6 * 4
    assert "precache: 6 / 6 samples" in capsys.readouterr().out
    d = torch.load(os.path.join(str(tmp_path / "b"), T.LATENTS_FILE), weights_only=True)
    assert sorted(d["index"].tolist()) == list(range(6))


def test_time_limit_stops_with_a_checkpoint(vae_run, tmp_path, capsys):
    """--time-limit: once the steps have run that long the run stops with a checkpoint at that step (here after
    the first), says the schedule did not end, and --resume continues it."""
    vae = os.path.join(vae_run[0], "vae")
    run = str(tmp_path / "r")
    first = diffusion(vae, run, "--steps", "4", "--time-limit", "1e-9")
    assert len(first) == 1
    assert "--time-limit 1e-09 s reached at step 1 of 4" in capsys.readouterr().out
    ck = torch.load(os.path.join(run, T.CKPT), map_location="cpu", weights_only=False)
    assert ck["step"] == 1
    full = diffusion(vae, str(tmp_path / "full"), "--steps", "4")
    rest = diffusion(vae, run, "--steps", "4", "--resume")
    assert first + rest == pytest.approx(full, rel=1e-6, abs=1e-7)


def test_vae_resume_continues_exactly(tmp_path):
    args = ["--data", "synthetic:4", "--steps", "4", "--batch", "2", "--warmup", "1", "--ckpt-every", "1000",
            "--crop", "32x48"] + COMMON
    full = V.main(args + ["--out", str(tmp_path / "a")])
    first = V.main(args + ["--out", str(tmp_path / "b"), "--stop-after", "2"])
    rest = V.main(args + ["--out", str(tmp_path / "b"), "--resume"])
    assert first + rest == pytest.approx(full, rel=1e-6, abs=1e-7)
    # the checkpoint keeps the loss flags: a resume with another objective is refused, naming the flag
    with pytest.raises(SystemExit, match=r"--recon-loss l2 \(the run: l1\)"):
        V.main(args + ["--out", str(tmp_path / "b"), "--resume", "--steps", "6", "--recon-loss", "l2"])
    with pytest.raises(SystemExit, match=r"--se-weight 1.0 \(the run: 0.0\)"):
        V.main(args + ["--out", str(tmp_path / "b"), "--resume", "--steps", "6", "--se-weight", "1"])
    # a checkpoint written before --se-weight existed (no such key) resumes as a run without it
    ck_path = tmp_path / "b" / "checkpoint.pt"
    ck = torch.load(ck_path, weights_only=False)
    del ck["loss"]["se_weight"]
    torch.save(ck, ck_path)
    assert len(V.main(args + ["--out", str(tmp_path / "b"), "--resume", "--steps", "5"])) == 1


def test_export_round_trip(vae_run, tmp_path):
    from b2dr_ref.controlnet import B2DRControlNetModel
    from b2dr_ref.package import load_package

    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "2")
    model = str(tmp_path / "model")
    size = T.main(["export", "--run", run, "--out", model, "--dtype", "f16"])
    assert size < 30e6
    pkg = load_package(model)
    assert pkg.meta["dtype"] == "f16" and pkg.meta["sampler"] == "unipc" and pkg.meta["steps"] == 20
    assert pkg.meta["ref_guidance"] == 2.0 and pkg.meta["render_size"] == nano.TEST["render_size"]
    assert pkg.meta["cameras"] == ["CAM_FRONT", "CAM_BACK"]
    assert isinstance(pkg.controlnet, B2DRControlNetModel)
    with open(os.path.join(model, "controlnet", "config.json")) as f:
        cfg = json.load(f)
    assert cfg["_class_name"] == "B2DRControlNetModel"
    B2DRControlNetModel.from_config(cfg)                      # parses strictly
    assert tuple(pkg.context.shape) == (2, 77, nano.TEST["context_dim"])
    ck = torch.load(os.path.join(run, T.CKPT), weights_only=False)
    for k, v in ck["controlnet"].items():
        torch.testing.assert_close(pkg.controlnet.state_dict()[k], v.half().float())
    torch.testing.assert_close(pkg.context, ck["context"].half().float())
    # the package's sampler steps are an export choice; below 1 is refused
    one = str(tmp_path / "one")
    T.main(["export", "--run", run, "--out", one, "--sampler-steps", "1"])
    assert load_package(one).meta["steps"] == 1
    with pytest.raises(SystemExit, match="--sampler-steps 0"):
        T.main(["export", "--run", run, "--out", str(tmp_path / "zero"), "--sampler-steps", "0"])
    assert not os.path.exists(str(tmp_path / "zero"))
    # the previous frame's source is the run's ("previous") unless export says; a reference needs a warping run
    assert cfg["prev_source"] == "previous"
    for src in ("reference", "composite"):
        with pytest.raises(SystemExit, match=f"--prev-source {src}: the run does not warp"):
            T.main(["export", "--run", run, "--out", str(tmp_path / src), "--prev-source", src])
    ck["cfg"]["controlnet"]["prev_warp_max_depth"] = 30.0
    torch.save(ck, os.path.join(run, T.CKPT))
    for src in ("reference", "composite"):
        T.main(["export", "--run", run, "--out", str(tmp_path / src), "--prev-source", src])
        assert load_package(str(tmp_path / src)).controlnet.config.prev_source == src


def test_pe_vectorised_matches_pe_py():
    cfg = pe.PeConfig(depth_num=4)
    s = T.SyntheticSource(n=1, render_size=(56, 104))[0]
    m = pe.cam2cur(s.cam2ego, s.ref_ego2global[0], s.ego2global)
    for grid in (pe.PixelGrid.CENTRE, pe.PixelGrid.PETR_CORNER):
        cfg.grid = grid
        ref = pe.position_encoding(s.k, 104, 56, m, 4, 7, cfg)
        np.testing.assert_allclose(T.position_encoding_np(s.k, 104, 56, m, 4, 7, cfg), ref, rtol=1e-5, atol=1e-5)


def test_dataset_adapter():
    class FakeSet:
        cameras = ["CAM_FRONT", "CAM_BACK", "CAM_LEFT"]
        mask_channels = list(T.MASK_CHANNELS)
        height, width = 16, 24

        def __len__(self):
            return 2

        def __getitem__(self, f):
            c = len(self.cameras)
            r = np.random.default_rng(f)
            return {"target": r.integers(0, 255, (c, 3, 16, 24), dtype=np.uint8),
                    "prev": r.integers(0, 255, (c, 3, 16, 24), dtype=np.uint8),
                    "ref": r.integers(0, 255, (c, 2, 3, 16, 24), dtype=np.uint8),
                    "masks": r.integers(0, 2, (c, 15, 16, 24), dtype=np.uint8),
                    "intrinsics": np.tile(np.eye(3), (c, 1, 1)) * (f + 1), "cam2ego": np.tile(np.eye(4), (c, 1, 1)),
                    "ego2global": np.tile(np.eye(4), (c, 1, 1)), "prev_ego2global": np.tile(np.eye(4), (c, 1, 1)),
                    "ref_ego2global": np.tile(np.eye(4), (c, 2, 1, 1)), "cameras": self.cameras}

    fake = FakeSet()
    src = T.DatasetSource(ds=fake)
    assert len(src) == 6 and src.render_size == (16, 24) and src.cameras == fake.cameras
    s = src[4]                                                   # frame 1, camera 1
    assert s.camera == "CAM_BACK" and s.refs.shape == (2, 3, 16, 24) and s.masks.shape == (15, 16, 24)
    np.testing.assert_array_equal(s.target, fake[1]["target"][1])
    assert s.k[0, 0] == 2.0


def test_nano_config_is_engine_shaped():
    from diffusers import AutoencoderKL, UNet2DConditionModel

    from b2dr_ref.controlnet import B2DRControlNetModel

    cfg = nano.get_config("nano")
    nano.check_config(cfg)
    assert cfg["render_size"] == [112, 200]
    cn = B2DRControlNetModel.from_config(cfg["controlnet"])
    assert list(cn.config.ref_attn) == ["down.0", "down.1", "down.2", "down.3", "mid"]
    unet = UNet2DConditionModel(**cfg["unet"])
    vae = AutoencoderKL(**cfg["vae"])
    heads = cfg["unet"]["attention_head_dim"]
    for c, h in zip(cfg["unet"]["block_out_channels"], heads):
        assert c % h == 0 and (c // h) % 4 == 0
    n = sum(p.numel() for m in (unet, cn, vae) for p in m.parameters())
    assert n * 2 < 30e6                                          # the f16 package stays small
    with torch.no_grad():
        z = vae.encode(torch.zeros(1, 3, 112, 200)).latent_dist.mean
    assert tuple(z.shape) == (1, 4, 14, 25)


def test_init_from_package_starts_from_its_weights(vae_run, tmp_path):
    from b2dr_ref.package import load_package

    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "2")
    model = str(tmp_path / "model")
    T.main(["export", "--run", run, "--out", model, "--dtype", "f16"])
    # lr 0: one step leaves the weights where --init-from put them (the package's, f16 widened to f32)
    cont = str(tmp_path / "cont")
    T.main(["--data", "synthetic:4", "--out", cont, "--steps", "1", "--batch", "2", "--lr", "0",
            "--init-from", model] + COMMON)
    pkg = load_package(model)
    ck = torch.load(os.path.join(cont, T.CKPT), weights_only=False)
    assert ck["vae_path"] == os.path.abspath(os.path.join(model, "vae"))
    for k, v in pkg.controlnet.state_dict().items():
        torch.testing.assert_close(ck["controlnet"][k], v, rtol=0, atol=0)
    for k, v in pkg.unet.state_dict().items():
        torch.testing.assert_close(ck["unet"][k], v, rtol=0, atol=0)
    torch.testing.assert_close(ck["context"], pkg.context, rtol=0, atol=0)


def test_init_context_from_fills_the_cameras_the_package_lacks(vae_run, tmp_path):
    """A one-camera package (CAM_FRONT) starts a run on two-camera data only with --init-context-from: CAM_FRONT's
    row from --init-from, CAM_BACK's from the other package; without it, or without --init-from, a clear exit."""
    from b2dr_ref.package import load_package, save_package

    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "1")
    both = str(tmp_path / "both")
    T.main(["export", "--run", run, "--out", both, "--dtype", "f32"])
    pkg = load_package(both)
    assert list(pkg.meta["cameras"]) == ["CAM_FRONT", "CAM_BACK"]
    front = str(tmp_path / "front")
    meta = dict(pkg.meta, cameras=["CAM_FRONT"])
    save_package(front, pkg.unet, pkg.controlnet, pkg.vae, pkg.context[:1] + 1.0, meta)   # its own row
    args = ["--data", "synthetic:4", "--steps", "1", "--batch", "2", "--lr", "0"] + COMMON
    with pytest.raises(SystemExit, match="CAM_BACK.*--init-context-from"):
        T.main(args + ["--out", str(tmp_path / "a"), "--init-from", front])
    with pytest.raises(SystemExit, match="give --init-from"):
        T.main(args + ["--out", str(tmp_path / "b"), "--vae", os.path.join(vae_run[0], "vae"),
                       "--init-context-from", both])
    cont = str(tmp_path / "c")
    T.main(args + ["--out", cont, "--init-from", front, "--init-context-from", both])
    ctx = torch.load(os.path.join(cont, T.CKPT), weights_only=False)["context"]
    torch.testing.assert_close(ctx[0], pkg.context[0] + 1.0, rtol=0, atol=0)    # --init-from's CAM_FRONT
    torch.testing.assert_close(ctx[1], pkg.context[1], rtol=0, atol=0)          # --init-context-from's CAM_BACK


def test_keep_every_keeps_steps_that_export_step_packages(vae_run, tmp_path):
    """--keep-every N keeps every N-th step's weights in RUN/keep/; export --step N packages them (the last kept
    step's weights are the final checkpoint's, an earlier one's differ); a step not kept is a clear exit."""
    from b2dr_ref.package import load_package

    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "4", "--keep-every", "2")
    assert sorted(os.listdir(os.path.join(run, "keep"))) == ["step_0000002.pt", "step_0000004.pt"]
    last = torch.load(os.path.join(run, T.CKPT), weights_only=False)
    for step in (2, 4):
        out = str(tmp_path / f"m{step}")
        T.main(["export", "--run", run, "--out", out, "--dtype", "f32", "--step", str(step)])
        sd = load_package(out).unet.state_dict()
        same = all(torch.equal(v, last["unet"][k]) for k, v in sd.items())
        assert same == (step == 4), step
    with pytest.raises(SystemExit, match="kept: step_0000002.pt, step_0000004.pt"):
        T.main(["export", "--run", run, "--out", str(tmp_path / "m3"), "--step", "3"])


def test_object_loss_weight_marks_the_object_cells():
    """train.object_loss_weight: 1 + w on the latent cells whose 8x8 image cell holds any object-class pixel
    (channels car .. bicycle), 1 elsewhere (road, lanes and the other map channels never count)."""
    m = torch.zeros((2, 15, 16, 24))
    m[0, 0, 9, 17] = 1          # one car pixel -> latent cell (1, 2)
    m[1, 5, 0:3, 0:2] = 1       # pedestrian -> cell (0, 0)
    m[:, 10] = 1                # drivable area everywhere: no weight
    w = T.object_loss_weight(m, (2, 3), 4.0)
    want = torch.ones((2, 1, 2, 3))
    want[0, 0, 1, 2] = 5.0
    want[1, 0, 0, 0] = 5.0
    torch.testing.assert_close(w, want)


def test_layout_loss_weight_adds_object_and_marking_cells():
    """train.layout_loss_weight (--object-weight, --marking-weight): 1 + wo on cells holding an object pixel, + wm on
    cells holding a crosswalk or lane-divider pixel (both in one cell add up); lane area and road boundary never
    count; wm = 0 is object_loss_weight."""
    m = torch.zeros((1, 15, 16, 24))
    m[0, 13, 3, 5] = 1          # one lane-divider pixel -> latent cell (0, 0)
    m[0, 12, 12, 20] = 1        # crosswalk -> cell (1, 2)
    m[0, 0, 15, 23] = 1         # car in the same cell (1, 2)
    m[0, 11] = 1                # lane area everywhere: no weight
    m[0, 14, 9, 9] = 1          # road boundary -> cell (1, 1): no weight
    w = T.layout_loss_weight(m, (2, 3), 4.0, 2.0)
    want = torch.ones((1, 1, 2, 3))
    want[0, 0, 0, 0] = 3.0
    want[0, 0, 1, 2] = 7.0
    torch.testing.assert_close(w, want)
    torch.testing.assert_close(T.layout_loss_weight(m, (2, 3), 4.0, 0.0), T.object_loss_weight(m, (2, 3), 4.0))


def test_vae_object_weight_and_init_from(vae_run, tmp_path):
    """--init-from starts from a VAE folder (the first loss equals the trained VAE's, not a fresh one's);
    --object-weight weighs object pixels up (logged L1 stays the plain one); a wrong architecture is refused."""
    out, losses = vae_run
    args = ["--data", "synthetic:4", "--steps", "2", "--batch", "2", "--lr", "1e-9", "--warmup", "1", "--fixed-batch",
            "--ckpt-every", "1000"] + COMMON
    warm = V.main(args + ["--out", str(tmp_path / "a"), "--init-from", os.path.join(out, "vae")])
    cold = V.main(args + ["--out", str(tmp_path / "b")])
    assert warm[0] < 0.8 * cold[0], (warm, cold)
    weighted = V.main(args + ["--out", str(tmp_path / "c"), "--init-from", os.path.join(out, "vae"),
                              "--object-weight", "4"])
    assert weighted[0] > warm[0]
    with open(tmp_path / "c" / "log.csv") as f:
        l1 = [float(r["l1"]) for r in csv.DictReader(f)]
    assert abs(l1[0] - warm[0]) < 0.05 * warm[0]     # the logged L1 is unweighted (KL term ~1e-6)
    with pytest.raises(SystemExit, match="blocks differ"):
        V.main(["--data", "synthetic:4", "--steps", "1", "--batch", "2", "--out", str(tmp_path / "d"),
                "--config", "nano", "--threads", "1", "--init-from", os.path.join(out, "vae")])


def test_vae_decoder_only_keeps_the_latent_space(vae_run, tmp_path):
    """--decoder-only: the encoder side (encoder, quant_conv) and the scaling factor come out exactly as the
    --init-from VAE's (no gradient, no re-centring), so a denoiser trained on its latents stays valid; the decoder
    trains (its loss falls on a fixed batch); a resume continues exactly and keeps the factor; no init, --se-weight
    and a mismatched latent width are refused."""
    from safetensors.torch import load_file

    from b2dr_ref.train import load_vae

    init = os.path.join(vae_run[0], "vae")
    args = ["--data", "synthetic:4", "--batch", "2", "--lr", "2e-3", "--warmup", "1", "--fixed-batch",
            "--ckpt-every", "1000", "--decoder-only", "--init-from", init] + COMMON
    losses = V.main(args + ["--out", str(tmp_path / "a"), "--steps", "8"])
    assert np.mean(losses[-2:]) < 0.9 * np.mean(losses[:2]), losses
    before = load_file(os.path.join(init, "diffusion_pytorch_model.safetensors"))
    after = load_file(str(tmp_path / "a" / "vae" / "diffusion_pytorch_model.safetensors"))
    enc = [k for k in before if k.startswith(("encoder.", "quant_conv."))]
    dec = [k for k in before if k.startswith(("decoder.", "post_quant_conv."))]
    assert enc and dec and len(enc) + len(dec) == len(before)
    for k in enc:
        torch.testing.assert_close(after[k], before[k], rtol=0, atol=0)
    assert any(not torch.equal(after[k], before[k]) for k in dec)
    assert load_vae(str(tmp_path / "a" / "vae")).config.scaling_factor == load_vae(init).config.scaling_factor
    # resume: the same losses as one run, the factor kept through the checkpoint
    first = V.main(args + ["--out", str(tmp_path / "b"), "--steps", "8", "--stop-after", "3"])
    rest = V.main(args + ["--out", str(tmp_path / "b"), "--steps", "8", "--resume"])
    assert first + rest == pytest.approx(losses, rel=1e-6, abs=1e-7)
    assert load_vae(str(tmp_path / "b" / "vae")).config.scaling_factor == load_vae(init).config.scaling_factor
    with pytest.raises(SystemExit, match=r"--decoder-only False \(the run: True\)"):
        V.main([a for a in args if a != "--decoder-only"] + ["--out", str(tmp_path / "b"), "--steps", "9",
                                                           "--resume"])
    base = ["--data", "synthetic:4", "--steps", "1", "--batch", "2", "--decoder-only"] + COMMON
    with pytest.raises(SystemExit, match="give it with --init-from"):
        V.main(base + ["--out", str(tmp_path / "c")])
    with pytest.raises(SystemExit, match="--se-weight"):
        V.main(base + ["--out", str(tmp_path / "d"), "--init-from", init, "--se-weight", "1"])
    with pytest.raises(SystemExit, match="latent channels differ"):
        V.main(base[:-len(COMMON)] + ["--config", "test-z8", "--threads", "1", "--out", str(tmp_path / "e"),
                                      "--init-from", init])


def test_more_latent_channels_train_export_and_init(vae_run, tmp_path):
    """The design variant with 8 latent channels (nano.TEST_Z8): the VAE body starts from a 4-channel VAE (the
    latent-facing tensors fresh), the diffusion stage trains on its latents, the package exports and loads with
    UNet in / out 8 and ControlNet in_channels 16, and a 4-channel package initialises everything but those."""
    from b2dr_ref.package import load_package

    vae8 = str(tmp_path / "vae8")
    V.main(["--data", "synthetic:4", "--out", vae8, "--steps", "2", "--batch", "2", "--ckpt-every", "1000",
            "--config", "test-z8", "--init-from", os.path.join(vae_run[0], "vae"), "--marking-weight", "2",
            "--threads", "1", "--log-every", "1000"])
    v = T.load_vae(os.path.join(vae8, "vae"))
    assert v.config.latent_channels == 8
    run = str(tmp_path / "run8")
    losses = T.main(["--data", "synthetic:4", "--vae", os.path.join(vae8, "vae"), "--out", run, "--steps", "2",
                     "--batch", "2", "--config", "test-z8", "--threads", "1", "--log-every", "1000"])
    assert all(np.isfinite(losses))
    model = str(tmp_path / "model8")
    T.main(["export", "--run", run, "--out", model, "--dtype", "f32"])
    pkg = load_package(model)
    assert pkg.unet.config.in_channels == pkg.unet.config.out_channels == 8
    assert pkg.controlnet.config.in_channels == 16 and pkg.controlnet.latent_channels == 8
    assert pkg.controlnet.ref_encoder.conv_in.weight.shape[1] == 8
    # a 4-channel package initialises an 8-channel run: all but the latent-facing tensors
    run4 = str(tmp_path / "run4")
    diffusion(os.path.join(vae_run[0], "vae"), run4, "--steps", "1")
    m4 = str(tmp_path / "m4")
    T.main(["export", "--run", run4, "--out", m4, "--dtype", "f32"])
    cont = str(tmp_path / "cont8")
    T.main(["--data", "synthetic:4", "--vae", os.path.join(vae8, "vae"), "--out", cont, "--steps", "1",
            "--batch", "2", "--lr", "0", "--config", "test-z8", "--init-from", m4, "--threads", "1",
            "--log-every", "1000"])
    p4 = load_package(m4)
    ck = torch.load(os.path.join(cont, T.CKPT), weights_only=False)
    fresh = {"conv_in.weight", "conv_out.weight", "conv_out.bias", "ref_encoder.conv_in.weight"}
    for part, sd in (("unet", p4.unet.state_dict()), ("controlnet", p4.controlnet.state_dict())):
        for k, val in sd.items():
            if ck[part][k].shape != val.shape:
                assert k in fresh, (part, k)
            else:
                torch.testing.assert_close(ck[part][k], val, rtol=0, atol=0)


def test_grad_l1_on_hand_computed_edges():
    """vae_train.grad_l1 (--grad-weight): zero for the image itself and for a uniform colour shift; hand-computed
    values on a one-pixel line blurred over three pixels and moved one pixel; weights take the larger of two
    neighbours."""
    x = torch.zeros(1, 3, 4, 5)
    x[..., :, 2] = 1.0                                        # a vertical line one pixel wide
    assert float(V.grad_l1(x, x)) == 0.0
    assert float(V.grad_l1(x + 0.25, x)) == 0.0                 # 0.25: exact in binary
    blur = torch.zeros_like(x)
    blur[..., :, 1:4] = 1 / 3                                  # the line spread over three pixels
    shifted = torch.roll(x, 1, dims=-1)                      # the line one pixel to the right
    # horizontal differences per row: x (0, 1, -1, 0), blur (1/3, 0, 0, -1/3), |diff| sum 1/3 + 1 + 1 + 1/3
    # = 8/3 a row, 4 rows, 3 channels; vertical differences all zero
    assert float(V.grad_l1(blur, x)) == pytest.approx(3 * 4 * 8 / 3)
    # shifted: x (0, 1, -1, 0) vs (0, 0, 1, -1): 0 + 1 + 2 + 1 = 4 a row -> 48
    assert float(V.grad_l1(shifted, x)) == pytest.approx(3 * 4 * 4)
    w = torch.ones(1, 1, 4, 5)
    w[..., 0, 2] = 5.0                                        # one heavy pixel on the line, top row
    # top row's horizontal pairs (1,2) and (2,3) take weight 5: the blur's row costs 1/3 + 5 + 5 + 1/3; its
    # vertical pairs (0,1) at column 2 take 5 too but their differences are zero
    assert float(V.grad_l1(blur, x, w)) == pytest.approx(3 * (3 * 8 / 3 + (2 / 3 + 10)))


def test_recon_loss_l2_is_the_squared_error():
    """vae_loss(recon="l2"): the weighted squared error per pixel (the decoded sample drawn with the same
    generator state as the L1 loss), the logged L1 unchanged; an unknown loss is refused."""
    vae = V.build_vae(nano.get_config("test"), 0).eval()
    x = torch.rand(2, 3, 16, 24) * 2 - 1
    w = torch.ones(2, 1, 16, 24)
    w[:, :, 3:6] = 5.0
    loss1, l1a, _ = V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, w)
    loss2, l1b, _ = V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, w, recon="l2")
    gen = torch.Generator().manual_seed(3)
    post = vae.encode(x).latent_dist
    rec = vae.decode(post.mean + post.std * torch.randn(post.mean.shape, generator=gen)).sample
    n = 3 * 16 * 24
    torch.testing.assert_close(loss1, ((rec - x).abs() * w).flatten(1).sum(1).mean() / n)
    torch.testing.assert_close(loss2, ((rec - x).square() * w).flatten(1).sum(1).mean() / n)
    torch.testing.assert_close(l1a, l1b)
    with pytest.raises(ValueError, match="l1 or l2"):
        V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, recon="huber")


def test_scale_equivariance_term():
    """vae_loss(se_weight=w) adds w times the squared error per pixel value of the half-size latent's decode
    against the half-size image (the same antialiased bilinear filter on both, sizes from the latent's halves);
    w = 0 leaves the loss as it was (a resume of a run that predates the flag: test_vae_resume_continues_exactly)."""
    vae = V.build_vae(nano.get_config("test"), 0).eval()
    x = torch.rand(2, 3, 24, 40) * 2 - 1
    base, _, _ = V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, recon="l2")
    off, _, _ = V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, recon="l2", se_weight=0.0)
    on, _, _ = V.vae_loss(vae, x, torch.Generator().manual_seed(3), 0.0, recon="l2", se_weight=0.5)
    torch.testing.assert_close(base, off)
    gen = torch.Generator().manual_seed(3)
    post = vae.encode(x).latent_dist
    z = post.mean + post.std * torch.randn(post.mean.shape, generator=gen)
    h, w = z.shape[-2] // 2, z.shape[-1] // 2
    f = x.shape[-1] // z.shape[-1]
    small = vae.decode(torch.nn.functional.interpolate(z, size=(h, w), mode="bilinear", antialias=True)).sample
    assert small.shape[-2:] == (f * h, f * w)
    target = torch.nn.functional.interpolate(x, size=(f * h, f * w), mode="bilinear", antialias=True)
    torch.testing.assert_close(on, base + 0.5 * (small - target).square().mean())
    assert float(on.detach()) > float(base.detach())


class _ZeroUnet(torch.nn.Module):      # predicts 0 (epsilon or v)
    def forward(self, x, *a, **k):
        return type("O", (), {"sample": torch.zeros_like(x)})()


class _NoControlNet:
    config = type("C", (), {"prev_noise_max": 400, "ref_dropout": 0.0, "prev_noise_level": 200,
                            "prev_blur_sigma": 1.0})()

    def __call__(self, *a, **k):
        return None, None


def test_x0_base_prev_diffuses_the_residual_against_the_previous_latent(vae_run, tmp_path):
    """--x0-base prev: the v target is that of x_0 - z_prev for the rows with a previous frame and of x_0 for the
    rows drawn as 'no previous frame'; the run trains, the export says x0_base prev, a resume with another base
    is refused, and an unknown base is an error."""
    gen_state = torch.Generator().manual_seed(7).get_state()
    B = 4
    b = dict(x0=torch.randn(B, 4, 7, 13), z_prev=torch.randn(B, 4, 7, 13), masks=None,
             cams=torch.zeros(B, dtype=torch.int64))
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)

    Zero, NoCn = _ZeroUnet, _NoControlNet      # predicts 0: the loss is the target's mean square

    g = torch.Generator()
    g.set_state(gen_state)
    d = T.draw_noise(b, g, 400, 0.5, 1.0)
    assert 0 < int(d["noprev"].sum()) < B                 # both kinds of rows in this draw
    a = abar[d["t"]].reshape(B, 1, 1, 1)
    keep = (~d["noprev"]).float().reshape(B, 1, 1, 1)
    v = a.sqrt() * d["eps"] - (1 - a).sqrt() * (b["x0"] - keep * b["z_prev"])
    g.set_state(gen_state)
    lr = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.5, ref_dropout=1.0,
                          prediction="v_prediction", x0_base="prev")
    torch.testing.assert_close(lr, (v ** 2).mean())
    g.set_state(gen_state)
    ln = T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, p_noprev=0.5, ref_dropout=1.0,
                          prediction="v_prediction")
    assert not torch.allclose(ln, lr)                     # the plain loss is another target
    with pytest.raises(ValueError, match="x0_base"):
        T.diffusion_loss(Zero(), NoCn(), torch.zeros(1, 77, 8), b, g, abar, x0_base="next")

    run = str(tmp_path / "run")
    losses = diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "3", "--prediction", "v_prediction",
                       "--x0-base", "prev")
    assert all(np.isfinite(losses))
    T.main(["export", "--run", run, "--out", str(tmp_path / "model")])
    with open(tmp_path / "model" / "b2dr.json") as f:
        assert json.load(f)["x0_base"] == "prev"
    from b2dr_ref.package import load_package

    assert load_package(str(tmp_path / "model")).meta["x0_base"] == "prev"
    with pytest.raises(SystemExit, match="x_0 base is prev"):
        diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "4", "--prediction", "v_prediction", "--resume")
    plain = str(tmp_path / "plain")
    diffusion(os.path.join(vae_run[0], "vae"), plain, "--steps", "1")
    T.main(["export", "--run", plain, "--out", str(tmp_path / "pm")])
    with open(tmp_path / "pm" / "b2dr.json") as f:
        assert "x0_base" not in json.load(f)              # older readers keep reading plain packages


def test_prev_noise_overrides_reach_the_loss_and_the_package(vae_run, tmp_path, monkeypatch):
    """--prev-noise-max / --prev-noise-level replace the design's previous-frame noise levels: the loss draws n
    from 0..max, the exported ControlNet config holds both, a resume with other values and a level outside 0..998
    are refused."""
    drawn = []
    real = T.draw_noise

    def spy(b, gen, prev_noise_max, *a):
        drawn.append(prev_noise_max)
        return real(b, gen, prev_noise_max, *a)

    monkeypatch.setattr(T, "draw_noise", spy)
    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "2", "--prev-noise-max", "30",
              "--prev-noise-level", "20")
    assert drawn == [30, 30]
    T.main(["export", "--run", run, "--out", str(tmp_path / "model")])
    with open(tmp_path / "model" / "controlnet" / "config.json") as f:
        c = json.load(f)
    assert (c["prev_noise_max"], c["prev_noise_level"]) == (30, 20)
    T.main(["export", "--run", run, "--out", str(tmp_path / "m0"), "--prev-noise-level", "0"])   # inference only
    with open(tmp_path / "m0" / "controlnet" / "config.json") as f:
        c = json.load(f)
    assert (c["prev_noise_max"], c["prev_noise_level"]) == (30, 0)
    with pytest.raises(SystemExit, match="--prev-noise-level 999"):
        T.main(["export", "--run", run, "--out", str(tmp_path / "m9"), "--prev-noise-level", "999"])
    with pytest.raises(SystemExit, match="prev_noise_max is 30"):
        diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "3", "--resume", "--prev-noise-max", "40")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "3", "--resume")      # the run's own values
    assert drawn[-1] == 30
    with pytest.raises(SystemExit, match="--prev-noise-level 999"):
        diffusion(os.path.join(vae_run[0], "vae"), str(tmp_path / "r2"), "--steps", "1", "--prev-noise-level", "999")


def test_prev_blur_override_reaches_the_data_and_the_package(vae_run, tmp_path, monkeypatch):
    """--prev-blur-sigma replaces the design's blur of the previous frame: the data blurs with it, the exported
    ControlNet config holds it, a resume with another value and a blur outside (0, 4] are refused."""
    sigmas = []
    real = T.gaussian_blur

    def spy(x, sigma):
        sigmas.append(float(sigma))
        return real(x, sigma)

    monkeypatch.setattr(T, "gaussian_blur", spy)
    run = str(tmp_path / "run")
    diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "2", "--prev-blur-sigma", "0.5")
    assert sigmas and set(sigmas) == {0.5}
    T.main(["export", "--run", run, "--out", str(tmp_path / "model")])
    with open(tmp_path / "model" / "controlnet" / "config.json") as f:
        assert json.load(f)["prev_blur_sigma"] == 0.5
    with pytest.raises(SystemExit, match="prev_blur_sigma is 0.5"):
        diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "3", "--resume", "--prev-blur-sigma", "1")
    for bad in ("0", "5", "nan"):
        with pytest.raises(SystemExit, match=f"--prev-blur-sigma {bad}"):
            diffusion(os.path.join(vae_run[0], "vae"), str(tmp_path / f"bad{bad}"), "--steps", "1",
                      "--prev-blur-sigma", bad)


def test_one_step_x0_is_the_one_step_unipc_sample():
    """selfprev.one_step_x0's sampler is diffusers' UniPC at one step on the SD1.5 schedule (what the engine's
    one-step package runs): timesteps [999] and the step returns the x_0 of the prediction."""
    from b2dr_ref.frame import make_scheduler
    from b2dr_ref.training import selfprev as S

    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    g = torch.Generator().manual_seed(3)
    x_T, v = torch.randn(2, 4, 7, 13, generator=g), torch.randn(2, 4, 7, 13, generator=g)
    sch = make_scheduler("unipc", "v_prediction")
    sch.set_timesteps(1)
    assert sch.timesteps.tolist() == [S.ONE_STEP_T]
    ref = sch.step(v, sch.timesteps[0], x_T).prev_sample

    class V(torch.nn.Module):
        def forward(self, x, *a, **k):
            return type("O", (), {"sample": v})()

    zp = torch.randn(2, 4, 7, 13, generator=g)
    x0 = S.one_step_x0(V(), _NoControlNet(), torch.zeros(2, 77, 8), None, zp, x_T, torch.zeros_like(zp), abar, 200,
                       "v_prediction", "prev")
    torch.testing.assert_close(x0 - zp, ref, atol=1e-5, rtol=1e-5)


def test_self_prev_gives_rows_the_models_own_previous_frame(vae_run, tmp_path):
    """--self-prev P: after the usual draws, rows with a previous frame take (probability P) the previous-frame
    latent (decode, 8-bit, blur, encode) of the model's own one-step render of their frame; the loss is then that
    of the residual against this latent. Checked with a model that predicts 0, whose one-step render is
    sqrt(abar_999) x_T + z_prev. The CLI trains with it and refuses a P outside [0, 1]."""
    from b2dr_ref.training import selfprev as S

    vae = T.load_vae(os.path.join(vae_run[0], "vae"))
    lc = vae.config.latent_channels
    B = 4
    g0 = torch.Generator().manual_seed(11)
    b = dict(x0=torch.randn(B, lc, 7, 13, generator=g0), z_prev=torch.randn(B, lc, 7, 13, generator=g0),
             masks=torch.zeros(B, 15, 56, 104), cams=torch.zeros(B, dtype=torch.int64))
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    gen_state = torch.Generator().manual_seed(7).get_state()
    g = torch.Generator()
    g.set_state(gen_state)
    d = T.draw_noise(b, g, 400, 0.5, 1.0)
    s = S.draw_self(b, g, 1.0)
    rows = ~d["noprev"]
    assert 0 < int(rows.sum()) < B
    from b2dr_ref.frame import gaussian_blur

    sf = vae.config.scaling_factor
    with torch.no_grad():      # the engine's path: decode, clamp, 8-bit, blur sigma 1 (the config's), encode mean
        img = vae.decode((abar[999].sqrt() * s["x_T"] + b["z_prev"]) / sf).sample
        u8 = ((img.clamp(-1, 1) + 1) * 127.5).round()
        own = vae.encode(2.0 * gaussian_blur(u8 / 255.0, 1.0) - 1.0).latent_dist.mean * sf
    assert not torch.allclose(own[rows], b["z_prev"][rows], atol=0.1)
    zp = torch.where(rows.reshape(B, 1, 1, 1), own, b["z_prev"])
    a = abar[d["t"]].reshape(B, 1, 1, 1)
    v = a.sqrt() * d["eps"] - (1 - a).sqrt() * (b["x0"] - rows.float().reshape(B, 1, 1, 1) * zp)
    ctx = torch.zeros(1, 77, 8)
    g.set_state(gen_state)
    loss = T.diffusion_loss(_ZeroUnet(), _NoControlNet(), ctx, b, g, abar, p_noprev=0.5, ref_dropout=1.0,
                            prediction="v_prediction", x0_base="prev", self_prev=1.0, vae=vae)
    torch.testing.assert_close(loss, (v ** 2).mean(), atol=1e-5, rtol=1e-5)
    g.set_state(gen_state)
    plain = T.diffusion_loss(_ZeroUnet(), _NoControlNet(), ctx, b, g, abar, p_noprev=0.5, ref_dropout=1.0,
                             prediction="v_prediction", x0_base="prev")
    assert not torch.allclose(plain, loss)
    with pytest.raises(ValueError, match="needs the VAE"):
        T.diffusion_loss(_ZeroUnet(), _NoControlNet(), ctx, b, g, abar, self_prev=0.5)

    run = str(tmp_path / "run")
    losses = diffusion(os.path.join(vae_run[0], "vae"), run, "--steps", "2", "--prediction", "v_prediction",
                       "--x0-base", "prev", "--self-prev", "0.5")
    assert len(losses) == 2 and all(np.isfinite(losses))
    with pytest.raises(SystemExit, match="--self-prev 1.5"):
        diffusion(os.path.join(vae_run[0], "vae"), str(tmp_path / "bad"), "--steps", "1", "--self-prev", "1.5")


class _MaskCn:       # the layout decides the output: residual = mean of the first mask channel per row
    config = _NoControlNet.config

    def __call__(self, x, t, ctx, masks, z, n, refs=None, ref_mask=None):
        return [masks[:, :1].mean((2, 3), keepdim=True).expand_as(x)], None


class _Echo(torch.nn.Module):     # the UNet's output is the ControlNet's first residual
    def forward(self, x, t, ctx, down_block_additional_residuals=None, mid_block_additional_residual=None):
        return type("O", (), {"sample": down_block_additional_residuals[0]})()


def test_self_prev_pose_other_renders_the_partners_layout(vae_run, tmp_path):
    """--self-prev-pose other: the own render takes the batch's masks_other (the partner offset's layout), not the
    row's masks; pose_partners groups an index's samples by scenario and step (None when one stands alone,
    refused when partners have other previous frames); the CLI refuses 'other' on data without offsets and
    without --self-prev."""
    from b2dr_ref.training import selfprev as S

    vae = T.load_vae(os.path.join(vae_run[0], "vae"))
    lc = vae.config.latent_channels
    B = 2
    g = torch.Generator().manual_seed(5)
    b = dict(z_prev=torch.randn(B, lc, 7, 13, generator=g), x0=torch.zeros(B, lc, 7, 13),
             masks=torch.zeros(B, 15, 56, 104), masks_other=torch.ones(B, 15, 56, 104))
    s = S.draw_self(b, g, 1.0)
    rows = torch.ones(B, dtype=torch.bool)
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    ctx = torch.zeros(B, 77, 8)
    got = S.own_previous(_Echo(), _MaskCn(), vae, ctx, b, s, rows, abar, "v_prediction", "prev")
    with torch.no_grad():
        x0 = abar[999].sqrt() * s["x_T"] - (1 - abar[999]).sqrt() * torch.ones_like(s["x_T"]) + b["z_prev"]
        want = S.previous_frame_latent(vae, x0, 1.0)
    torch.testing.assert_close(got, want)
    same = S.own_previous(_Echo(), _MaskCn(), vae, ctx, {k: v for k, v in b.items() if k != "masks_other"}, s, rows,
                          abar, "v_prediction", "prev")
    assert not torch.allclose(same, got)

    class Src:
        cameras = ["A", "B"]

        def __init__(self, rows):
            self.ds = type("D", (), {"samples": rows})()

    r = [dict(scenario="x", step=3, prev_step=1), dict(scenario="x", step=3, prev_step=1),
         dict(scenario="y", step=3, prev_step=1)]
    assert S.pose_partners(Src(r)) is None                     # y step 3 stands alone
    assert S.pose_partners(Src(r[:2])) == [[2], [3], [0], [1]]
    with pytest.raises(ValueError, match="other previous frames"):
        S.pose_partners(Src([r[0], dict(r[1], prev_step=2)]))
    assert S.pose_partners(type("Syn", (), {"cameras": ["A"]})()) is None

    vae_dir = os.path.join(vae_run[0], "vae")
    with pytest.raises(SystemExit, match="not an exported dataset"):
        diffusion(vae_dir, str(tmp_path / "a"), "--steps", "1", "--self-prev", "0.5", "--self-prev-pose", "other")
    with pytest.raises(SystemExit, match="give --self-prev"):
        diffusion(vae_dir, str(tmp_path / "b"), "--steps", "1", "--self-prev-pose", "other")


def _chain_export(tmp_path):
    """A tiny --prev-chain export (b2dr binary of this checkout) at the test config's size; None without a binary."""
    import subprocess

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    exe = next((p for p in (os.path.join(repo, "target", k, "b2dr") for k in ("release", "debug"))
                if os.path.isfile(p) and os.access(p, os.X_OK)), None)
    if exe is None:
        return None
    out = str(tmp_path / "chain")
    h, w = nano.TEST["render_size"]
    subprocess.run([exe, "export-training", "--scenario", "builtin:straight:1", "--out", out, "--size", f"{h}x{w}",
                    "--samples-per-scenario", "2", "--cameras", "CAM_FRONT", "--seed", "2", "--prev-chain",
                    "--quiet"], check=True)
    return out


def test_self_prev_pose_chain_renders_the_previous_frame(vae_run, tmp_path, capsys):
    """--self-prev-pose chain: the own render takes the previous frame's layout (masks_prev) and starts from the frame
    before it (z_prev2), not the row's masks and previous latent; the Batcher of a --prev-chain export gives those
    (z_prev2 = the blurred encode of prev2, as z_prev is of prev); the CLI refuses chain on data without them and
    without --self-prev, and trains with it on a --prev-chain export."""
    from b2dr_ref.training import selfprev as S

    vae = T.load_vae(os.path.join(vae_run[0], "vae"))
    lc = vae.config.latent_channels
    B = 2
    g = torch.Generator().manual_seed(6)
    b = dict(z_prev=torch.randn(B, lc, 7, 13, generator=g), z_prev2=torch.randn(B, lc, 7, 13, generator=g),
             x0=torch.zeros(B, lc, 7, 13), masks=torch.zeros(B, 15, 56, 104), masks_prev=torch.ones(B, 15, 56, 104))
    s = S.draw_self(b, g, 1.0)
    rows = torch.tensor([True, False])
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    ctx = torch.zeros(B, 77, 8)
    got = S.own_previous(_Echo(), _MaskCn(), vae, ctx, b, s, rows, abar, "v_prediction", "prev")
    with torch.no_grad():
        x0 = abar[999].sqrt() * s["x_T"][:1] - (1 - abar[999]).sqrt() + b["z_prev2"][:1]
        want = S.previous_frame_latent(vae, x0, 1.0)
    torch.testing.assert_close(got[:1], want)
    assert torch.equal(got[1], b["z_prev"][1])            # a row not drawn keeps its true previous frame
    plain = {k: v for k, v in b.items() if k not in ("masks_prev", "z_prev2")}
    assert not torch.allclose(S.own_previous(_Echo(), _MaskCn(), vae, ctx, plain, s, rows, abar, "v_prediction",
                                             "prev")[:1], got[:1])

    vae_dir = os.path.join(vae_run[0], "vae")
    with pytest.raises(SystemExit, match="--prev-chain"):
        diffusion(vae_dir, str(tmp_path / "a"), "--steps", "1", "--self-prev", "0.5", "--self-prev-pose", "chain")
    with pytest.raises(SystemExit, match="give --self-prev"):
        diffusion(vae_dir, str(tmp_path / "b"), "--steps", "1", "--self-prev-pose", "chain")
    src_syn = T.open_source("synthetic:2", nano.TEST["render_size"])
    _, cn = T.build_diffusion_models(nano.TEST)
    with pytest.raises(ValueError, match="not a --prev-chain export"):
        T.Batcher(src_syn, vae, cn, "cpu", chain=True)

    data = _chain_export(tmp_path)
    if data is None:
        print("SKIP (rest): no b2dr binary under target/(release|debug); run cargo build --release")
        return
    src = T.open_source(data, nano.TEST["render_size"])
    assert src.prev_chain and len(src) == 2
    bt = T.Batcher(src, vae, cn, "cpu", chain=True)
    batch = bt.batch([0, 1])
    want_z2 = bt._encode(np.stack([src[i].prev2 for i in range(2)]), True)
    torch.testing.assert_close(batch["z_prev2"], want_z2)
    np.testing.assert_array_equal(batch["masks_prev"].numpy(), np.stack([src[i].prev_masks for i in range(2)]))
    assert not torch.equal(batch["z_prev2"], batch["z_prev"])
    assert "z_prev2" not in T.Batcher(src, vae, cn, "cpu").batch([0])
    # with the warp, the chain's first hop warps prev2 to the previous frame's pose (the export holds prev2's pose),
    # as the loop warps every frame it carries; an export without that pose trains it unwarped and says so
    from b2dr_ref.warp import ground_warp_grid
    import dataclasses

    _, cw = T.build_diffusion_models(dict(nano.TEST, controlnet=dict(nano.TEST["controlnet"], prev_warp_max_depth=30.0)))
    bw = T.Batcher(src, vae, cw, "cpu", chain=True)
    hop1 = [ground_warp_grid(src[i].k, src[i].cam2ego, src[i].prev_ego2global, src[i].prev2_ego2global,
                             src.render_size, 30.0) for i in range(2)]
    assert all(np.isfinite(g).mean() > 0.5 for g in hop1)     # most pixels have a source in prev2
    torch.testing.assert_close(bw.batch([0, 1])["z_prev2"], bw._encode(np.stack([src[i].prev2 for i in range(2)]),
                                                                        True, hop1))
    assert not torch.allclose(bw.batch([0, 1])["z_prev2"], want_z2)
    capsys.readouterr()
    old = [dataclasses.replace(src[i], prev2_ego2global=None) for i in range(2)]
    assert bw._hop1_grids(old) is None and bw._hop1_grids(old) is None     # called twice ...
    assert capsys.readouterr().out.count("UNwarped previous frame") == 1   # ... said once
    run = str(tmp_path / "run")
    losses = T.main(["--data", data, "--vae", vae_dir, "--out", run, "--batch", "2", "--warmup", "1", "--steps", "2",
                     "--ckpt-every", "1000", "--prediction", "v_prediction", "--x0-base", "prev", "--self-prev", "1",
                     "--self-prev-pose", "chain"] + COMMON)
    assert len(losses) == 2 and all(np.isfinite(losses))
    d = torch.load(os.path.join(run, T.LATENTS_FILE), weights_only=True)
    assert d["z_prev2"].shape == d["z_prev"].shape       # the chain latents are kept for a resume
    # a latents file without them (a run of another pose on the same data) serves a plain Batcher, not a chain one
    plain_file = str(tmp_path / "plain_latents.pt")
    torch.save({k: v for k, v in d.items() if k != "z_prev2"}, plain_file)
    assert len(T.Batcher(src, vae, cn, "cpu", latents=(plain_file, d["key"])).disk) == len(d["index"])
    capsys.readouterr()
    assert not T.Batcher(src, vae, cn, "cpu", latents=(plain_file, d["key"]), chain=True).disk
    assert "holds no prev2 latents" in capsys.readouterr().out


def test_prev_warp_reaches_the_data_the_own_previous_frame_and_the_package(vae_run, tmp_path):
    """--prev-warp-max-depth D: the Batcher encodes the previous frame warped to the sample's pose (b2dr_ref/warp.py)
    before the blur and hands each row's grid to the self-prev chain, whose own previous frame is warped the same
    way; the latents file's key and the exported ControlNet config carry D; a bad D, a resume with another D and
    a self-prev pose whose own render is not at the previous pose are refused."""
    from b2dr_ref.training import selfprev as S
    from b2dr_ref.warp import ground_warp_grid, warp_image

    vae_dir = os.path.join(vae_run[0], "vae")
    vae = T.load_vae(vae_dir)
    src = T.open_source("synthetic:2", nano.TEST["render_size"])
    _, cn = T.build_diffusion_models(nano.TEST)
    _, cw = T.build_diffusion_models(dict(nano.TEST, controlnet=dict(nano.TEST["controlnet"], prev_warp_max_depth=30.0)))
    plain, warped = T.Batcher(src, vae, cn, "cpu").batch([0, 1]), T.Batcher(src, vae, cw, "cpu").batch([0, 1])
    assert "prev_grid" not in plain and warped["prev_grid"].shape == (2, *src.render_size, 2)
    grids = [ground_warp_grid(src[i].k, src[i].cam2ego, src[i].ego2global, src[i].prev_ego2global, src.render_size,
                              30.0) for i in range(2)]
    np.testing.assert_array_equal(warped["prev_grid"].numpy(), np.stack(grids))
    assert np.isfinite(grids[0]).mean() > 0.5              # the synthetic previous pose is 3 m behind: most pixels move
    want = torch.cat([vae.encode(2 * T.gaussian_blur(warp_image(torch.from_numpy(src[i].prev[None]).float() / 255,
                                                                 torch.from_numpy(grids[i])[None]), 1.0) - 1)
                      .latent_dist.mean * vae.config.scaling_factor for i in range(2)])
    torch.testing.assert_close(warped["z_prev"], want.detach())
    assert not torch.allclose(warped["z_prev"], plain["z_prev"])
    torch.testing.assert_close(warped["x0"], plain["x0"])
    # the self-prev chain: the own render of the previous frame is warped with the row's grid
    lc = vae.config.latent_channels
    g = torch.Generator().manual_seed(6)
    b = dict(z_prev=torch.randn(2, lc, 7, 13, generator=g), z_prev2=torch.randn(2, lc, 7, 13, generator=g),
             x0=torch.zeros(2, lc, 7, 13), masks=torch.zeros(2, 15, 56, 104), masks_prev=torch.ones(2, 15, 56, 104),
             prev_grid=warped["prev_grid"])
    s = S.draw_self(b, g, 1.0)
    rows = torch.tensor([False, True])
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    got = S.own_previous(_Echo(), _MaskCn(), vae, torch.zeros(2, 77, 8), b, s, rows, abar, "v_prediction", "prev")
    with torch.no_grad():
        x0 = abar[999].sqrt() * s["x_T"][1:] - (1 - abar[999]).sqrt() + b["z_prev2"][1:]
        want = S.previous_frame_latent(vae, x0, 1.0, b["prev_grid"][1:])
        unwarped = S.previous_frame_latent(vae, x0, 1.0)
    torch.testing.assert_close(got[1:], want)
    assert not torch.allclose(want, unwarped)
    assert torch.equal(got[0], b["z_prev"][0])
    # the key, the package, the refusals
    assert T.latent_cache_key("synthetic:2", vae_dir, 1.0, 30.0) != T.latent_cache_key("synthetic:2", vae_dir, 1.0)
    run = str(tmp_path / "run")
    diffusion(vae_dir, run, "--steps", "2", "--prev-warp-max-depth", "30")
    T.main(["export", "--run", run, "--out", str(tmp_path / "model")])
    with open(tmp_path / "model" / "controlnet" / "config.json") as f:
        assert json.load(f)["prev_warp_max_depth"] == 30.0
    with pytest.raises(SystemExit, match="prev_warp_max_depth is 30"):
        diffusion(vae_dir, run, "--steps", "3", "--resume", "--prev-warp-max-depth", "0")
    for bad in ("-1", "2000", "nan"):
        with pytest.raises(SystemExit, match=f"--prev-warp-max-depth {bad}"):
            diffusion(vae_dir, str(tmp_path / f"bad{bad}"), "--steps", "1", "--prev-warp-max-depth", bad)
    with pytest.raises(SystemExit, match="use --self-prev-pose chain"):
        diffusion(vae_dir, str(tmp_path / "same"), "--steps", "1", "--prev-warp-max-depth", "30", "--self-prev", "0.5")
