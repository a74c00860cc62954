"""Round trip of ``b2dr export-training`` through python/b2dr_ref/dataset.py.

Runs the release (else debug) b2dr binary of this checkout to export a tiny set; skips with a printed reason
when neither binary exists (build one with ``cargo build --release``).
"""
import os
import subprocess
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.dirname(HERE))

from b2dr_ref.dataset import TrainingSet, unpack_masks  # noqa: E402


def _binary():
    for kind in ("release", "debug"):
        p = os.path.join(REPO, "target", kind, "b2dr")
        if os.path.isfile(p) and os.access(p, os.X_OK):
            return p
    return None


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory):
    exe = _binary()
    if exe is None:
        reason = f"no b2dr binary under {REPO}/target/(release|debug); run cargo build --release"
        print("SKIP:", reason)
        pytest.skip(reason)
    out = str(tmp_path_factory.mktemp("export"))
    cmd = [
        exe, "export-training", "--scenario", "builtin:straight:1", "builtin:town:2",
        "--out", out, "--size", "24x40", "--samples-per-scenario", "2",
        "--offsets", "0,0,0;0,-1.5,4", "--cameras", "CAM_FRONT,CAM_BACK",
        "--shard-samples", "3", "--seed", "5", "--quiet",
    ]
    subprocess.run(cmd, check=True)
    return out


def test_round_trip(export_dir):
    ds = TrainingSet(export_dir)
    assert len(ds) == 8
    assert len(ds.index["shards"]) == 3
    assert ds.cameras == ["CAM_FRONT", "CAM_BACK"]
    assert ds.mask_channels[10] == "drivable_area" and len(ds.mask_channels) == 15
    seen_perturbed = False
    for i, s in enumerate(ds):
        meta = ds.samples[i]
        assert s["target"].shape == (2, 3, 24, 40) and s["target"].dtype == np.uint8
        assert s["prev"].shape == (2, 3, 24, 40)
        assert s["ref"].shape == (2, 2, 3, 24, 40)
        assert s["masks"].shape == (2, 15, 24, 40) and set(np.unique(s["masks"])) <= {0, 1}
        assert s["masks"][:, 10].sum() > 0, "drivable area visible"
        assert s["intrinsics"].shape == (2, 3, 3) and s["intrinsics"].dtype == np.float64
        assert s["ego2global"].shape == (2, 4, 4) and s["ref_ego2global"].shape == (2, 2, 4, 4)
        assert s["step"] == meta["step"] and s["prev_step"] == meta["step"] - 5
        np.testing.assert_allclose(s["offset"], meta["offset"])
        for c in range(2):
            for r in range(2):
                ref = meta["refs"][c][r]
                assert s["ref_step"][c, r] == ref["step"]
                assert abs(s["ref_distance"][c, r] - ref["distance"]) < 1e-4
                assert 2.0 <= abs(ref["distance"]) < 15.0
        # The PE's cam2cur of a reference is a rigid transform whose translation is its offset in the ego frame.
        rot = s["cam2cur_ref"][..., :3, :3]
        np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
        if not s["perturbed"]:
            # The logged pose: the along-heading distance of each reference is its x in the current ego frame.
            rel = np.linalg.inv(s["ego2global"])[:, None] @ s["ref_ego2global"]
            np.testing.assert_allclose(rel[..., 0, 3], s["ref_distance"], atol=1e-3)
            np.testing.assert_allclose(s["intrinsics"][:, 2, 2], 1.0)
        else:
            seen_perturbed = True
        assert s["target"].std() > 5.0, "a real image, not a constant"
    assert seen_perturbed


def test_unpack_masks():
    packed = np.array([[[1 | (1 << 14), 0], [2, 1 << 7]]], dtype=np.uint16)
    m = unpack_masks(packed)
    assert m.shape == (1, 15, 2, 2)
    assert m[0, 0, 0, 0] == 1 and m[0, 14, 0, 0] == 1 and m[0, 1, 1, 0] == 1 and m[0, 7, 1, 1] == 1
    assert m.sum() == 4


def test_torch_optional(export_dir):
    torch = pytest.importorskip("torch")
    from b2dr_ref.dataset import to_torch

    t = to_torch(TrainingSet(export_dir)[0])
    assert isinstance(t["target"], torch.Tensor) and t["target"].dtype == torch.float32
    assert float(t["target"].max()) <= 1.0


def test_self_prev_pose_partners_on_an_export(export_dir):
    """train --self-prev-pose other renders a sample's frame at another ego offset: on a real export every sample
    index (frame row x cameras + camera) has partners at the same scenario, step and camera and another offset, and
    they share the previous frame (the image itself)."""
    from b2dr_ref.training.data import DatasetSource
    from b2dr_ref.training.selfprev import pose_partners

    src = DatasetSource(export_dir)
    parts = pose_partners(src)
    assert parts is not None and len(parts) == len(src) == 16
    rows = src.ds.samples
    for i, ps in enumerate(parts):
        f, c = divmod(i, 2)
        assert len(ps) == 1                      # two offsets per frame in this export
        for j in ps:
            g, d = divmod(j, 2)
            assert d == c and g != f
            assert (rows[g]["scenario"], rows[g]["step"]) == (rows[f]["scenario"], rows[f]["step"])
            assert rows[g]["offset"] != rows[f]["offset"]
            np.testing.assert_array_equal(src[i].prev, src[j].prev)
            assert not np.array_equal(src[i].masks, src[j].masks)


def test_prev_chain_export_holds_the_previous_frames_inputs(export_dir, tmp_path):
    """``--prev-chain``: each sample also holds ``prev2`` (the log's image 0.5 s before its previous frame) and
    ``prev_masks`` (the previous frame's layout). Where the export drew the previous frame itself as a target (same
    scenario, target step = this prev_step, logged pose), those equal that sample's own ``prev`` and ``masks``,
    which the export computes through the target path. A plain export has neither."""
    exe = _binary()
    assert exe is not None       # export_dir skipped otherwise
    out = str(tmp_path / "chain")
    subprocess.run([exe, "export-training", "--scenario", "builtin:straight:1", "--out", out, "--size", "24x40",
                    "--samples-per-scenario", "40", "--cameras", "CAM_FRONT", "--seed", "3", "--prev-chain",
                    "--quiet"], check=True)
    ds = TrainingSet(out)
    assert ds.prev_chain and not TrainingSet(export_dir).prev_chain
    assert "prev2" not in TrainingSet(export_dir)[0]
    by_step = {}
    samples = [ds[i] for i in range(len(ds))]
    for s in samples:
        assert s["prev2"].shape == (1, 3, 24, 40) and s["prev2"].dtype == np.uint8
        assert s["prev_masks"].shape == (1, 15, 24, 40) and set(np.unique(s["prev_masks"])) <= {0, 1}
        assert s["prev2_step"] == s["prev_step"] - 5 and s["prev_step"] == s["step"] - 5
        assert s["prev2_ego2global"].shape == (1, 4, 4) and s["prev2_ego2global"].dtype == np.float64
        assert not np.array_equal(s["prev2"], s["prev"])
        by_step[s["step"]] = s
    pairs = 0
    for s in samples:
        p = by_step.get(s["prev_step"])
        if p is None:
            continue
        pairs += 1
        np.testing.assert_array_equal(s["prev_masks"], p["masks"])
        np.testing.assert_array_equal(s["prev2"], p["prev"])
        np.testing.assert_array_equal(s["prev_ego2global"], p["ego2global"])
        np.testing.assert_array_equal(s["prev2_ego2global"], p["prev_ego2global"])     # prev2's pose: the log's
    assert pairs >= 3, f"only {pairs} samples whose previous frame is a target too"
