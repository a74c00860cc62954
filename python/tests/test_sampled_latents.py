"""The renderer's own one-step latents (training/sampled_latents.py) and the decoder trained on them
(vae_train --decoder-only --decode-latents)."""

import os

import numpy as np
import pytest
import torch

from b2dr_ref import train as T
from b2dr_ref import vae_train as V
from b2dr_ref.training import sampled_latents as SL

COMMON = ["--config", "test", "--threads", "1", "--log-every", "1000"]


@pytest.fixture(scope="module")
def vae_dir(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("vae"))
    V.main(["--data", "synthetic:4", "--out", out, "--steps", "6", "--batch", "2", "--lr", "2e-3", "--warmup", "1",
            "--fixed-batch", "--ckpt-every", "1000"] + COMMON)
    return os.path.join(out, "vae")


class _RefCn:
    """The residual is the (noised) previous latent it is given, plus 2 when it is given references: the guided
    prediction is then z + 2 g, and a missing or doubled noising of the previous latent shows."""
    config = type("C", (), {"prev_noise_level": 200, "prev_blur_sigma": 1.0})()

    def prepare_references(self, lat, pc, pr):
        return "refs"

    def __call__(self, x, t, ctx, masks, z, n, refs=None, ref_mask=None):
        assert int(t[0]) == 999 and int(n[0]) == 200
        return [z + (2.0 if refs is not None else 0.0)], None


class _Echo(torch.nn.Module):
    def forward(self, x, t, ctx, down_block_additional_residuals=None, mid_block_additional_residual=None):
        return type("O", (), {"sample": down_block_additional_residuals[0]})()


def test_one_step_with_refs_is_the_guided_one_step_sample():
    """pred = u + g (c - u) (renderer.md f: uncond without references), the previous latent noised to
    prev_noise_level, x_0 from v at t = 999, plus the previous latent for x0_base prev; g = 1 runs the cond pass
    only."""
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    g = torch.Generator().manual_seed(1)
    B, sh = 2, (2, 4, 7, 13)
    x_T, eps_in, zp = (torch.randn(sh, generator=g) for _ in range(3))
    b = dict(masks=None, ref_latents=torch.zeros(B, 2, 4, 7, 13), pe_cur=[torch.zeros(B, 1)],
             pe_ref=[torch.zeros(B, 1)])
    z = abar[200].sqrt() * zp + (1 - abar[200]).sqrt() * eps_in
    at = abar[999]
    for guid in (1.0, 2.0, 3.5):
        got = SL.one_step_with_refs(_Echo(), _RefCn(), torch.zeros(B, 77, 8), b, zp, x_T, eps_in, abar,
                                    "v_prediction", "prev", guid)
        want = at.sqrt() * x_T - (1 - at).sqrt() * (z + 2.0 * guid) + zp
        torch.testing.assert_close(got, want)
    eps = SL.one_step_with_refs(_Echo(), _RefCn(), torch.zeros(B, 77, 8), b, zp, x_T, eps_in, abar, "epsilon",
                                "none", 2.0)
    torch.testing.assert_close(eps, (x_T - (1 - at).sqrt() * (z + 4.0)) / at.sqrt())


def _latents_file(path, n, sf, lat, render_size=(56, 104)):
    torch.save(dict(format=SL.FORMAT, index=torch.arange(n), latents=lat * sf, scaling_factor=sf, samples=n,
                    render_size=list(render_size), package="-", prev="truth", guidance=2.0, seed=0), path)


def test_vae_loss_decodes_the_given_latents_for_the_given_rows(vae_dir):
    """vae_loss(decoder_only, z_given, given): the rows of ``given`` decode z_given, the others the encoder's mean;
    z_given without decoder_only is refused."""
    vae = T.load_vae(vae_dir)
    x = torch.rand(2, 3, 56, 104) * 2 - 1
    with torch.no_grad():
        mean = vae.encode(x).latent_dist.mean
    zg = torch.randn_like(mean)
    given = torch.tensor([True, False])
    loss, _, _ = V.vae_loss(vae, x, torch.Generator(), 0.0, recon="l2", decoder_only=True, z_given=zg, given=given)
    with torch.no_grad():
        rec = vae.decode(torch.stack([zg[0], mean[1]])).sample
    want = (rec - x).square().flatten(1).sum(1).mean() / (3 * 56 * 104)
    torch.testing.assert_close(loss.detach(), want, rtol=1e-5, atol=1e-7)
    none, _, _ = V.vae_loss(vae, x, torch.Generator(), 0.0, recon="l2", decoder_only=True, z_given=zg,
                            given=torch.tensor([False, False]))
    plain, _, _ = V.vae_loss(vae, x, torch.Generator(), 0.0, recon="l2", decoder_only=True)
    torch.testing.assert_close(none, plain)
    with pytest.raises(ValueError, match="only with decoder_only"):
        V.vae_loss(vae, x, torch.Generator(), 0.0, z_given=zg, given=given)


def test_decoder_trains_on_given_latents_and_keeps_the_latent_space(vae_dir, tmp_path):
    """--decode-latents: the decoder learns to map the file's latents to their frames (the loss on them falls),
    the encoder side and the scaling factor stay the initial VAE's, a resume continues exactly; a file of another
    size or scaling factor, no --decoder-only, --crop and a bad probability are refused."""
    from safetensors.torch import load_file

    sf = float(T.load_vae(vae_dir).config.scaling_factor)
    f = str(tmp_path / "lat.pt")
    _latents_file(f, 4, sf, torch.randn(4, 4, 7, 13, generator=torch.Generator().manual_seed(2)))
    def with_file(path):
        return ["--data", "synthetic:4", "--batch", "2", "--lr", "2e-3", "--warmup", "1", "--ckpt-every", "1000",
                "--decoder-only", "--init-from", vae_dir, "--recon-loss", "l2", "--decode-latents", path] + COMMON

    args = with_file(f)
    losses = V.main(args + ["--out", str(tmp_path / "a"), "--steps", "24"])
    assert np.mean(losses[-6:]) < 0.8 * np.mean(losses[:6]), losses
    before = load_file(os.path.join(vae_dir, "diffusion_pytorch_model.safetensors"))
    after = load_file(str(tmp_path / "a" / "vae" / "diffusion_pytorch_model.safetensors"))
    for k in before:
        if k.startswith(("encoder.", "quant_conv.")):
            torch.testing.assert_close(after[k], before[k], rtol=0, atol=0)
    assert T.load_vae(str(tmp_path / "a" / "vae")).config.scaling_factor == sf
    first = V.main(args + ["--out", str(tmp_path / "b"), "--steps", "24", "--stop-after", "10"])
    rest = V.main(args + ["--out", str(tmp_path / "b"), "--steps", "24", "--resume"])
    assert first + rest == pytest.approx(losses, rel=1e-6, abs=1e-7)
    # p = 0: the same draws, every row decodes the encoder's mean: other losses
    zero = V.main(args + ["--out", str(tmp_path / "c"), "--steps", "3", "--decode-latents-p", "0"])
    assert zero != pytest.approx(losses[:3], rel=1e-3)
    base = [a for a in args if a != "--decoder-only"]
    with pytest.raises(SystemExit, match="give --decoder-only"):
        V.main(base + ["--out", str(tmp_path / "d"), "--steps", "1"])
    with pytest.raises(SystemExit, match="whole frames"):
        V.main(args + ["--out", str(tmp_path / "e"), "--steps", "1", "--crop", "48x96"])
    with pytest.raises(SystemExit, match="a probability"):
        V.main(args + ["--out", str(tmp_path / "f"), "--steps", "1", "--decode-latents-p", "1.5"])
    bad = str(tmp_path / "bad.pt")
    _latents_file(bad, 3, sf, torch.zeros(3, 4, 7, 13))
    with pytest.raises(SystemExit, match="made from 3 samples"):
        V.main(with_file(bad) + ["--out", str(tmp_path / "g"), "--steps", "1"])
    _latents_file(bad, 4, 2 * sf, torch.zeros(4, 4, 7, 13))
    with pytest.raises(SystemExit, match="another latent space"):
        V.main(with_file(bad) + ["--out", str(tmp_path / "h"), "--steps", "1"])
    torch.save({"x": 1}, bad)
    with pytest.raises(SystemExit, match="not a b2dr-sampled-latents file"):
        V.main(with_file(bad) + ["--out", str(tmp_path / "i"), "--steps", "1"])


def test_cli_samples_a_one_step_package(vae_dir, tmp_path):
    """sampled_latents main on a one-step test package: one latent per sample, equal to one_step_with_refs on the
    same draws (the package's guidance, the log's previous frame); a 20-step package and --prev chain on data
    without the chain are refused."""
    from b2dr_ref.package import load_package

    run = str(tmp_path / "run")
    T.main(["--data", "synthetic:4", "--vae", vae_dir, "--out", run, "--batch", "2", "--warmup", "1", "--steps", "1",
            "--ckpt-every", "1000", "--prediction", "v_prediction", "--x0-base", "prev"] + COMMON)
    pkg_dir = str(tmp_path / "pkg")
    T.main(["export", "--run", run, "--out", pkg_dir, "--dtype", "f32", "--sampler-steps", "1"])
    out = str(tmp_path / "lat.pt")
    SL.main(["--package", pkg_dir, "--data", "synthetic:4", "--out", out, "--batch", "3", "--threads", "1"])
    d = torch.load(out, weights_only=False)
    pkg = load_package(pkg_dir)
    assert d["format"] == SL.FORMAT and d["index"].tolist() == [0, 1, 2, 3] and d["guidance"] == 2.0
    assert d["latents"].shape == (4, pkg.vae.config.latent_channels, 7, 13)
    src = T.open_source("synthetic:4", pkg.meta["render_size"])
    bt = T.Batcher(src, pkg.vae, pkg.controlnet, torch.device("cpu"), cache=0)
    b = bt.batch([0, 1, 2])
    gen = torch.Generator().manual_seed(0)
    x_T = torch.randn(b["x0"].shape, generator=gen)
    eps_in = torch.randn(b["z_prev"].shape, generator=gen)
    abar = T.make_noise_scheduler().alphas_cumprod.to(torch.float32)
    want = SL.one_step_with_refs(pkg.unet, pkg.controlnet, pkg.context[b["cams"]], b, b["z_prev"], x_T, eps_in,
                                 abar, "v_prediction", "prev", 2.0)
    torch.testing.assert_close(d["latents"][:3], want, rtol=1e-4, atol=1e-5)
    with pytest.raises(SystemExit, match="--prev-chain"):
        SL.main(["--package", pkg_dir, "--data", "synthetic:4", "--out", out, "--prev", "chain"])
    T.main(["export", "--run", run, "--out", str(tmp_path / "pkg20"), "--dtype", "f32"])
    with pytest.raises(SystemExit, match="20-step package"):
        SL.main(["--package", str(tmp_path / "pkg20"), "--data", "synthetic:4", "--out", out])


def test_export_takes_a_decoder_trained_alone_and_refuses_another_latent_space(vae_dir, tmp_path):
    """train export --vae and train replace-vae: a decoder trained alone on the run's VAE (same encoder, same
    factor) goes into the package, the rest of it unchanged; a VAE whose encoder trained too is refused (the
    denoiser's samples would decode into garbage)."""
    from b2dr_ref.package import load_package

    run = str(tmp_path / "run")
    T.main(["--data", "synthetic:4", "--vae", vae_dir, "--out", run, "--batch", "2", "--warmup", "1", "--steps", "1",
            "--ckpt-every", "1000"] + COMMON)
    sf = float(T.load_vae(vae_dir).config.scaling_factor)
    f = str(tmp_path / "lat.pt")
    _latents_file(f, 4, sf, torch.randn(4, 4, 7, 13, generator=torch.Generator().manual_seed(3)))
    base = ["--data", "synthetic:4", "--batch", "2", "--lr", "2e-3", "--warmup", "1", "--ckpt-every", "1000",
            "--init-from", vae_dir, "--steps", "2"] + COMMON
    V.main(base + ["--out", str(tmp_path / "dec"), "--decoder-only", "--decode-latents", f])
    V.main(base + ["--out", str(tmp_path / "full")])
    dec = os.path.join(str(tmp_path / "dec"), "vae")
    T.main(["export", "--run", run, "--out", str(tmp_path / "pkg"), "--dtype", "f32", "--vae", dec])
    got = load_package(str(tmp_path / "pkg")).vae.state_dict()
    for k, v in T.load_vae(dec).state_dict().items():
        torch.testing.assert_close(got[k], v, rtol=0, atol=0)
    with pytest.raises(SystemExit, match="not the latent space the denoiser trained in"):
        T.main(["export", "--run", run, "--out", str(tmp_path / "bad"), "--vae",
                os.path.join(str(tmp_path / "full"), "vae")])
    # replace-vae: a package (the run's VAE) given the decoder; unet, controlnet, context and b2dr.json unchanged
    T.main(["export", "--run", run, "--out", str(tmp_path / "own"), "--dtype", "f32"])
    T.main(["replace-vae", "--package", str(tmp_path / "own"), "--vae", dec, "--out", str(tmp_path / "swap")])
    own, swap = load_package(str(tmp_path / "own")), load_package(str(tmp_path / "swap"))
    assert swap.meta == own.meta
    torch.testing.assert_close(swap.context, own.context, rtol=0, atol=0)
    for a, b in ((own.unet, swap.unet), (own.controlnet, swap.controlnet)):
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    got = swap.vae.state_dict()
    for k, v in T.load_vae(dec).state_dict().items():
        torch.testing.assert_close(got[k], v, rtol=0, atol=0)
    with pytest.raises(SystemExit, match="not the latent space the denoiser trained in"):
        T.main(["replace-vae", "--package", str(tmp_path / "own"), "--vae",
                os.path.join(str(tmp_path / "full"), "vae"), "--out", str(tmp_path / "bad2")])
    with pytest.raises(SystemExit, match="not empty"):
        T.main(["replace-vae", "--package", str(tmp_path / "own"), "--vae", dec, "--out", str(tmp_path / "swap")])
