"""A small nuPlan log (SQLite DB), map (GeoPackage) and sensor_blobs folder written from a known, hand-made scenario
(docs/nuplan.md, "Test fixture"). No nuPlan file can be downloaded here, so tests build one at test time, laid out
and pickled the way motional/nuplan-devkit lays out and writes the real dataset:

    OUT/nuplan-v1.1/splits/mini/<LOG>.db                 the log (tables of motional/nuplan-devkit docs/nuplan_schema.md)
    OUT/nuplan-v1.1/sensor_blobs/<LOG>/CAM_*/<tok>.jpg   camera images (small JPEGs; PNGs with --png)
    OUT/maps/nuplan-maps-v1.0.json                       the maps manifest: {map name: {"version": ...}}
    OUT/maps/<MAP_NAME>/<MAP_VERSION>/map.gpkg           the map (GeoPackage: GPKG header + WKB geometry blobs)
    OUT/expected.json                                    the known scenario at 10 Hz (for the round-trip test)

Layouts and classes of the devkit:
- maps as its GPKGMapsDB (nuplan/database/maps_db/gpkg_mapsdb.py) reads them: the manifest `<map_version>.json`
  at the maps root (default NUPLAN_MAP_VERSION `nuplan-maps-v1.0`) gives each map name its version, and the
  GeoPackage is `<map name>/<version>/map.gpkg`; the log's `map_version` column is the map name
  (`us-nv-las-vegas-strip`) and its `location` a city (`las_vegas`) that names no folder;
- calibration (`--calibration devkit`, the default) as its ORM writes it: `camera.translation`, `rotation`,
  `intrinsic` and `lidar.translation`, `rotation` are SqlTranslation / SqlRotation / SqlCameraIntrinsic columns,
  whose `process_bind_param` is `pickle.dumps(value)` (nuplan/database/common/sql_types.py `SimplePickleType`);
  the values are the devkit's own `Translation`, `Rotation`, `CameraIntrinsic` (list subclasses of
  nuplan.database.common.data_types, vendored unmodified with their licence in
  python/tests/fixtures/nuplan_devkit); `camera.distortion` is a plain `PickleType` column (a list pickled with
  the highest protocol). `--calibration lists` pickles plain lists, `--calibration numpy` numpy arrays (forms
  other writers of the format produce; every form must import). `--pickle-protocol P` pickles the devkit
  classes with protocol P instead of Python's default.

The known scenario (`--seconds`, default 20 s, at 20 Hz in the DB):
- a straight road along +x in UTM zone 11N (origin X0, Y0): lane group 1 (lanes 11 at y = 0 and 12 at y = 3.5,
  x in [0, 100]), an intersection x in [100, 120] with lane group connector 2 (connectors 21: 11 -> 31 and
  22: 12 -> 32), lane group 3 (lanes 31, 32, x in [120, 300]); a crosswalk before the intersection, a stop
  polygon on lane 11's end, an intersection polygon, the `meta` layer (projectedCoordSystem epsg:32611); with
  `--lonlat` the layers are stored in EPSG:4326 (longitude, latitude: the UTM design points inverse-projected);
- the ego (rear axle) drives lane 11 from x = 10 with v(t) = 8 + 0.1 t m/s, heading 0 (a slight yaw wobble);
- tracks: a car ahead in lane 11 at 10 m/s, a pedestrian walking across at x = 97, a cyclist in lane 12
  (appears at t = 2 s, leaves at t = 15 s), a static traffic cone;
- traffic_light_status on connector 21: green for t < 8 s, yellow until 10 s, red after; unknown on 22;
- two scenes (the first and the second half of the log; `lidar_pc.scene_token`) with the devkit's space-separated
  `roadblock_ids`: "1 2 3" and "3 7" (7: a roadblock beyond the fixture's map, as a route may run past the loaded
  region), `goal_ego_pose_token` = the ego pose of each scene's last lidar_pc; scenario_tag rows at t = 2 s and
  t = 4 s;
- 8 cameras (CAM_F0 ... CAM_L2) with pickled calibration (above), 64 x 36 px; images at 10 Hz each.

Tokens are 8-byte BLOBs (`--hex-tokens` is not offered: the devkit stores bytes). Standard library + numpy.
`python3 -m b2dr_ref.nuplan_fixture --out DIR [--seconds S] [--png] [--calibration devkit|lists|numpy]`.
"""
import argparse
import io
import json
import math
import pickle
import sqlite3
import struct
import sys
import zlib
from pathlib import Path

import numpy as np

X0, Y0 = 664_400.0, 3_996_800.0
LOG = "2021.07.16.20.45.29_veh-35_01095_01486"
LOCATION = "las_vegas"  # log.location: a city, names no folder
MAP_NAME = "us-nv-las-vegas-strip"  # log.map_version: the map's name (its folder under the maps root)
MAP_VERSION = "9.15.1915"  # the manifest's version of MAP_NAME (the folder below it)
MAPS_MANIFEST = "nuplan-maps-v1.0"  # the devkit's default NUPLAN_MAP_VERSION: OUT/maps/<MAPS_MANIFEST>.json
# The other maps of the nuPlan maps download, listed in the manifest (their files are not written).
OTHER_MAPS = {"sg-one-north": "9.17.1964", "us-ma-boston": "9.12.1817", "us-pa-pittsburgh-hazelwood": "9.17.1937"}
CALIBRATIONS = ("devkit", "lists", "numpy")
DEVKIT_VENDOR = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "nuplan_devkit"
T0_US = 1_626_469_529_050_000
EPSG = 32611
CAMERAS = ["CAM_F0", "CAM_R0", "CAM_R1", "CAM_R2", "CAM_B0", "CAM_L0", "CAM_L1", "CAM_L2"]
CAM_YAW_DEG = [0.0, -55.0, -90.0, -135.0, 180.0, 55.0, 90.0, 135.0]
CAM_W, CAM_H = 64, 36
CATEGORIES = ["vehicle", "bicycle", "pedestrian", "traffic_cone", "barrier", "czone_sign", "generic_object"]

SCHEMA = """
CREATE TABLE log (token BLOB NOT NULL, vehicle_name VARCHAR(64), date VARCHAR(64), timestamp INTEGER,
  logfile VARCHAR(64), location VARCHAR(64), map_version VARCHAR(64), PRIMARY KEY (token));
CREATE TABLE ego_pose (token BLOB NOT NULL, timestamp INTEGER, x FLOAT, y FLOAT, z FLOAT, qw FLOAT, qx FLOAT,
  qy FLOAT, qz FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, acceleration_x FLOAT, acceleration_y FLOAT,
  acceleration_z FLOAT, angular_rate_x FLOAT, angular_rate_y FLOAT, angular_rate_z FLOAT, epsg INTEGER,
  log_token BLOB NOT NULL, PRIMARY KEY (token), FOREIGN KEY(log_token) REFERENCES log (token));
CREATE TABLE camera (token BLOB NOT NULL, log_token BLOB NOT NULL, channel VARCHAR(64), model VARCHAR(64),
  translation BLOB, rotation BLOB, intrinsic BLOB, distortion BLOB, width INTEGER, height INTEGER,
  PRIMARY KEY (token), FOREIGN KEY(log_token) REFERENCES log (token));
CREATE TABLE lidar (token BLOB NOT NULL, log_token BLOB NOT NULL, channel VARCHAR(64), model VARCHAR(64),
  translation BLOB, rotation BLOB, PRIMARY KEY (token), FOREIGN KEY(log_token) REFERENCES log (token));
CREATE TABLE image (token BLOB NOT NULL, next_token BLOB, prev_token BLOB, ego_pose_token BLOB NOT NULL,
  camera_token BLOB NOT NULL, filename_jpg VARCHAR(128), timestamp INTEGER, PRIMARY KEY (token),
  FOREIGN KEY(ego_pose_token) REFERENCES ego_pose (token), FOREIGN KEY(camera_token) REFERENCES camera (token));
CREATE TABLE category (token BLOB NOT NULL, name VARCHAR(64), description TEXT, PRIMARY KEY (token));
CREATE TABLE track (token BLOB NOT NULL, category_token BLOB NOT NULL, width FLOAT, length FLOAT, height FLOAT,
  PRIMARY KEY (token), FOREIGN KEY(category_token) REFERENCES category (token));
CREATE TABLE scene (token BLOB NOT NULL, log_token BLOB NOT NULL, name TEXT, goal_ego_pose_token BLOB,
  roadblock_ids TEXT, PRIMARY KEY (token), FOREIGN KEY(log_token) REFERENCES log (token),
  FOREIGN KEY(goal_ego_pose_token) REFERENCES ego_pose (token));
CREATE TABLE lidar_pc (token BLOB NOT NULL, next_token BLOB, prev_token BLOB, scene_token BLOB NOT NULL,
  ego_pose_token BLOB NOT NULL, lidar_token BLOB NOT NULL, filename VARCHAR(128), timestamp INTEGER,
  PRIMARY KEY (token), FOREIGN KEY(scene_token) REFERENCES scene (token),
  FOREIGN KEY(ego_pose_token) REFERENCES ego_pose (token), FOREIGN KEY(lidar_token) REFERENCES lidar (token));
CREATE TABLE lidar_box (token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, track_token BLOB NOT NULL,
  next_token BLOB, prev_token BLOB, x FLOAT, y FLOAT, z FLOAT, width FLOAT, length FLOAT, height FLOAT, vx FLOAT,
  vy FLOAT, vz FLOAT, yaw FLOAT, confidence FLOAT, PRIMARY KEY (token),
  FOREIGN KEY(lidar_pc_token) REFERENCES lidar_pc (token), FOREIGN KEY(track_token) REFERENCES track (token));
CREATE TABLE scenario_tag (token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, type TEXT, agent_track_token BLOB,
  PRIMARY KEY (token), FOREIGN KEY(lidar_pc_token) REFERENCES lidar_pc (token));
CREATE TABLE traffic_light_status (token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL, lane_connector_id INTEGER,
  status VARCHAR(8), PRIMARY KEY (token), FOREIGN KEY(lidar_pc_token) REFERENCES lidar_pc (token));
"""

_counter = [0]


def token() -> bytes:
    _counter[0] += 1
    return struct.pack(">Q", 0x5A00_0000_0000_0000 + _counter[0] * 0x9E37)


def devkit_data_types():
    """nuplan.database.common.data_types of the devkit (vendored unmodified): pickles of its classes name that
    module, exactly as the devkit's own writes do."""
    if str(DEVKIT_VENDOR) not in sys.path:
        sys.path.insert(0, str(DEVKIT_VENDOR))
    from nuplan.database.common import data_types
    return data_types


def calibration_blobs(calibration, translation, rotation, intrinsic=None, distortion=None, protocol=None):
    """The pickled calibration columns of one camera (or the lidar: no intrinsic / distortion).
    devkit: SimplePickleType.process_bind_param = pickle.dumps(value) of the devkit's classes; distortion is a
    PickleType column (SQLAlchemy's default protocol: pickle.HIGHEST_PROTOCOL) holding a list."""
    if calibration == "devkit":
        dt = devkit_data_types()
        values = [dt.Translation(translation), dt.Rotation(rotation)]
        if intrinsic is not None:
            values.append(dt.CameraIntrinsic([list(r) for r in intrinsic]))
        out = [pickle.dumps(v) if protocol is None else pickle.dumps(v, protocol=protocol) for v in values]
        if distortion is not None:
            out.append(pickle.dumps(list(distortion), protocol=pickle.HIGHEST_PROTOCOL))
        return out
    if calibration == "lists":
        values = [list(translation), list(rotation)]
        if intrinsic is not None:
            values += [[list(r) for r in intrinsic], list(distortion)]
        return [pickle.dumps(v) for v in values]
    if calibration == "numpy":
        values = [np.array(translation), np.array(rotation)]
        if intrinsic is not None:
            values += [np.array(intrinsic), np.array(distortion)]
        return [pickle.dumps(v) for v in values]
    raise ValueError(f"calibration {calibration!r}: expected one of {CALIBRATIONS}")


def write_manifest(maps_root: Path):
    """OUT/maps/<MAPS_MANIFEST>.json: what GPKGMapsDB reads (`metadata[map]["version"]`; "layers" holds the raster
    layers' metadata, none here)."""
    maps = {MAP_NAME: {"version": MAP_VERSION, "layers": {}}}
    maps.update({m: {"version": v, "layers": {}} for m, v in OTHER_MAPS.items()})
    maps_root.mkdir(parents=True, exist_ok=True)
    (maps_root / f"{MAPS_MANIFEST}.json").write_text(json.dumps(maps, indent=2, sort_keys=True))


def quat_z(yaw):
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


# ---------------------------------------------------------------- the known scenario (global frame, metres)
def ego_at(t):
    """Rear-axle pose and velocity (global) at t seconds."""
    x = 10.0 + 8.0 * t + 0.05 * t * t
    yaw = 0.01 * math.sin(0.5 * t)
    return X0 + x, Y0 + 0.0, yaw, 8.0 + 0.1 * t


def tracks_at(t):
    """[(name, category, (l, w, h), x, y, yaw, vx, vy)] present at t."""
    out = [("car", "vehicle", (4.8, 2.0, 1.6), X0 + 30.0 + 10.0 * t, Y0, 0.0, 10.0, 0.0),
           ("ped", "pedestrian", (0.6, 0.6, 1.8), X0 + 97.0, Y0 - 6.0 + 0.8 * t, math.pi / 2, 0.0, 0.8),
           ("cone", "traffic_cone", (0.4, 0.4, 0.7), X0 + 60.0, Y0 + 5.5, 0.0, 0.0, 0.0)]
    if 2.0 <= t <= 15.0 + 1e-9:
        out.append(("bike", "bicycle", (1.8, 0.6, 1.5), X0 + 5.0 + 6.0 * (t - 2.0), Y0 + 3.5, 0.0, 6.0, 0.0))
    return out


def light_at(t):
    return "green" if t < 8.0 else ("yellow" if t < 10.0 else "red")


# ---------------------------------------------------------------- images
def pixel(rgb, x, y):
    # the camera's colour with a diagonal ramp in green (a lens model must move something visible)
    return (rgb[0], (rgb[1] + 4 * x + 6 * y) % 256, rgb[2])


def png_bytes(w, h, rgb):
    raw = b"".join(b"\x00" + b"".join(bytes(pixel(rgb, x, y)) for x in range(w)) for y in range(h))

    def chunk(kind, data):
        c = struct.pack(">I", len(data)) + kind + data
        return c + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def image_bytes(cam_i, k, png):
    rgb = (30 * cam_i % 256, (7 * k) % 256, 200)
    if png:
        return png_bytes(CAM_W, CAM_H, rgb)
    from PIL import Image  # the test virtualenv has Pillow; --png needs nothing
    buf = io.BytesIO()
    im = Image.new("RGB", (CAM_W, CAM_H))
    im.putdata([pixel(rgb, x, y) for y in range(CAM_H) for x in range(CAM_W)])
    im.save(buf, format="JPEG", quality=90)
    return buf.getvalue()


# ---------------------------------------------------------------- GeoPackage
_LONLAT = [False]


def _pt(p):
    return tm_inverse(*p) if _LONLAT[0] else p


def wkb_point(x, y):
    return struct.pack("<BIdd", 1, 1, x, y)


def wkb_line(pts):
    return struct.pack("<BII", 1, 2, len(pts)) + b"".join(struct.pack("<dd", *_pt(p)) for p in pts)


def wkb_polygon(rings):
    out = struct.pack("<BII", 1, 3, len(rings))
    for r in rings:
        r = list(r) + [r[0]]  # closed, as WKB stores it
        out += struct.pack("<I", len(r)) + b"".join(struct.pack("<dd", *_pt(p)) for p in r)
    return out


def wkb_multipolygon(polys):
    return struct.pack("<BII", 1, 6, len(polys)) + b"".join(wkb_polygon(p) for p in polys)


def gpkg_blob(wkb, pts, envelope=True, srs=None):
    """GPKG geometry header (magic, version 0, flags: little endian, envelope [minx, maxx, miny, maxy]) + WKB."""
    srs = srs if srs is not None else (4326 if _LONLAT[0] else EPSG)
    flags = 0x01 | (0x02 if envelope else 0)
    head = b"GP" + bytes([0, flags]) + struct.pack("<i", srs)
    if envelope:
        pts = [_pt(p) for p in pts]
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        head += struct.pack("<dddd", min(xs), max(xs), min(ys), max(ys))
    return head + wkb


def rect(x0, x1, y0, y1):
    return [(X0 + x0, Y0 + y0), (X0 + x1, Y0 + y0), (X0 + x1, Y0 + y1), (X0 + x0, Y0 + y1)]


def line(x0, x1, y, step=1.0):
    n = int(round((x1 - x0) / step))
    return [(X0 + x0 + (x1 - x0) * i / n, Y0 + y) for i in range(n + 1)]


# Map description: lanes (fid, group, y centre, x0, x1), connectors (fid, group connector, exit, entry, y).
LANES = [(11, 1, 0.0, 0.0, 100.0), (12, 1, 3.5, 0.0, 100.0), (31, 3, 0.0, 120.0, 300.0), (32, 3, 3.5, 120.0, 300.0)]
CONNECTORS = [(21, 2, 11, 31, 0.0), (22, 2, 12, 32, 3.5)]
SPEED_LIMIT = 13.4112


def tm_forward(lon, lat, lon0=-117.0, a=6378137.0, f=1 / 298.257223563, k0=0.9996):
    """UTM (easting, northing) of lon / lat degrees (Krueger series to n^6, northern hemisphere)."""
    n = f / (2 - f)
    big_a = a / (1 + n) * (1 + n**2 / 4 + n**4 / 64 + n**6 / 256)
    al = [n / 2 - 2 * n**2 / 3 + 5 * n**3 / 16 + 41 * n**4 / 180 - 127 * n**5 / 288 + 7891 * n**6 / 37800,
          13 * n**2 / 48 - 3 * n**3 / 5 + 557 * n**4 / 1440 + 281 * n**5 / 630 - 1983433 * n**6 / 1935360,
          61 * n**3 / 240 - 103 * n**4 / 140 + 15061 * n**5 / 26880 + 167603 * n**6 / 181440,
          49561 * n**4 / 161280 - 179 * n**5 / 168 + 6601661 * n**6 / 7257600,
          34729 * n**5 / 80640 - 3418889 * n**6 / 1995840, 212378941 * n**6 / 319334400]
    e = math.sqrt(f * (2 - f))
    phi, dl = math.radians(lat), math.radians(lon - lon0)
    t = math.sinh(math.atanh(math.sin(phi)) - e * math.atanh(e * math.sin(phi)))
    xi_p, eta_p = math.atan2(t, math.cos(dl)), math.atanh(math.sin(dl) / math.sqrt(1 + t * t))
    xi, eta = xi_p, eta_p
    for j, a_j in enumerate(al, 1):
        xi += a_j * math.sin(2 * j * xi_p) * math.cosh(2 * j * eta_p)
        eta += a_j * math.cos(2 * j * xi_p) * math.sinh(2 * j * eta_p)
    return 500000.0 + k0 * big_a * eta, k0 * big_a * xi


def tm_inverse(x, y):
    """lon / lat of a UTM zone 11N point (Newton on tm_forward, to 1e-9 m)."""
    lon, lat = -117.0 + (x - 500000.0) / 90000.0, y / 111000.0
    for _ in range(20):
        fx, fy = tm_forward(lon, lat)
        h = 1e-7
        ax, ay = tm_forward(lon + h, lat)
        bx, by = tm_forward(lon, lat + h)
        j = [[(ax - fx) / h, (bx - fx) / h], [(ay - fy) / h, (by - fy) / h]]
        det = j[0][0] * j[1][1] - j[0][1] * j[1][0]
        rx, ry = x - fx, y - fy
        lon += (j[1][1] * rx - j[0][1] * ry) / det
        lat += (-j[1][0] * rx + j[0][0] * ry) / det
        if abs(rx) < 1e-9 and abs(ry) < 1e-9:
            break
    return lon, lat


def write_map(path: Path, lonlat: bool = False):
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    _LONLAT[0] = lonlat
    srs_layers = 4326 if lonlat else EPSG
    db = sqlite3.connect(path)
    db.executescript("""
    CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY,
      organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL,
      description TEXT);
    CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT,
      description TEXT DEFAULT '', last_change DATETIME, min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE,
      srs_id INTEGER);
    CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
      geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
      CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name));
    """)
    db.execute("PRAGMA application_id = 1196444487")  # 'GPKG'
    db.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?,?,?,?,?,?)", [
        ("Undefined cartesian SRS", -1, "NONE", -1, "undefined", ""),
        ("Undefined geographic SRS", 0, "NONE", 0, "undefined", ""),
        ("WGS 84 / UTM zone 11N", EPSG, "EPSG", EPSG, 'PROJCS["WGS 84 / UTM zone 11N"]', ""),
        ("WGS 84 geodetic", 4326, "EPSG", 4326, 'GEOGCS["WGS 84"]', ""),
    ])

    def layer(name, gtype, cols, rows):
        """rows: (fid, geometry blob, *cols)."""
        coldefs = "".join(f", {c} {t}" for c, t in cols)
        db.execute(f"CREATE TABLE {name} (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom {gtype}{coldefs})")
        db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, srs_id) VALUES (?,?,?,?)",
                   (name, "features", name, srs_layers))
        db.execute("INSERT INTO gpkg_geometry_columns VALUES (?,?,?,?,0,0)", (name, "geom", gtype, srs_layers))
        marks = ",".join("?" * (2 + len(cols)))
        db.executemany(f"INSERT INTO {name} (fid, geom{''.join(', ' + c for c, _ in cols)}) VALUES ({marks})",
                       rows)

    lane_rows = []
    for fid, grp, y, x0, x1 in LANES:
        ring = rect(x0, x1, y - 1.75, y + 1.75)
        lane_rows.append((fid, gpkg_blob(wkb_polygon([ring]), ring), grp, int(y > 1), SPEED_LIMIT, str(fid)))
    layer("lanes_polygons", "POLYGON", [("lane_group_fid", "INTEGER"), ("lane_index", "INTEGER"),
                                        ("speed_limit_mps", "REAL"), ("creator_id", "TEXT")], lane_rows)
    conn_rows = []
    for fid, gc, ex, en, y in CONNECTORS:
        ls = line(100.0, 120.0, y)
        conn_rows.append((fid, gpkg_blob(wkb_line(ls), ls, envelope=False), ex, en, gc, SPEED_LIMIT,
                          "41" if fid == 21 else ""))
    layer("lane_connectors", "LINESTRING", [("exit_lane_fid", "INTEGER"), ("entry_lane_fid", "INTEGER"),
                                            ("lane_group_connector_fid", "INTEGER"), ("speed_limit_mps", "REAL"),
                                            ("traffic_light_stop_line_fids", "TEXT")], conn_rows)
    poly_rows = []
    for fid, gc, ex, en, y in CONNECTORS:
        ring = rect(100.0, 120.0, y - 1.75, y + 1.75)
        poly_rows.append((100 + fid, gpkg_blob(wkb_polygon([ring]), ring), fid))
    layer("gen_lane_connectors_scaled_width_polygons", "POLYGON", [("lane_connector_fid", "INTEGER")], poly_rows)
    bp = []
    for fid, grp, y, x0, x1 in LANES:
        ls = line(x0, x1, y)
        bp.append((1000 + fid, gpkg_blob(wkb_line(ls), ls, envelope=False), fid, None))
    for fid, gc, ex, en, y in CONNECTORS:
        ls = line(100.0, 120.0, y)
        bp.append((1000 + fid, gpkg_blob(wkb_line(ls), ls, envelope=False), None, fid))
    layer("baseline_paths", "LINESTRING", [("lane_fid", "INTEGER"), ("lane_connector_fid", "INTEGER")], bp)
    groups = [(1, rect(0.0, 100.0, -1.75, 5.25)), (3, rect(120.0, 300.0, -1.75, 5.25))]
    layer("lane_groups_polygons", "POLYGON", [("road_segment_fid", "INTEGER")],
          [(f, gpkg_blob(wkb_polygon([r]), r), 1) for f, r in groups])
    gcr = rect(100.0, 120.0, -1.75, 5.25)
    layer("lane_group_connectors", "POLYGON", [("from_lane_group_fid", "INTEGER"), ("to_lane_group_fid", "INTEGER"),
                                               ("intersection_fid", "INTEGER")],
          [(2, gpkg_blob(wkb_polygon([gcr]), gcr), 1, 3, 51)])
    ir = rect(100.0, 120.0, -8.0, 11.0)
    layer("intersections", "POLYGON", [("intersection_type_fid", "INTEGER")],
          [(51, gpkg_blob(wkb_polygon([ir]), ir), 1)])
    cw = rect(95.0, 99.0, -8.0, 11.0)
    layer("crosswalks", "POLYGON", [("creator_id", "TEXT")], [(61, gpkg_blob(wkb_polygon([cw]), cw), "cw")])
    sp = rect(99.0, 100.0, -1.75, 1.75)
    layer("stop_polygons", "POLYGON", [("stop_polygon_type_fid", "INTEGER"), ("lane_fid", "INTEGER")],
          [(41, gpkg_blob(wkb_polygon([sp]), sp), 2, 11)])
    # A carpark beside the road: a MultiPolygon with a hole, to exercise Multi* and holes.
    cp = [rect(20.0, 60.0, 8.0, 30.0), rect(30.0, 40.0, 15.0, 20.0)]
    layer("carpark_areas", "MULTIPOLYGON", [("creator_id", "TEXT")],
          [(71, gpkg_blob(wkb_multipolygon([cp]), cp[0]), "cp")])
    layer("generic_drivable_areas", "POLYGON", [("creator_id", "TEXT")], [])
    # The `meta` layer (attributes only): key / value rows, the projection among them.
    db.execute("CREATE TABLE meta (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, key TEXT, value TEXT)")
    db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier) VALUES ('meta','attributes','meta')")
    db.executemany("INSERT INTO meta (key, value) VALUES (?,?)", [
        ("projectedCoordSystem", "epsg:32611"),
        ("geographicCoordSystem", "epsg:4326"),
        ("version", MAP_VERSION)])
    db.commit()
    db.close()
    _LONLAT[0] = False


# ---------------------------------------------------------------- the log
def write_fixture(out: Path, seconds: float = 20.0, png: bool = False, lonlat: bool = False,
                  calibration: str = "devkit", protocol=None) -> dict:
    _counter[0] = 0
    out = Path(out)
    db_path = out / "nuplan-v1.1" / "splits" / "mini" / f"{LOG}.db"
    db_path.parent.mkdir(parents=True, exist_ok=True)
    if db_path.exists():
        db_path.unlink()
    map_path = out / "maps" / MAP_NAME / MAP_VERSION / "map.gpkg"
    write_map(map_path, lonlat)
    write_manifest(out / "maps")
    blobs = out / "nuplan-v1.1" / "sensor_blobs"
    db = sqlite3.connect(db_path)
    db.executescript(SCHEMA)
    log_tok = token()
    db.execute("INSERT INTO log VALUES (?,?,?,?,?,?,?)",
               (log_tok, "veh-35", "2021-07-16", T0_US, LOG, LOCATION, MAP_NAME))
    lidar_tok = token()
    db.execute("INSERT INTO lidar VALUES (?,?,?,?,?,?)",
               (lidar_tok, log_tok, "MergedPointCloud", "merged",
                *calibration_blobs(calibration, [1.5, 0.0, 1.8], [1.0, 0.0, 0.0, 0.0], protocol=protocol)))
    cat_tok = {}
    for name in CATEGORIES:
        cat_tok[name] = token()
        db.execute("INSERT INTO category VALUES (?,?,?)", (cat_tok[name], name, f"{name} objects"))
    cams = []
    for i, (ch, yaw_deg) in enumerate(zip(CAMERAS, CAM_YAW_DEG)):
        yaw = math.radians(yaw_deg)
        # camera -> ego: camera z forward along the yaw, x right, y down.
        rot = np.array([[math.sin(yaw), 0.0, math.cos(yaw)], [-math.cos(yaw), 0.0, math.sin(yaw)],
                        [0.0, -1.0, 0.0]])
        q = mat_to_quat(rot)
        tr = [1.5 * math.cos(yaw), 0.8 * math.sin(yaw), 1.6]
        f = 32.0 + i
        intr = np.array([[f, 0.0, CAM_W / 2], [0.0, f, CAM_H / 2], [0.0, 0.0, 1.0]])
        dist = np.array([-0.35, 0.15, 0.0001, -0.0002, -0.03])
        tok = token()
        db.execute("INSERT INTO camera VALUES (?,?,?,?,?,?,?,?,?,?)",
                   (tok, log_tok, ch, "fixture",
                    *calibration_blobs(calibration, tr, q, intr.tolist(), dist.tolist(), protocol), CAM_W, CAM_H))
        cams.append({"channel": ch, "token": tok, "translation": tr, "rotation": q, "intrinsic": intr.tolist(),
                     "distortion": dist.tolist(), "width": CAM_W, "height": CAM_H})
    n = int(round(seconds * 20)) + 1
    scene_toks = [token(), token()]
    half = n // 2
    lpc = [token() for _ in range(n)]
    track_tok, track_last = {}, {}
    poses = []
    for k in range(n):
        t = k * 0.05
        ts = T0_US + k * 50_000
        x, y, yaw, v = ego_at(t)
        ep = token()
        q = quat_z(yaw)
        db.execute("INSERT INTO ego_pose VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                   (ep, ts, x, y, 0.0, *q, v, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, EPSG, log_tok))
        poses.append(ep)
        db.execute("INSERT INTO lidar_pc VALUES (?,?,?,?,?,?,?,?)",
                   (lpc[k], lpc[k + 1] if k + 1 < n else None, lpc[k - 1] if k > 0 else None, scene_toks[k >= half], ep,
                    lidar_tok, f"{LOG}/MergedPointCloud/{lpc[k].hex()}.pcd", ts))
        for name, cat, (l, w, h), bx, by, byaw, vx, vy in tracks_at(t):
            if name not in track_tok:
                track_tok[name] = token()
                db.execute("INSERT INTO track VALUES (?,?,?,?,?)", (track_tok[name], cat_tok[cat], w, l, h))
            bt = token()
            prev = track_last.get(name)
            if prev is not None and prev[1] == k - 1:
                db.execute("UPDATE lidar_box SET next_token = ? WHERE token = ?", (bt, prev[0]))
                prev_tok = prev[0]
            else:
                prev_tok = None
            db.execute("INSERT INTO lidar_box VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                       (bt, lpc[k], track_tok[name], None, prev_tok, bx, by, h / 2, w, l, h, vx, vy, 0.0, byaw,
                        0.9))
            track_last[name] = (bt, k)
        db.execute("INSERT INTO traffic_light_status VALUES (?,?,?,?)", (token(), lpc[k], 21, light_at(t)))
        db.execute("INSERT INTO traffic_light_status VALUES (?,?,?,?)", (token(), lpc[k], 22, "unknown"))
        # Images: every camera at 10 Hz, 5 ms apart from each other, from the lidar sweep time.
        if k % 2 == 0:
            for i, c in enumerate(cams):
                it = ts + 5_000 * i
                tokn = token()
                rel = f"{LOG}/{c['channel']}/{tokn.hex()}.{'png' if png else 'jpg'}"
                p = blobs / rel
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(image_bytes(i, k, png))
                db.execute("INSERT INTO image VALUES (?,?,?,?,?,?,?)",
                           (tokn, None, c.get("last"), ep, c["token"], rel, it))
                if c.get("last") is not None:
                    db.execute("UPDATE image SET next_token = ? WHERE token = ?", (tokn, c["last"]))
                c["last"] = tokn
    scenes = [("scene-0001", 0, half - 1, "1 2 3"), ("scene-0002", half, n - 1, "3 7")]
    for tok, (name, first, last, rbs) in zip(scene_toks, scenes):
        db.execute("INSERT INTO scene VALUES (?,?,?,?,?)", (tok, log_tok, name, poses[last], rbs))
    tags = [(40, "on_intersection"), (80, "following_lane_with_lead")]
    for k, kind in tags:
        if k < n:
            db.execute("INSERT INTO scenario_tag VALUES (?,?,?,?)", (token(), lpc[k], kind, track_tok["car"]))
    db.commit()
    db.close()

    # Expected scenario at 10 Hz (every second lidar_pc), global frame.
    steps = []
    for k in range(0, n, 2):
        t = k * 0.05
        x, y, yaw, v = ego_at(t)
        steps.append({"t": t, "ego": [x, y, yaw, v],
                      "tracks": {nm: [bx, by, byaw, vx, vy] for nm, _, _, bx, by, byaw, vx, vy in tracks_at(t)},
                      "lights": {"21": light_at(t), "22": "unknown"}})
    summary = {
        "db": str(db_path), "maps_root": str(out / "maps"), "sensor_root": str(blobs), "log": LOG,
        "location": LOCATION, "map_name": MAP_NAME, "map_version": MAP_VERSION, "maps_manifest": MAPS_MANIFEST,
        "map": str(map_path), "calibration": calibration, "t0_us": T0_US, "origin": [X0, Y0],
        "lidar_pc": n, "tracks": {nm: track_tok[nm].hex() for nm in track_tok},
        "track_sizes": {"car": [4.8, 2.0, 1.6], "ped": [0.6, 0.6, 1.8], "cone": [0.4, 0.4, 0.7],
                        "bike": [1.8, 0.6, 1.5]},
        "scenes": [{"token": tok.hex(), "name": name, "first_lidar_pc": lpc[first].hex(), "roadblock_ids": rbs.split(" "),
                    "goal": list(ego_at(last * 0.05)[:3])}
                   for tok, (name, first, last, rbs) in zip(scene_toks, scenes)],
        "scenario_tags": [{"lidar_pc": lpc[k].hex(), "type": kind, "t": k * 0.05} for k, kind in tags if k < n],
        "cameras": [{k: v for k, v in c.items() if k not in ("token", "last")} for c in cams],
        "images_per_camera": (n + 1) // 2,
        "lanes": [f for f, *_ in LANES], "connectors": [f for f, *_ in CONNECTORS],
        "steps": steps,
    }
    (out / "expected.json").write_text(json.dumps(summary))
    return summary


def mat_to_quat(m):
    """w, x, y, z of a rotation matrix (the larger-trace branch is enough for the fixture's rotations)."""
    m = np.asarray(m)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return [float(v) for v in q]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--png", action="store_true", help="PNG images (no Pillow needed)")
    ap.add_argument("--lonlat", action="store_true",
                    help="map layers in EPSG:4326 longitude / latitude (as the devkit reprojects with to_crs)")
    ap.add_argument("--calibration", choices=CALIBRATIONS, default="devkit",
                    help="how calibration is pickled: the devkit's data_types classes (default), lists, numpy")
    ap.add_argument("--pickle-protocol", type=int, default=None,
                    help="pickle protocol of the devkit classes (default: Python's, as the devkit's pickle.dumps)")
    a = ap.parse_args()
    s = write_fixture(a.out, a.seconds, a.png, a.lonlat, a.calibration, a.pickle_protocol)
    print(json.dumps({k: s[k] for k in ("db", "maps_root", "sensor_root", "lidar_pc")}))


if __name__ == "__main__":
    main()
