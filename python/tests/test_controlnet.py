import json

import pytest
import torch
from diffusers import ControlNetModel

from b2dr_ref.controlnet import PLAIN_KEYS, B2DRControlNetModel, ConfigError
from b2dr_ref.testing import configs, nontrivial_init

from helpers import frame_inputs

NEW_PREFIXES = ("noise_embedding.", "ref_encoder.", "pos_embed.", "ref_attn.")


def _inputs(cn, n=2, h=7, w=13, seed=1):
    g = torch.Generator().manual_seed(seed)
    fi = frame_inputs(cn, n=n, h=h, w=w, seed=seed)
    return dict(
        sample=torch.randn((n, 4, h, w), generator=g),
        timestep=torch.tensor(601),
        encoder_hidden_states=torch.randn((n, 77, cn.config.cross_attention_dim), generator=g),
        controlnet_cond=fi["masks"],
        prev_latent=torch.randn((n, 4, h, w), generator=g),
        noise_level=torch.tensor([200, 37][:n]),
    ), fi


def test_state_dict_names_are_diffusers_plus_b2dr():
    cn = B2DRControlNetModel.from_config(configs()["controlnet"])
    plain = ControlNetModel(**cn.plain_config())
    own = cn.state_dict()
    ref = plain.state_dict()
    assert [k for k in own if not k.startswith(NEW_PREFIXES)] == list(ref)
    for k, v in ref.items():
        want = (v.shape[0], 8) + tuple(v.shape[2:]) if k == "conv_in.weight" else v.shape
        assert own[k].shape == want, k
    nl = len(cn.config.ref_attn)
    assert cn.config.ref_attn == ["down.0", "down.1", "down.2", "mid"] and nl == 4
    assert {k.split(".")[1] for k in own if k.startswith(("pos_embed.", "ref_attn."))} == {"0", "1", "2", "3"}
    assert [a.heads for a in cn.ref_attn_modules] == [2, 4, 8, 8]


@torch.no_grad()
def test_fresh_equals_plain():
    """A fresh B2D-R ControlNet (zero-init new outputs) equals diffusers' plain ControlNet on x_t, whatever z_prev,
    the noise level and the references are."""
    cn = B2DRControlNetModel.from_config(configs()["controlnet"]).eval()
    plain = ControlNetModel(**cn.plain_config()).eval()
    nontrivial_init(plain, 5)  # non-zero zero-convs so the residuals are not trivially 0
    cn.load_plain_weights(plain.state_dict())
    assert torch.equal(cn.conv_in.weight[:, 4:], torch.zeros_like(cn.conv_in.weight[:, 4:]))
    args, fi = _inputs(cn)
    from b2dr_ref.frame import encode_reference_images  # noqa: F401  (refs from random latents here)

    g = torch.Generator().manual_seed(3)
    ref_lat = torch.randn((2, 2, 4, 7, 13), generator=g)
    refs = cn.prepare_references(ref_lat, fi["pe_cur"], fi["pe_ref"])
    want_down, want_mid = plain(args["sample"], args["timestep"], args["encoder_hidden_states"],
                                controlnet_cond=args["controlnet_cond"], return_dict=False)
    for r in (None, refs):
        down, mid = cn(**args, refs=r)
        assert len(down) == len(want_down) == 6  # 1 + (1 + 1) + (1 + 1) + 1
        for a, b in zip(list(down) + [mid], list(want_down) + [want_mid]):
            assert a.shape == b.shape
            # conv_in has 8 input channels here and 4 there (zero weights on 4..8): the same sum, but the conv
            # kernel may block the reduction differently, so allow f32 rounding.
            err = (a - b).abs().max().item() / max(b.abs().max().item(), 1e-30)
            assert err < 1e-5, err
    # The B2D-R parts themselves are exact no-ops when fresh:
    h = torch.randn((2, 16, 4, 7), generator=g)
    assert torch.equal(cn.apply_ref_attn(0, h, refs, None), h)
    h = torch.randn((2, 32, 2, 4), generator=g)
    assert torch.equal(cn.apply_ref_attn(3, h, refs, None), h)
    assert torch.equal(cn.noise_embed(torch.tensor([200, 37]), 2), torch.zeros(2, 64))


@torch.no_grad()
def test_ref_attn_is_used_and_skipped_per_row(models):
    cn = models["controlnet"]
    args, fi = _inputs(cn)
    g = torch.Generator().manual_seed(4)
    refs = cn.prepare_references(torch.randn((2, 2, 4, 7, 13), generator=g), fi["pe_cur"], fi["pe_ref"])
    d_ref, m_ref = cn(**args, refs=refs)
    d_no, m_no = cn(**args, refs=None)
    from b2dr_ref import ReferenceInputs

    g = torch.Generator().manual_seed(4)
    raw = ReferenceInputs(torch.randn((2, 2, 4, 7, 13), generator=g), fi["pe_cur"], fi["pe_ref"])
    d_raw, m_raw = cn(**args, refs=raw)
    assert torch.equal(m_raw, m_ref) and all(torch.equal(a, b) for a, b in zip(d_raw, d_ref))
    assert (m_ref - m_no).abs().max() > 1e-3
    # ref_mask with no rows selected == refs None, exactly
    empty = cn.prepare_references(torch.randn((0, 2, 4, 7, 13)), [p[:0] for p in fi["pe_cur"]],
                                  [p[:0] for p in fi["pe_ref"]])
    d_e, m_e = cn(**args, refs=empty, ref_mask=torch.tensor([False, False]))
    assert torch.equal(m_e, m_no) and all(torch.equal(a, b) for a, b in zip(d_e, d_no))
    # Ref-Attn output on selected rows only
    h = torch.randn((2, 16, 4, 7), generator=g)
    one = cn.prepare_references(torch.randn((1, 2, 4, 7, 13), generator=g), [p[:1] for p in fi["pe_cur"]],
                                [p[:1] for p in fi["pe_ref"]])
    out = cn.apply_ref_attn(0, h, one, torch.tensor([False, True]))
    assert torch.equal(out[0], h[0]) and not torch.equal(out[1], h[1])
    assert torch.allclose(out[1:], cn.apply_ref_attn(0, h[1:], one, None), rtol=0, atol=1e-6)


def test_ref_attn_matches_formula(models):
    """Ref-Attn against a direct transcription of contract 2d (explicit softmax, f64)."""
    cn = models["controlnet"]
    g = torch.Generator().manual_seed(8)
    for j in range(4):
        blk = cn.location_block(j)
        c = cn.config.block_out_channels[blk]
        heads = cn.config.attention_head_dim[blk]
        a = cn.ref_attn_modules[j]
        h = torch.randn((2, c, 3, 5), generator=g)
        f = torch.randn((2, 2, c, 3, 5), generator=g)
        pc = torch.randn((2, c, 3, 5), generator=g)
        pr = torch.randn((2, 2, c, 3, 5), generator=g)
        with torch.no_grad():
            got = a(h, f, pc, pr)
            d = c // heads
            dd = lambda t: t.double()  # noqa: E731
            tok = lambda t: dd(t).flatten(2).transpose(1, 2)  # noqa: E731
            nh = torch.nn.functional.group_norm(dd(h), cn.config.norm_num_groups, dd(a.norm.weight), dd(a.norm.bias),
                                                cn.config.norm_eps)
            q = tok(nh + dd(pc)) @ dd(a.to_q.weight).T
            k = torch.cat([tok(f[:, 0] + pr[:, 0]), tok(f[:, 1] + pr[:, 1])], 1) @ dd(a.to_k.weight).T
            v = torch.cat([tok(f[:, 0]), tok(f[:, 1])], 1) @ dd(a.to_v.weight).T
            outs = []
            for hd in range(heads):
                s = slice(hd * d, (hd + 1) * d)
                w = torch.softmax(q[..., s] @ k[..., s].transpose(1, 2) / d ** 0.5, -1)
                outs.append(w @ v[..., s])
            o = torch.cat(outs, -1) @ dd(a.to_out[0].weight).T + dd(a.to_out[0].bias)
            want = dd(h) + o.transpose(1, 2).reshape(2, c, 3, 5)
        assert (got.double() - want).abs().max() < 1e-5


def test_reference_features_shapes(models):
    cn = models["controlnet"]
    with torch.no_grad():
        feats = cn.encode_references(torch.randn((3, 2, 4, 7, 13)))
    assert [tuple(f.shape) for f in feats] == [(3, 2, 16, 4, 7), (3, 2, 16, 2, 4), (3, 2, 32, 2, 4),
                                               (3, 2, 32, 2, 4)]


def test_config_rejects_unknown_key(tmp_path):
    cfg = configs()["controlnet"]
    with pytest.raises(ConfigError, match="unknown key `ref_atn`"):
        B2DRControlNetModel.from_config(dict(cfg, ref_atn=["mid"]))
    with pytest.raises(ConfigError, match="_class_name"):
        B2DRControlNetModel.from_config(dict(cfg, _class_name="ControlNetModel"))
    with pytest.raises(ConfigError, match="must be a subset"):
        B2DRControlNetModel.from_config(dict(cfg, ref_attn=["mid", "down.0"]))
    with pytest.raises(ConfigError, match="unknown"):
        B2DRControlNetModel.from_config(dict(cfg, ref_attn=["down.3"]))
    # in_channels = 2 x the latent channels ([x_t, z_prev]): an odd count cannot be split
    with pytest.raises(ConfigError, match="in_channels"):
        B2DRControlNetModel.from_config(dict(cfg, in_channels=7))
    with pytest.raises(ConfigError, match="conditioning_channels"):
        B2DRControlNetModel.from_config(dict(cfg, conditioning_channels=3))
    with pytest.raises(ConfigError, match="ref_encoder_channels"):
        B2DRControlNetModel.from_config(dict(cfg, ref_encoder_channels=[8, 16, 32]))
    # the previous frame's source: a reference needs the warp (the engine refuses the same)
    with pytest.raises(ConfigError, match="prev_source"):
        B2DRControlNetModel.from_config(dict(cfg, prev_source="carried"))
    for src in ("reference", "composite"):
        with pytest.raises(ConfigError, match="prev_warp_max_depth > 0"):
            B2DRControlNetModel.from_config(dict(cfg, prev_source=src))
        assert B2DRControlNetModel.from_config(dict(cfg, prev_source=src, prev_warp_max_depth=30.0)) \
            .config.prev_source == src
    # a subset of locations works and numbers them in order
    m = B2DRControlNetModel.from_config(dict(cfg, ref_attn=["down.1", "mid"]))
    assert len(m.ref_attn_modules) == 2 and m.location_block(0) == 1
    # from_pretrained names the key and the file
    m.save_pretrained(str(tmp_path))
    p = tmp_path / "config.json"
    d = json.loads(p.read_text())
    assert d["_class_name"] == "B2DRControlNetModel"
    assert set(d) - {"_class_name", "_diffusers_version"} == set(PLAIN_KEYS) | {
        "mask_channels", "prev_noise_level", "prev_noise_max", "prev_blur_sigma", "prev_warp_max_depth",
        "prev_source", "ref_encoder_channels",
        "ref_attn", "pe_depth_num", "pe_depth_start", "pe_position_range", "ref_dropout"}
    d["prev_noise_levl"] = 100
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match=r"config\.json: unknown key `prev_noise_levl`"):
        B2DRControlNetModel.from_pretrained(str(tmp_path))


def test_save_load_roundtrip(tmp_path, models):
    cn = models["controlnet"]
    cn.save_pretrained(str(tmp_path))
    back = B2DRControlNetModel.from_pretrained(str(tmp_path))
    assert back.config_dict() == cn.config_dict()
    a, b = cn.state_dict(), back.state_dict()
    assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)


@torch.no_grad()
def test_from_unet_equals_plain_from_unet(models):
    unet = models["unet"]
    torch.manual_seed(11)  # the conditioning embedding is freshly initialised in both
    cn = B2DRControlNetModel.from_unet(unet, conditioning_embedding_out_channels=[8, 16, 16, 32], pe_depth_num=16)
    torch.manual_seed(11)
    plain = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=[8, 16, 16, 32],
                                      conditioning_channels=15)
    assert cn.config.ref_attn == ["down.0", "down.1", "down.2", "mid"]
    for k, v in plain.state_dict().items():
        got = cn.state_dict()[k]
        assert torch.equal(got[:, :4] if k == "conv_in.weight" else got, v), k
    assert torch.equal(cn.state_dict()["down_blocks.0.resnets.0.conv1.weight"],
                       unet.state_dict()["down_blocks.0.resnets.0.conv1.weight"])
    with pytest.raises(ConfigError, match="unknown key `ref_atn`"):
        B2DRControlNetModel.from_unet(unet, ref_atn=["mid"])
