"""A nuScenes-mini-style dataset folder written from the shared real data (docs/nuscenes.md, "Test fixture").

The real nuScenes tables cannot be shipped here, so tests build a small, faithful stand-in at test time, into a
temporary folder, from `../shared/data/nuscenes-mini` (licence CC BY-NC-SA 4.0: nothing of it enters the repo):

    DATAROOT/v1.0-mini/{scene,sample,sample_data,ego_pose,calibrated_sensor,sensor,sample_annotation,
                        instance,category,log,map,attribute,visibility}.json
    DATAROOT/samples/CAM_*/<logfile>__<CAM>__<timestamp>.jpg
    DATAROOT/maps/expansion/<map>.json        (map-expansion v1.3 subset)

Table layouts follow nutonomy/nuscenes-devkit docs/schema_nuscenes.md; the map follows map_expansion/map_api.py
(geometric layers node / line / polygon, lane / lane_connector / drivable_area / ped_crossing / lane_divider /
road_divider records, `arcline_path_3`, `connectivity`). Where the values come from:

- samples: one per 0.5 s of the ScenarioNet log (`scenes/<scene>.json`, 10 Hz; keyframes are the steps k = 5j),
  timestamps `T0 + 500000 j` us with `T0` the scene's first LIDAR_TOP keyframe time;
- sample_annotation: every non-ego track valid at a keyframe step: `translation` = its box centre (x, y, z),
  `size` = [width, length, height] (nuScenes order), `rotation` = the heading as a quaternion w, x, y, z about +z;
  instance tokens are the ScenarioNet track ids (they are the nuScenes instance tokens);
- ego_pose: one per sample_data. LIDAR_TOP sample_data run at 20 Hz with poses interpolated from the ScenarioNet
  ego track (linear position, shortest-angle heading; z = 0). The six keyframe camera sample_data of the first
  sample carry the real calibration and per-camera ego pose of `keyframe-scene-0061/frame.json`; later camera
  keyframes keep each camera's real time offset from the lidar and take the interpolated ego track;
- calibrated_sensor: intrinsics and cam2ego of frame.json (translation + quaternion w, x, y, z); LIDAR_TOP gets
  a nominal mounting (it is not used by b2dr);
- camera sweeps (`camera_sweeps=True` only): non-key camera sample_data at 12 Hz between the keyframes
  (`sweeps/CAM_*/...`, each belonging to the sample that follows it, as in nuScenes), interpolated ego poses;
- images: the six real JPEGs of frame.json are copied to the first sample's files; later samples' files are
  symbolic links to them (same pixels: only the first keyframe's images are real) unless `images="copy"`;
- map: the scene's ScenarioNet lanes (with polygon) become `lane`, those without become `lane_connector` (polygon:
  the centre line buffered by 1.75 m each side), centre lines become straight `arcline_path_3` pieces, links are
  inferred from geometry (end within 1 m of a start, headings within 30 degrees) into `connectivity`;
  ROAD_LINE_BROKEN_SINGLE_WHITE -> lane_divider, ROAD_LINE_SOLID_SINGLE_YELLOW -> road_divider; a `stop_line`
  (TURN_STOP, a quadrilateral 1 m deep) across the end of every lane leading into a connector; the drivable area is
  `maps/<map>.drivable_area.geojson` cropped to 300 m around the scene.
- `--no-map-expansion`: the dataset as the main nuScenes download alone lays it out (the map expansion pack is a
  separate download, which the devkit needs only for its map API): no `maps/expansion/` folder at all.

Only the Python standard library is needed (`python3 -m b2dr_ref.nuscenes_fixture --shared DIR --out DIR`).
"""
import argparse
import hashlib
import json
import math
import os
import shutil
from pathlib import Path

CAMERAS = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
# scene-0061's first LIDAR_TOP keyframe (= its first sample's timestamp, us) and its log.
T0_US = {"scene-0061": 1532402927647951}
LOGFILE = {"scene-0061": "n015-2018-07-24-11-22-45+0800"}
KEY_EVERY = 5  # ScenarioNet steps (10 Hz) per sample (2 Hz)
CATEGORIES = [
    "animal", "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility", "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone", "static_object.bicycle_rack",
    "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction",
    "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer",
    "vehicle.truck",
]
ATTRIBUTES = [
    "vehicle.moving", "vehicle.stopped", "vehicle.parked", "cycle.with_rider", "cycle.without_rider",
    "pedestrian.sitting_lying_down", "pedestrian.standing", "pedestrian.moving",
]
VISIBILITY = [("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100")]
LIDAR_CALIB = ([0.943713, 0.0, 1.84023], [0.7077955119163518, -0.006492242056004365, 0.010646214713995808,
                                          -0.7063073142877817])
CONNECTOR_HALF_WIDTH = 1.75
LINK_GAP_M, LINK_HEADING_RAD = 1.0, math.radians(30.0)
DRIVABLE_MARGIN_M = 300.0
STOP_LINE_DEPTH_M = 1.0


def token(*parts) -> str:
    """A stable 32-hex token (nuScenes tokens are 32 lowercase hex digits)."""
    return hashlib.md5("|".join(str(p) for p in parts).encode()).hexdigest()


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def yaw_quat(yaw: float):
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def mat_to_quat(r):
    """Rotation matrix (3x3 rows) -> unit quaternion [w, x, y, z] (Shepperd's method, w >= 0)."""
    t = r[0][0] + r[1][1] + r[2][2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2]) * 2
        q = [(r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    elif r[1][1] > r[2][2]:
        s = math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2]) * 2
        q = [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s]
    else:
        s = math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1]) * 2
        q = [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s]
    if q[0] < 0:
        q = [-v for v in q]
    n = math.sqrt(sum(v * v for v in q))
    return [v / n for v in q]


def pose_of_matrix(m):
    """4x4 row-major -> (translation [3], rotation [w, x, y, z])."""
    return [m[0][3], m[1][3], m[2][3]], mat_to_quat([row[:3] for row in m[:3]])


class EgoTrack:
    """The ScenarioNet ego track (rear axle, 10 Hz), interpolated in time (linear, shortest-angle heading)."""

    def __init__(self, track, t0_us: int, dt_us: int = 100000):
        st = track["state"]
        self.pos = [p[:2] for p in st["position"]]
        self.head = list(st["heading"])
        self.t0, self.dt = t0_us, dt_us

    def at(self, t_us: int):
        f = (t_us - self.t0) / self.dt
        n = len(self.pos)
        if f <= 0:
            i, a = 0, 0.0
        elif f >= n - 1:
            i, a = n - 2, 1.0
        else:
            i = int(math.floor(f))
            a = f - i
        p0, p1 = self.pos[i], self.pos[i + 1]
        h = self.head[i] + a * wrap(self.head[i + 1] - self.head[i])
        return [p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), 0.0], yaw_quat(wrap(h))


def _buffer(points, half):
    """Outline of a centre line buffered by `half` metres (left side forward, right side back)."""
    left, right = [], []
    n = len(points)
    for i in range(n):
        a = points[max(i - 1, 0)]
        b = points[min(i + 1, n - 1)]
        dx, dy = b[0] - a[0], b[1] - a[1]
        norm = math.hypot(dx, dy) or 1.0
        nx, ny = -dy / norm * half, dx / norm * half
        left.append([points[i][0] + nx, points[i][1] + ny])
        right.append([points[i][0] - nx, points[i][1] - ny])
    return left + right[::-1]


def _distinct(points):
    out = []
    for p in points:
        if not out or math.hypot(p[0] - out[-1][0], p[1] - out[-1][1]) > 1e-6:
            out.append([float(p[0]), float(p[1])])
    return out


class MapWriter:
    """Geometric layers (node / line / polygon) with stable tokens, and the records that use them."""

    def __init__(self):
        self.node, self.line, self.polygon = [], [], []

    def nodes(self, key, pts):
        toks = []
        for i, p in enumerate(pts):
            t = token("node", key, i)
            self.node.append({"token": t, "x": p[0], "y": p[1]})
            toks.append(t)
        return toks

    def add_line(self, key, pts):
        t = token("line", key)
        self.line.append({"token": t, "node_tokens": self.nodes(("l", key), pts)})
        return t

    def add_polygon(self, key, exterior, holes=()):
        t = token("polygon", key)
        self.polygon.append({
            "token": t,
            "exterior_node_tokens": self.nodes(("pe", key), exterior),
            "holes": [{"node_tokens": self.nodes(("ph", key, k), h)} for k, h in enumerate(holes)],
        })
        return t


def arclines(points):
    """A centre line as straight arcline paths (shape LSL with zero-length arcs), one per segment."""
    out = []
    for a, b in zip(points, points[1:]):
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        out.append({
            "start_pose": [a[0], a[1], yaw], "end_pose": [b[0], b[1], yaw], "shape": "LSL", "radius": 999.0,
            "segment_length": [0.0, math.hypot(b[0] - a[0], b[1] - a[1]), 0.0],
        })
    return out


def infer_links(lanes):
    """(from, to) pairs: the end of `from` within 1 m of the start of `to`, end/start headings within 30 deg."""
    cell = 5.0
    starts = {}
    for k, (tok, pts) in enumerate(lanes):
        starts.setdefault((math.floor(pts[0][0] / cell), math.floor(pts[0][1] / cell)), []).append(k)

    def heading(p, q):
        return math.atan2(q[1] - p[1], q[0] - p[0])

    links = []
    for i, (tok, pts) in enumerate(lanes):
        end = pts[-1]
        h_end = heading(pts[-2], pts[-1])
        cx, cy = math.floor(end[0] / cell), math.floor(end[1] / cell)
        for gx in (cx - 1, cx, cx + 1):
            for gy in (cy - 1, cy, cy + 1):
                for j in starts.get((gx, gy), []):
                    if j == i:
                        continue
                    q = lanes[j][1]
                    if math.hypot(q[0][0] - end[0], q[0][1] - end[1]) <= LINK_GAP_M and abs(
                            wrap(heading(q[0], q[1]) - h_end)) <= LINK_HEADING_RAD:
                        links.append((i, j))
    return sorted(links)


def expansion_map(scene, drivable_geojson, centre):
    """The map-expansion JSON (v1.3 layers) of the scene's map features and the cropped drivable area."""
    mw = MapWriter()
    lane, connector, lane_div, road_div = [], [], [], []
    centres = []
    arc = {}
    for fid in sorted(scene["map_features"]):
        f = scene["map_features"][fid]
        ty = f["type"]
        if ty.startswith("LANE_"):
            pts = _distinct(f["polyline"])
            if len(pts) < 2:
                continue
            centres.append((fid, pts))
            arc[fid] = arclines(pts)
            if "polygon" in f and len(f["polygon"]) >= 3:
                ring = _distinct(f["polygon"])
                pt = mw.add_polygon(fid, ring)
                # Edge lines across the lane's start and end (the record's from/to edges).
                lane.append({
                    "token": fid, "polygon_token": pt, "lane_type": "CAR",
                    "from_edge_line_token": mw.add_line(("from", fid), _edge(pts[0], pts[1])),
                    "to_edge_line_token": mw.add_line(("to", fid), _edge(pts[-1], pts[-2], flip=True)),
                    "left_lane_divider_segments": [], "right_lane_divider_segments": [],
                })
            else:
                pt = mw.add_polygon(fid, _buffer(pts, CONNECTOR_HALF_WIDTH))
                connector.append({"token": fid, "polygon_token": pt})
        elif ty == "ROAD_LINE_BROKEN_SINGLE_WHITE":
            pts = _distinct(f["polyline"])
            lt = mw.add_line(fid, pts)
            lane_div.append({"token": fid, "line_token": lt, "road_segment_token": "",
                             "lane_divider_segments": [{"node_token": n, "segment_type": "SINGLE_DASHED_WHITE"}
                                                       for n in mw.line[-1]["node_tokens"]]})
        elif ty == "ROAD_LINE_SOLID_SINGLE_YELLOW":
            road_div.append({"token": fid, "line_token": mw.add_line(fid, _distinct(f["polyline"])),
                             "road_segment_token": ""})
    connectivity = {tok: {"incoming": [], "outgoing": []} for tok, _ in centres}
    for i, j in infer_links(centres):
        connectivity[centres[i][0]]["outgoing"].append(centres[j][0])
        connectivity[centres[j][0]]["incoming"].append(centres[i][0])
    # Stop lines (ScenarioNet's conversion keeps none): a TURN_STOP line across the end of every lane that leads
    # into a connector, a quadrilateral 1 m deep ending at the lane's end.
    connectors = {c["token"] for c in connector}
    stop = []
    for fid, pts in centres:
        if fid in connectors or not any(o in connectors for o in connectivity[fid]["outgoing"]):
            continue
        (ex, ey), (px, py) = pts[-1], pts[-2]
        d = math.hypot(ex - px, ey - py) or 1.0
        back = [ex - (ex - px) / d * STOP_LINE_DEPTH_M, ey - (ey - py) / d * STOP_LINE_DEPTH_M]
        a, b = _edge(pts[-1], pts[-2], flip=True)
        c, e = _edge(back, pts[-2], flip=True)
        pt = mw.add_polygon(("stop", fid), [a, b, e, c])
        stop.append({"token": token("stop_line", fid), "polygon_token": pt, "stop_line_type": "TURN_STOP",
                     "ped_crossing_tokens": [], "traffic_light_tokens": [], "road_block_token": ""})
    polys = drivable_geojson["coordinates"] if drivable_geojson["type"] == "MultiPolygon" else [
        drivable_geojson["coordinates"]]
    cx, cy = centre
    kept = []
    for k, poly in enumerate(polys):
        xs = [p[0] for p in poly[0]]
        ys = [p[1] for p in poly[0]]
        if max(xs) < cx - DRIVABLE_MARGIN_M or min(xs) > cx + DRIVABLE_MARGIN_M or max(
                ys) < cy - DRIVABLE_MARGIN_M or min(ys) > cy + DRIVABLE_MARGIN_M:
            continue
        rings = [_distinct(r) for r in poly]
        # GeoJSON repeats the first vertex at the end; nuScenes polygons do not.
        rings = [r[:-1] if len(r) > 1 and r[0] == r[-1] else r for r in rings]
        kept.append(mw.add_polygon(("drivable", k), rings[0], rings[1:]))
    empty = ["road_segment", "road_block", "ped_crossing", "walkway", "carpark_area", "traffic_light"]
    out = {
        "version": "1.3",
        "canvas_edge": [2000.0, 2000.0],
        "node": mw.node, "line": mw.line, "polygon": mw.polygon,
        "drivable_area": [{"token": token("drivable_area", 0), "polygon_tokens": kept}],
        "lane": lane, "lane_connector": connector,
        "lane_divider": lane_div, "road_divider": road_div, "stop_line": stop,
        "arcline_path_3": arc, "connectivity": connectivity,
    }
    for k in empty:
        out[k] = []
    return out


def _edge(p, q, flip=False, half=1.75):
    dx, dy = q[0] - p[0], q[1] - p[1]
    n = math.hypot(dx, dy) or 1.0
    nx, ny = -dy / n * half, dx / n * half
    a, b = [p[0] + nx, p[1] + ny], [p[0] - nx, p[1] - ny]
    return [b, a] if flip else [a, b]


def write_fixture(shared, out, scene_name="scene-0061", version="v1.0-mini", images="link", camera_sweeps=False,
                  map_expansion=True):
    """Writes the fixture for `scene_name` under `out`; returns a summary (counts, tokens, t0)."""
    shared, out = Path(shared), Path(out)
    scene = json.loads((shared / "scenes" / f"{scene_name}.json").read_text())
    frame = json.loads((shared / f"keyframe-{scene_name}" / "frame.json").read_text().replace("NaN", "null"))
    map_name = scene["metadata"]["map"]
    t0 = T0_US[scene_name]
    logfile = LOGFILE[scene_name]
    n_steps = scene["length"]
    n_samples = (n_steps - 1) // KEY_EVERY + 1
    tables = {k: [] for k in ["scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                              "sample_annotation", "instance", "category", "log", "map", "attribute",
                              "visibility"]}
    log_tok = token("log", logfile)
    tables["log"].append({"token": log_tok, "logfile": logfile, "vehicle": logfile.split("-")[0],
                          "date_captured": scene["metadata"].get("date", ""), "location": map_name})
    tables["map"].append({"token": token("map", map_name), "log_tokens": [log_tok], "category": "semantic_prior",
                          "filename": f"maps/{token('mapfile', map_name)}.png"})
    cat_tok = {}
    for i, c in enumerate(CATEGORIES):
        cat_tok[c] = token("category", c)
        tables["category"].append({"token": cat_tok[c], "name": c, "description": c, "index": i})
    for a in ATTRIBUTES:
        tables["attribute"].append({"token": token("attribute", a), "name": a, "description": a})
    for t, level in VISIBILITY:
        tables["visibility"].append({"token": t, "level": level, "description": f"visibility of {level}"})
    # Sensors and calibration.
    sensor_tok, calib_tok = {}, {}
    for ch in CAMERAS + ["LIDAR_TOP"]:
        sensor_tok[ch] = token("sensor", ch)
        tables["sensor"].append({"token": sensor_tok[ch], "channel": ch,
                                 "modality": "lidar" if ch == "LIDAR_TOP" else "camera"})
        calib_tok[ch] = token("calibrated_sensor", logfile, ch)
        if ch == "LIDAR_TOP":
            tr, rot = LIDAR_CALIB
            k = []
        else:
            c = frame["cameras"][ch]
            tr, rot = pose_of_matrix(c["cam2ego"])
            k = c["intrinsic"]
        tables["calibrated_sensor"].append({"token": calib_tok[ch], "sensor_token": sensor_tok[ch],
                                            "translation": tr, "rotation": rot, "camera_intrinsic": k})
    # Samples.
    scene_tok = scene["metadata"].get("scenario_token") or token("scene", scene_name)
    sample_tok = [token("sample", scene_name, j) for j in range(n_samples)]
    sample_ts = [t0 + 500000 * j for j in range(n_samples)]
    for j in range(n_samples):
        tables["sample"].append({"token": sample_tok[j], "timestamp": sample_ts[j], "scene_token": scene_tok,
                                 "prev": sample_tok[j - 1] if j > 0 else "",
                                 "next": sample_tok[j + 1] if j + 1 < n_samples else ""})
    tables["scene"].append({"token": scene_tok, "log_token": log_tok, "nbr_samples": n_samples,
                            "first_sample_token": sample_tok[0], "last_sample_token": sample_tok[-1],
                            "name": scene_name, "description": f"{scene_name} (b2dr test fixture)"})
    ego = EgoTrack(scene["tracks"][scene["metadata"]["sdc_id"]], t0)

    def add_sd(ch, ts, j, key_frame, pose, filename, fmt, wh):
        tok = token("sample_data", ch, ts)
        ep = token("ego_pose", ch, ts)
        tables["ego_pose"].append({"token": ep, "timestamp": ts, "translation": pose[0], "rotation": pose[1]})
        tables["sample_data"].append({
            "token": tok, "sample_token": sample_tok[j], "ego_pose_token": ep,
            "calibrated_sensor_token": calib_tok[ch], "timestamp": ts, "fileformat": fmt,
            "is_key_frame": key_frame, "height": wh[1], "width": wh[0], "filename": filename,
            "prev": "", "next": ""})
        return tok

    chains = {}
    # LIDAR_TOP at 20 Hz; a sweep belongs to the sample that follows it in time (nuScenes' rule).
    for i in range((n_samples - 1) * 10 + 1):
        ts = t0 + 50000 * i
        j = -(-i // 10)
        key = i % 10 == 0
        folder = "samples" if key else "sweeps"
        fn = f"{folder}/LIDAR_TOP/{logfile}__LIDAR_TOP__{ts}.pcd.bin"
        chains.setdefault("LIDAR_TOP", []).append(add_sd("LIDAR_TOP", ts, j, key, ego.at(ts), fn, "pcd", (0, 0)))
    image_files = []
    for j in range(n_samples):
        for ch in CAMERAS:
            c = frame["cameras"][ch]
            ts = sample_ts[j] + (c["timestamp_us"] - t0)
            pose = pose_of_matrix(c["ego2global"]) if j == 0 else ego.at(ts)
            fn = f"samples/{ch}/{logfile}__{ch}__{ts}.jpg"
            chains.setdefault(ch, []).append(add_sd(ch, ts, j, True, pose, fn, "jpg", (c["width"], c["height"])))
            image_files.append((j, ch, fn))
            if camera_sweeps and j + 1 < n_samples:
                for m in range(1, 6):
                    tsw = ts + m * 83333
                    fn = f"sweeps/{ch}/{logfile}__{ch}__{tsw}.jpg"
                    sd = add_sd(ch, tsw, j + 1, False, ego.at(tsw), fn, "jpg", (c["width"], c["height"]))
                    chains[ch].append(sd)
                    image_files.append((j + 1, ch, fn))
    by_tok = {r["token"]: r for r in tables["sample_data"]}
    for toks in chains.values():
        for a, b in zip(toks, toks[1:]):
            by_tok[a]["next"] = b
            by_tok[b]["prev"] = a
    # Annotations.
    n_ann = 0
    for tid in sorted(scene["tracks"]):
        if tid == scene["metadata"]["sdc_id"]:
            continue
        tr = scene["tracks"][tid]
        cat = tr["metadata"]["type"]
        st = tr["state"]
        anns = []
        for j in range(n_samples):
            k = j * KEY_EVERY
            if not st["valid"][k]:
                continue
            p = st["position"][k]
            size = [st["width"][k][0], st["length"][k][0], st["height"][k][0]]
            anns.append({
                "token": token("sample_annotation", tid, j), "sample_token": sample_tok[j], "instance_token": tid,
                "visibility_token": "4", "attribute_tokens": [],
                "translation": [p[0], p[1], p[2]], "size": size, "rotation": yaw_quat(st["heading"][k]),
                "num_lidar_pts": 10, "num_radar_pts": 0, "prev": "", "next": ""})
        if not anns:
            continue
        for a, b in zip(anns, anns[1:]):
            a["next"] = b["token"]
            b["prev"] = a["token"]
        tables["sample_annotation"].extend(anns)
        n_ann += len(anns)
        tables["instance"].append({"token": tid, "category_token": cat_tok[cat], "nbr_annotations": len(anns),
                                   "first_annotation_token": anns[0]["token"],
                                   "last_annotation_token": anns[-1]["token"]})
    # Write tables, images and map.
    tdir = out / version
    tdir.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (tdir / f"{name}.json").write_text(json.dumps(rows, indent=0))
    first = {}
    for j, ch, fn in image_files:
        dst = out / fn
        dst.parent.mkdir(parents=True, exist_ok=True)
        if j == 0:
            shutil.copyfile(shared / f"keyframe-{scene_name}" / frame["cameras"][ch]["image"], dst)
            first[ch] = dst
        elif images == "copy":
            shutil.copyfile(first[ch], dst)
        else:
            try:
                os.symlink(os.path.relpath(first[ch], dst.parent), dst)
            except OSError:
                shutil.copyfile(first[ch], dst)
    if map_expansion:
        geo = json.loads((shared / "maps" / f"{map_name}.drivable_area.geojson").read_text())
        centre = ego.pos[len(ego.pos) // 2]
        mdir = out / "maps" / "expansion"
        mdir.mkdir(parents=True, exist_ok=True)
        (mdir / f"{map_name}.json").write_text(json.dumps(expansion_map(scene, geo, centre)))
    return {"dataroot": str(out), "version": version, "scene": scene_name, "scene_token": scene_tok, "t0_us": t0,
            "samples": n_samples, "annotations": n_ann, "instances": len(tables["instance"]),
            "sample_data": len(tables["sample_data"]), "map": map_name}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", required=True, help="the nuscenes-mini folder of the shared data")
    ap.add_argument("--out", required=True, help="DATAROOT to write")
    ap.add_argument("--scene", default="scene-0061")
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--images", choices=["link", "copy"], default="link")
    ap.add_argument("--camera-sweeps", action="store_true", help="also write 12 Hz non-key camera sample_data")
    ap.add_argument("--no-map-expansion", action="store_true",
                    help="leave out maps/expansion (the separate map expansion pack), as the main download alone")
    a = ap.parse_args(argv)
    print(json.dumps(write_fixture(a.shared, a.out, a.scene, a.version, a.images, a.camera_sweeps,
                                   not a.no_map_expansion)))


if __name__ == "__main__":
    main()
