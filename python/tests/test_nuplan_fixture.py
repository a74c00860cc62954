"""The nuPlan fixture writer (b2dr_ref.nuplan_fixture): the devkit's tables with 8-byte BLOB tokens that resolve,
20 Hz lidar_pc, pickled camera calibration, a GeoPackage map whose geometry blobs parse back."""
import json
import pickle
import sqlite3
import struct

import pytest

from b2dr_ref import nuplan_fixture as nf


@pytest.fixture(scope="module")
def fixture(tmp_path_factory):
    out = tmp_path_factory.mktemp("nuplan")
    summary = nf.write_fixture(out, seconds=4.0, png=True)
    return out, summary


def test_tables_tokens_and_rates(fixture):
    out, s = fixture
    db = sqlite3.connect(s["db"])
    tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    assert {"log", "ego_pose", "lidar_pc", "lidar", "lidar_box", "track", "category", "scene", "scenario_tag",
            "traffic_light_status", "camera", "image"} <= tables
    for t in tables:
        for (tok,) in db.execute(f"SELECT token FROM {t}"):
            assert isinstance(tok, bytes) and len(tok) == 8, t
    # two scenes, the devkit's space-separated roadblock ids, goals are ego poses
    scenes = db.execute("SELECT token, roadblock_ids, goal_ego_pose_token FROM scene ORDER BY name").fetchall()
    assert [r[1] for r in scenes] == ["1 2 3", "3 7"]
    assert all(db.execute("SELECT count(*) FROM ego_pose WHERE token = ?", (r[2],)).fetchone()[0] == 1 for r in scenes)
    assert db.execute("SELECT count(DISTINCT scene_token) FROM lidar_pc").fetchone()[0] == 2
    ts = [r[0] for r in db.execute("SELECT timestamp FROM lidar_pc ORDER BY timestamp")]
    assert len(ts) == 81 and all(b - a == 50_000 for a, b in zip(ts, ts[1:]))
    # Foreign keys resolve.
    assert db.execute("SELECT count(*) FROM lidar_pc WHERE ego_pose_token NOT IN (SELECT token FROM ego_pose)"
                      ).fetchone()[0] == 0
    assert db.execute("SELECT count(*) FROM lidar_box WHERE track_token NOT IN (SELECT token FROM track)"
                      ).fetchone()[0] == 0
    assert db.execute("SELECT count(*) FROM image WHERE camera_token NOT IN (SELECT token FROM camera)"
                      ).fetchone()[0] == 0
    # next/prev chains of boxes follow a track.
    n = db.execute("SELECT count(*) FROM lidar_box a JOIN lidar_box b ON a.next_token = b.token "
                   "WHERE a.track_token != b.track_token").fetchone()[0]
    assert n == 0


def test_camera_calibration_is_pickled(fixture):
    out, s = fixture
    db = sqlite3.connect(s["db"])
    rows = db.execute("SELECT channel, translation, rotation, intrinsic, distortion FROM camera").fetchall()
    assert [r[0] for r in rows] == nf.CAMERAS
    for ch, t, q, k, d in rows:
        assert len(pickle.loads(t)) == 3 and len(pickle.loads(q)) == 4
        assert pickle.loads(k).shape == (3, 3) and pickle.loads(d).shape == (5,)
    files = db.execute("SELECT filename_jpg FROM image").fetchall()
    assert len(files) == 8 * s["images_per_camera"]
    for (f,) in files[:5]:
        assert (out / "nuplan-v1.1" / "sensor_blobs" / f).is_file()


def test_map_geometries_parse(fixture):
    out, s = fixture
    m = sqlite3.connect(out / "maps" / nf.LOCATION / nf.MAP_VERSION / "map.gpkg")
    layers = {r[0] for r in m.execute("SELECT table_name FROM gpkg_contents")}
    assert {"lanes_polygons", "lane_connectors", "baseline_paths", "lane_groups_polygons", "intersections",
            "crosswalks", "stop_polygons", "meta"} <= layers
    for (blob,) in m.execute("SELECT geom FROM baseline_paths"):
        assert blob[:2] == b"GP"
        flags = blob[3]
        env = {0: 0, 1: 32}[(flags >> 1) & 7]
        order, kind = struct.unpack_from("<BI", blob, 8 + env)
        assert (order, kind) == (1, 2)
    ex = json.loads((out / "expected.json").read_text())
    assert len(ex["steps"]) == 41


def test_projection_published_point_and_inverse():
    # The CN Tower (43 38' 33.24" N, 79 23' 13.7" W) is at 17T 630084 E 4833438 N (zone 17: lon0 = -81).
    x, y = nf.tm_forward(-(79 + 23 / 60 + 13.7 / 3600), 43 + 38 / 60 + 33.24 / 3600, lon0=-81.0)
    assert abs(x - 630084) < 1 and abs(y - 4833438) < 1
    lon, lat = nf.tm_inverse(nf.X0 + 12.3, nf.Y0 - 4.5)
    fx, fy = nf.tm_forward(lon, lat)
    assert abs(fx - nf.X0 - 12.3) < 1e-8 and abs(fy - nf.Y0 + 4.5) < 1e-8
