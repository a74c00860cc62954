"""tools/deepen_vae.py: the deeper VAE starts as the same function, and its added resnets really are new blocks."""

import torch
from diffusers import AutoencoderKL

from b2dr_ref import nano


def _small_vae(tmp_path):
    cfg = nano.get_config("test")["vae"]
    torch.manual_seed(0)
    vae = AutoencoderKL(**cfg).eval()
    # random, non-trivial weights everywhere (a freshly built VAE's conv_out etc. are not zero, but be explicit)
    with torch.no_grad():
        for p in vae.parameters():
            p.add_(0.05 * torch.randn_like(p))
    vae.save_pretrained(tmp_path / "src", safe_serialization=True)
    return vae


def test_deeper_vae_reproduces_the_source_and_can_learn(tool, tmp_path):
    src = _small_vae(tmp_path)
    assert tool("deepen_vae").main(["--vae", str(tmp_path / "src"), "--out", str(tmp_path / "deep")]) == 0
    deep = AutoencoderKL.from_pretrained(tmp_path / "deep").eval()
    assert deep.config.layers_per_block == 2 and src.config.layers_per_block == 1
    assert len(deep.encoder.down_blocks[0].resnets) == 2 and len(deep.decoder.up_blocks[0].resnets) == 3
    x = torch.rand(1, 3, 48, 80, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.no_grad():
        z = src.encode(x).latent_dist.mean
        assert torch.equal(z, deep.encode(x).latent_dist.mean)
        assert torch.equal(src.decode(z).sample, deep.decode(z).sample)
        # the added blocks are live: a non-zero conv2 in one of them changes the output
        deep.decoder.up_blocks[-1].resnets[2].conv2.weight.normal_(0, 0.1)
        assert not torch.allclose(src.decode(z).sample, deep.decode(z).sample)


def test_refuses_a_depth_it_already_has(tool, tmp_path, capsys):
    _small_vae(tmp_path)
    assert tool("deepen_vae").main(["--vae", str(tmp_path / "src"), "--out", str(tmp_path / "x"), "--layers", "1"]) == 2
    assert "already has layers_per_block 1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
