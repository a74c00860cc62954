"""The nuPlan fixture writer (b2dr_ref.nuplan_fixture): the devkit's tables with 8-byte BLOB tokens that resolve,
20 Hz lidar_pc, camera calibration pickled with the devkit's data_types classes (as its SimplePickleType does) or
as plain lists / numpy arrays, a GeoPackage map laid out under the maps manifest as GPKGMapsDB finds it, whose
geometry blobs parse back."""
import json
import pickle
import sqlite3
import struct

import numpy as np
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
    """Default: the devkit's classes, read back as the devkit reads them (`class_type(pickle.loads(blob))`)."""
    out, s = fixture
    dt = nf.devkit_data_types()
    db = sqlite3.connect(s["db"])
    rows = db.execute("SELECT channel, translation, rotation, intrinsic, distortion FROM camera").fetchall()
    assert [r[0] for r in rows] == nf.CAMERAS
    for (ch, t, q, k, d), cam in zip(rows, s["cameras"]):
        assert type(pickle.loads(t)) is dt.Translation and type(pickle.loads(q)) is dt.Rotation
        assert type(pickle.loads(k)) is dt.CameraIntrinsic and type(pickle.loads(d)) is list
        assert b"nuplan.database.common.data_types" in t and b"Translation" in t
        assert dt.Translation(pickle.loads(t)) == cam["translation"]
        assert dt.CameraIntrinsic(pickle.loads(k)) == cam["intrinsic"]
        assert pickle.loads(d) == cam["distortion"]
    lt, lq = db.execute("SELECT translation, rotation FROM lidar").fetchone()
    assert type(pickle.loads(lt)) is dt.Translation and pickle.loads(lq) == [1.0, 0.0, 0.0, 0.0]
    files = db.execute("SELECT filename_jpg FROM image").fetchall()
    assert len(files) == 8 * s["images_per_camera"]
    for (f,) in files[:5]:
        assert (out / "nuplan-v1.1" / "sensor_blobs" / f).is_file()


@pytest.mark.parametrize("calibration", ["lists", "numpy"])
def test_hand_written_calibration_forms(tmp_path, calibration):
    s = nf.write_fixture(tmp_path, seconds=1.0, png=True, calibration=calibration)
    db = sqlite3.connect(s["db"])
    want = type(np.zeros(1)) if calibration == "numpy" else list
    for t, q, k, d in db.execute("SELECT translation, rotation, intrinsic, distortion FROM camera"):
        assert all(type(pickle.loads(b)) is want for b in (t, q, k, d))
        assert b"data_types" not in t


def test_maps_laid_out_as_gpkg_mapsdb_reads_them(fixture):
    """GPKGMapsDB: `<maps root>/<NUPLAN_MAP_VERSION>.json`, version of the log's map_version, then
    `<map name>/<version>/map.gpkg`; log.location names no folder."""
    out, s = fixture
    db = sqlite3.connect(s["db"])
    location, map_name = db.execute("SELECT location, map_version FROM log").fetchone()
    assert (location, map_name) == ("las_vegas", "us-nv-las-vegas-strip")
    manifest = json.loads((out / "maps" / "nuplan-maps-v1.0.json").read_text())
    version = str(manifest[map_name]["version"])
    assert (out / "maps" / map_name / version / "map.gpkg").is_file()
    assert not (out / "maps" / location).exists()


def test_map_geometries_parse(fixture):
    out, s = fixture
    m = sqlite3.connect(out / "maps" / nf.MAP_NAME / nf.MAP_VERSION / "map.gpkg")
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
