"""tools/vae_ceiling.py's latent smoothness figures (the "diffusability" columns) on fields whose answer is known."""

import pytest
import torch


def test_white_noise_is_uncorrelated_and_pooling_keeps_a_quarter(tool):
    z = torch.randn(64, 16, 14, 25, generator=torch.Generator().manual_seed(0))
    s = tool("vae_ceiling").latent_smoothness(z)
    assert abs(s["lag1_x"]) < 0.02 and abs(s["lag1_y"]) < 0.02, s
    assert s["pool2_kept"] == pytest.approx(0.25, abs=0.01)


def test_rows_constant_along_x_with_channel_offsets(tool):
    # every row constant along x (lag-1 x correlation exactly 1), rows independent (y about 0), and per-channel
    # offsets of 5 that centring must remove (without it the y figure would be near 1)
    g = torch.Generator().manual_seed(1)
    z = torch.randn(64, 4, 14, 1, generator=g).expand(64, 4, 14, 26) + 5 * torch.arange(4.0).reshape(1, 4, 1, 1)
    s = tool("vae_ceiling").latent_smoothness(z)
    assert s["lag1_x"] == pytest.approx(1.0, abs=1e-9)
    assert abs(s["lag1_y"]) < 0.05, s
    assert s["pool2_kept"] == pytest.approx(0.5, abs=0.03)      # pooling averages two independent rows


def test_smooth_fields_score_high(tool):
    coarse = torch.randn(32, 8, 4, 7, generator=torch.Generator().manual_seed(2))
    z = torch.nn.functional.interpolate(coarse, size=(14, 25), mode="bilinear", align_corners=False)
    s = tool("vae_ceiling").latent_smoothness(z)
    assert s["lag1_x"] > 0.8 and s["lag1_y"] > 0.8 and s["pool2_kept"] > 0.85, s
