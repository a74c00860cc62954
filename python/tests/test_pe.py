import math

import numpy as np

from b2dr_ref import pe


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def test_bins_and_sizes():
    d = pe.depth_bins(pe.PeConfig())
    assert len(d) == 64 and d[0] == 1.0
    assert abs(d[63] - (1.0 + 60.2 * 63.0 / 65.0)) < 1e-9
    assert pe.latent_block_sizes(400, 224) == pe.LATENT_BLOCK_SIZES
    assert abs(pe.inverse_sigmoid(0.5, 1e-5)) < 1e-12
    assert abs(pe.inverse_sigmoid(2.0, 1e-5) - math.log(1.0 / 1e-5)) < 1e-9
    assert pe.location_sizes(["down.0", "down.1", "mid"], 2, (7, 13)) == [(4, 7), (4, 7), (4, 7)]
    assert pe.location_sizes(["down.0", "down.2", "down.3", "mid"], 4, (28, 50)) == [(14, 25), (4, 7), (4, 7),
                                                                                      (4, 7)]


def test_intrinsic_scaled():
    k = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
    ks = pe.intrinsic_scaled(k, 1600, 900, 400, 224)
    assert abs(ks[0, 0] - 1266.4 / 4) < 1e-12 and abs(ks[1, 1] - 1266.4 * 224 / 900) < 1e-12
    assert abs(ks[0, 2] - ((816.3 + 0.5) / 4 - 0.5)) < 1e-12
    assert abs(ks[1, 2] - ((491.5 + 0.5) * 224 / 900 - 0.5)) < 1e-12


def test_pe_matches_formula():
    """position_encoding against a vectorised transcription of the formula (centre and PETR grids)."""
    cfg = pe.PeConfig(depth_num=8)
    k = np.array([[50.0, 0.0, 51.5], [0.0, 48.0, 27.5], [0.0, 0.0, 1.0]])
    cam2ego = np.array([[0.0, 0.0, 1.0, 1.5], [-1.0, 0.0, 0.0, 0.1], [0.0, -1.0, 0.0, 1.6], [0, 0, 0, 1.0]])
    ego_img = _rot_z(0.3)
    ego_img[:3, 3] = [10.0, -4.0, 0.2]
    ego_cur = _rot_z(0.25)
    ego_cur[:3, 3] = [14.0, -3.0, 0.1]
    m = pe.cam2cur(cam2ego, ego_img, ego_cur)
    assert np.allclose(m, np.linalg.inv(ego_cur) @ ego_img @ cam2ego)
    h, w, W, H = 4, 7, 104, 56
    d = np.array(pe.depth_bins(cfg))
    lo = np.array(cfg.position_range[:3])
    span = np.array(cfg.position_range[3:]) - lo
    for grid in (pe.PixelGrid.CENTRE, pe.PixelGrid.PETR_CORNER):
        cfg.grid = grid
        got = pe.position_encoding(k, W, H, m, h, w, cfg)
        assert got.shape == (3 * 8, h, w) and got.dtype == np.float32
        if grid == pe.PixelGrid.CENTRE:
            u = (np.arange(w) + 0.5) * W / w - 0.5
            v = (np.arange(h) + 0.5) * H / h - 0.5
        else:
            u = np.arange(w) * W / w
            v = np.arange(h) * H / h
        uu, vv = np.meshgrid(u, v)  # (h, w)
        cam = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], -1)  # z = 1
        pts = cam[None] * d[:, None, None, None]  # (D, h, w, 3)
        p = pts @ m[:3, :3].T + m[:3, 3]
        x = np.clip((p - lo) / span, 0, 1)
        inv = np.log(np.maximum(x, 1e-5) / np.maximum(1 - x, 1e-5))  # (D, h, w, 3)
        want = inv.transpose(0, 3, 1, 2).reshape(3 * 8, h, w)  # channel d * 3 + axis
        assert np.abs(got - want).max() < 1e-5


def test_pe_inputs_layout():
    cfg = pe.PeConfig(depth_num=4)
    k = np.array([[30.0, 0.0, 23.5], [0.0, 30.0, 15.5], [0.0, 0.0, 1.0]])
    cams = [pe.CameraGeometry(k, np.eye(4)), pe.CameraGeometry(k, _rot_z(1.0))]
    cur = np.eye(4)
    refs = [(_rot_z(0.1), _rot_z(-0.1))] * 2
    pc, pr = pe.pe_inputs(cams, (32, 48), cur, refs, ["down.0", "mid"], 2, cfg)
    assert [a.shape for a in pc] == [(2, 12, 2, 3), (2, 12, 2, 3)]
    assert [a.shape for a in pr] == [(2, 2, 12, 2, 3), (2, 2, 12, 2, 3)]
    want = pe.position_encoding(k, 48, 32, pe.cam2cur(_rot_z(1.0), _rot_z(-0.1), cur), 2, 3, cfg)
    assert np.array_equal(pr[1][1, 1], want)


def test_position_encodings_for_blocks():
    cfg = pe.PeConfig(depth_num=2)
    k = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
    out = pe.position_encodings_for_blocks(k, 1600, 900, 400, 224, np.eye(4), cfg)
    assert [(h, w) for h, w, _ in out] == pe.LATENT_BLOCK_SIZES
    ks = pe.intrinsic_scaled(k, 1600, 900, 400, 224)
    assert np.array_equal(out[3][2], pe.position_encoding(ks, 400, 224, np.eye(4), 4, 7, cfg))
