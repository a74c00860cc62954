"""The nuScenes fixture writer (b2dr_ref.nuscenes_fixture): official table layout, resolvable tokens, values
taken from the shared data. Skips when the shared nuScenes-mini data is absent."""
import json
import math
import re
from pathlib import Path

import pytest

from b2dr_ref import nuscenes_fixture as nf

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "nuscenes-mini"
if not SHARED.exists():
    SHARED = Path("/work/shared/data/nuscenes-mini")


@pytest.fixture(scope="module")
def fixture(tmp_path_factory):
    if not (SHARED / "scenes" / "scene-0061.json").exists():
        pytest.skip(f"shared nuScenes data absent ({SHARED})")
    out = tmp_path_factory.mktemp("nuscenes")
    summary = nf.write_fixture(SHARED, out)
    tables = {p.stem: json.loads(p.read_text()) for p in (out / "v1.0-mini").glob("*.json")}
    return out, summary, tables


def test_tables_and_tokens(fixture):
    out, summary, t = fixture
    assert sorted(t) == sorted(["scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                                "sample_annotation", "instance", "category", "log", "map", "attribute",
                                "visibility"])
    hexre = re.compile(r"^[0-9a-f]{32}$")
    for name, rows in t.items():
        if name == "visibility":
            continue
        for r in rows:
            assert hexre.match(r["token"]), (name, r["token"])
        assert len({r["token"] for r in rows}) == len(rows), name
    idx = {name: {r["token"]: r for r in rows} for name, rows in t.items()}
    for sd in t["sample_data"]:
        assert sd["sample_token"] in idx["sample"]
        assert sd["ego_pose_token"] in idx["ego_pose"]
        assert sd["calibrated_sensor_token"] in idx["calibrated_sensor"]
        for k in ("prev", "next"):
            assert sd[k] == "" or sd[k] in idx["sample_data"]
    for a in t["sample_annotation"]:
        assert a["sample_token"] in idx["sample"] and a["instance_token"] in idx["instance"]
        assert a["visibility_token"] in idx["visibility"]
    for i in t["instance"]:
        assert i["category_token"] in idx["category"]
        assert idx["sample_annotation"][i["first_annotation_token"]]["prev"] == ""
    sc = t["scene"][0]
    assert sc["name"] == "scene-0061" and sc["nbr_samples"] == summary["samples"] == 39
    # Samples chain from first to last at 2 Hz.
    s, n = idx["sample"][sc["first_sample_token"]], 1
    while s["next"]:
        nxt = idx["sample"][s["next"]]
        assert nxt["timestamp"] - s["timestamp"] == 500000
        s, n = nxt, n + 1
    assert n == 39 and s["token"] == sc["last_sample_token"]


def test_values_follow_the_shared_data(fixture):
    out, summary, t = fixture
    scene = json.loads((SHARED / "scenes" / "scene-0061.json").read_text())
    frame = json.loads((SHARED / "keyframe-scene-0061" / "frame.json").read_text().replace("NaN", "null"))
    samples = {r["token"]: j for j, r in enumerate(t["sample"])}
    for a in t["sample_annotation"]:
        st = scene["tracks"][a["instance_token"]]["state"]
        k = samples[a["sample_token"]] * 5
        w, l, h = a["size"]
        assert (w, l, h) == (st["width"][k][0], st["length"][k][0], st["height"][k][0])
        assert a["translation"] == st["position"][k]
        q = a["rotation"]
        yaw = 2 * math.atan2(q[3], q[0])
        assert abs(nf.wrap(yaw - st["heading"][k])) < 1e-12
    sensors = {r["token"]: r["channel"] for r in t["sensor"]}
    calib = {r["token"]: r for r in t["calibrated_sensor"]}
    poses = {r["token"]: r for r in t["ego_pose"]}
    first = t["sample"][0]["token"]
    n_cam = 0
    for sd in t["sample_data"]:
        cs = calib[sd["calibrated_sensor_token"]]
        ch = sensors[cs["sensor_token"]]
        if ch == "LIDAR_TOP" or sd["sample_token"] != first:
            continue
        cam = frame["cameras"][ch]
        assert sd["timestamp"] == cam["timestamp_us"] and sd["is_key_frame"]
        assert cs["camera_intrinsic"] == cam["intrinsic"]
        assert cs["translation"] == [cam["cam2ego"][i][3] for i in range(3)]
        assert poses[sd["ego_pose_token"]]["translation"] == [cam["ego2global"][i][3] for i in range(3)]
        assert (out / sd["filename"]).read_bytes() == (SHARED / "keyframe-scene-0061" / cam["image"]).read_bytes()
        n_cam += 1
    assert n_cam == 6


def test_rotation_matrix_roundtrip():
    for yaw, pitch in [(0.3, 0.0), (-2.9, 0.02), (3.1, -0.01)]:
        cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
        r = [[cy * cp, -sy, cy * sp], [sy * cp, cy, sy * sp], [-sp, 0.0, cp]]
        w, x, y, z = nf.mat_to_quat(r)
        back = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
        assert max(abs(back[i][j] - r[i][j]) for i in range(3) for j in range(3)) < 1e-12


def test_map_expansion(fixture):
    out, summary, t = fixture
    m = json.loads((out / "maps" / "expansion" / "singapore-onenorth.json").read_text())
    assert m["version"] >= "1.3"
    nodes = {n["token"] for n in m["node"]}
    polys = {p["token"]: p for p in m["polygon"]}
    for layer in ("lane", "lane_connector"):
        assert m[layer], layer
        for r in m[layer]:
            assert all(n in nodes for n in polys[r["polygon_token"]]["exterior_node_tokens"])
            arcs = m["arcline_path_3"][r["token"]]
            assert arcs and all(a["shape"] in ("LSL", "LSR", "RSL", "RSR", "LRL", "RLR") for a in arcs)
    lanes = {r["token"] for r in m["lane"]} | {r["token"] for r in m["lane_connector"]}
    for tok, c in m["connectivity"].items():
        for o in c["outgoing"]:
            assert o in lanes and tok in m["connectivity"][o]["incoming"]
    assert sum(len(c["outgoing"]) for c in m["connectivity"].values()) > 100
    da = m["drivable_area"][0]["polygon_tokens"]
    assert da and all(p in polys for p in da)
    assert m["lane_divider"] and m["road_divider"]
    # stop lines: a quadrilateral polygon each, across the end of a lane leading into a connector
    connectors = {r["token"] for r in m["lane_connector"]}
    assert len(m["stop_line"]) > 10
    for sl in m["stop_line"]:
        assert sl["stop_line_type"] == "TURN_STOP" and len(polys[sl["polygon_token"]]["exterior_node_tokens"]) == 4
    assert connectors


def test_camera_sweeps(tmp_path):
    if not (SHARED / "scenes" / "scene-0061.json").exists():
        pytest.skip(f"shared nuScenes data absent ({SHARED})")
    nf.write_fixture(SHARED, tmp_path, camera_sweeps=True)
    t = {n: json.loads((tmp_path / "v1.0-mini" / f"{n}.json").read_text()) for n in ("sample", "sample_data")}
    ts = {r["token"]: r["timestamp"] for r in t["sample"]}
    sweeps = [sd for sd in t["sample_data"] if not sd["is_key_frame"] and sd["fileformat"] == "jpg"]
    assert len(sweeps) == 38 * 5 * 6
    for sd in sweeps:
        # A sweep belongs to the sample that follows it, within one sample period.
        assert 0 < ts[sd["sample_token"]] - sd["timestamp"] < 500000
        assert (tmp_path / sd["filename"]).is_file()


def test_without_the_map_expansion(tmp_path):
    """--no-map-expansion: the main download's layout alone (tables, images), no maps/expansion folder."""
    if not (SHARED / "scenes" / "scene-0061.json").exists():
        pytest.skip(f"shared nuScenes data absent ({SHARED})")
    nf.write_fixture(SHARED, tmp_path, map_expansion=False)
    assert (tmp_path / "v1.0-mini" / "sample_data.json").is_file()
    assert not (tmp_path / "maps" / "expansion").exists()
