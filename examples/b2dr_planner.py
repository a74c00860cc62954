#!/usr/bin/env python3
"""Client module for b2dr's planner protocol v2 (docs/planner_protocol.md): typed requests with the camera
images, served over JSON lines on stdin/stdout. Plain Python 3 (no dependencies); numpy is used when present
(`Camera.array()`), PIL when present to read PNG files (a small built-in PNG reader otherwise).

    from b2dr_planner import serve, reply
    def plan(req):                       # req: Request
        img = req.camera("CAM_FRONT").rgb()   # bytes, row-major (H, W, 3)
        return [[4.0 * (k + 1), 0.0, 0.0] for k in range(8)]
    serve(plan, images="inline", size=(112, 200))

Each `plan` request carries the navigation command (`Request.command`: "left", "right" or "straight", by the
run's definition `Request.command_def`: "route20" or "nuscenes"; docs/planner_protocol.md) and the ego history
(`Request.history`: the last K states, newest first, in the current ego frame, each flagged "sim", "log" or
"pad"; only states, no past images). `Request.command_as(model)` encodes the command as a model expects it:

    req.command_as("uniad")   # int: 0 right, 1 left, 2 forward (UniAD)
    req.command_as("vad")     # one-hot [right, left, straight] (VAD)
    req.command_as("navsim")  # one-hot [left, straight, right, unknown] (NAVSIM / OpenScene)

A model that plans in the nuScenes lidar frame, xy only (headings derived by b2dr from the path), 6 poses at
0.5 s, replies with `return reply(xy, dt_s=0.5, frame="lidar")` (`Camera.lidar2img` and `Request.lidar2ego`
give its calibration).

A model that takes long to load passes `load` (called once, before the first session) and runs resident
(`b2dr run --planner "resident:python3 my_planner.py"`): b2dr starts the process once for the whole batch, waits
for the load under `--planner-start-timeout` and then runs every scenario as a session on the same process:

    model = None
    def load():
        global model
        model = build_model()               # minutes: outside the per-call timeout when resident
    serve(plan, load=load)                  # the same script also serves `cmd:` (loading at the first start)

Test modes of b2dr's protocol tests (python3 b2dr_planner.py --mode M): cv, checksum, noread, closeout,
tworeplies, manyposes, project, lidarxy, dt1, badframe, baddt, mixed, short, dumpreq.
"""
import json
import math
import struct
import sys
import zlib


def fnv1a64(data):
    h = 0xCBF29CE484222325
    for b in data:
        h ^= b
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def read_png_rgb(path):
    """8-bit RGB/RGBA PNG -> (width, height, RGB bytes row-major). PIL when available."""
    try:
        from PIL import Image  # type: ignore

        im = Image.open(path).convert("RGB")
        return im.width, im.height, im.tobytes()
    except ImportError:
        pass
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: not a PNG"
    pos, idat, w, h, ctype = 8, b"", 0, 0, 2
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, ctype = struct.unpack(">IIBB", body[:10])
            assert depth == 8 and ctype in (2, 6), f"{path}: only 8-bit RGB/RGBA"
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    bpp = 3 if ctype == 2 else 4
    raw = zlib.decompress(idat)
    stride = w * bpp
    out = bytearray()
    prev = bytearray(stride)
    i = 0
    for _ in range(h):
        ft = raw[i]
        row = bytearray(raw[i + 1:i + 1 + stride])
        i += 1 + stride
        for x in range(stride):
            a = row[x - bpp] if x >= bpp else 0
            b = prev[x]
            c = prev[x - bpp] if x >= bpp else 0
            if ft == 1:
                row[x] = (row[x] + a) & 255
            elif ft == 2:
                row[x] = (row[x] + b) & 255
            elif ft == 3:
                row[x] = (row[x] + (a + b) // 2) & 255
            elif ft == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pr = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                row[x] = (row[x] + pr) & 255
        prev = row
        if bpp == 3:
            out += row
        else:
            for x in range(w):
                out += row[4 * x:4 * x + 3]
    return w, h, bytes(out)


class Camera:
    """One camera of a request: calibration at the delivered size and the image."""

    def __init__(self, d, inline):
        self.name = d["camera"]
        self.width, self.height = d["width"], d["height"]
        self.intrinsic = d["intrinsic"]      # 3x3 rows, at (width, height)
        self.cam2ego = d["cam2ego"]          # 4x4 rows
        self.ego2global = d["ego2global"]    # 4x4 rows
        self.lidar2img = d.get("lidar2img")  # 4x4 rows: lidar (request time) -> pixel at (width, height)
        self.checksum = int(d["fnv1a64"])
        self.path = d.get("path")
        self._rgb = None
        if "offset" in d:
            self._rgb = inline[d["offset"]:d["offset"] + d["bytes"]]

    def rgb(self):
        """RGB bytes, row-major (height, width, 3)."""
        if self._rgb is None and self.path:
            w, h, self._rgb = read_png_rgb(self.path)
            assert (w, h) == (self.width, self.height), f"{self.path}: {w}x{h}, request says {self.width}x{self.height}"
        return self._rgb

    def array(self):
        import numpy as np  # type: ignore

        return np.frombuffer(self.rgb(), dtype=np.uint8).reshape(self.height, self.width, 3)

    def project(self, p_ego):
        """A point in the ego frame -> pixel (u, v) of this camera, or None behind it."""
        m = self.cam2ego
        d = [p_ego[i] - m[i][3] for i in range(3)]
        # camera <- ego: R^T (p - t)
        pc = [sum(m[r][c] * d[r] for r in range(3)) for c in range(3)]
        if pc[2] <= 1e-6:
            return None
        k = self.intrinsic
        u = (k[0][0] * pc[0] + k[0][1] * pc[1] + k[0][2] * pc[2]) / pc[2]
        v = (k[1][1] * pc[1] + k[1][2] * pc[2]) / pc[2]
        return u, v

    def project_lidar(self, p_lidar):
        """A point in the lidar frame of the request -> pixel (u, v) through `lidar2img`, or None behind."""
        q = transform(self.lidar2img, p_lidar)
        if q[2] <= 1e-6:
            return None
        return q[0] / q[2], q[1] / q[2]


def transform(m, p):
    """4x4 rows `m` applied to the 3D point `p` (homogeneous w = 1; the last row of b2dr's matrices is
    [0, 0, 0, 1])."""
    return [sum(m[r][c] * p[c] for c in range(3)) + m[r][3] for r in range(3)]


class Request:
    def __init__(self, d, inline, start=None):
        self.raw = d
        # the scenario's `start` message (rig, lidar2ego, ...)
        self.start = start or {}
        # lidar -> ego (4x4 rows) of the rig's top lidar, and the rear axle in that lidar frame
        self.lidar2ego = self.start.get("lidar2ego")
        self.ego_in_lidar = d.get("ego_in_lidar")
        self.scenario = d["scenario"]
        self.step, self.time_s = d["step"], d["time_s"]
        self.ego = d["ego"]
        self.command = d.get("command", "straight")
        # which definition the command follows ("route20" or "nuscenes"); absent in version 1
        self.command_def = d.get("command_def")
        # the last K ego states, newest first (EgoPast)
        self.history = [EgoPast(h) for h in d.get("history", [])]
        self.route = d.get("route", {})
        self.poses = d.get("reply", {}).get("poses", 8)
        self.dt = d.get("reply", {}).get("dt_s", 0.5)
        self.cameras = [Camera(c, inline) for c in d.get("cameras", [])]

    def command_as(self, model):
        """The command as `model` ("uniad", "vad", "navsim") consumes it (`encode_command`)."""
        return encode_command(self.command, model)

    def camera(self, name):
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera {name} in the request ({[c.name for c in self.cameras]})")


# The three commands of the protocol, and each model's encoding of them. Sources (read 2026-12):
# - UniAD: OpenDriveLab/UniAD projects/mmdet3d_plugin/datasets/data_utils/trajectory_api.py,
#   get_sdc_planning_label: `command = 0 #'RIGHT'` (lidar x >= 2), `1 #'LEFT'` (x <= -2), `2 #'FORWARD'`.
# - VAD: hustvl/VAD tools/data_converter/vad_nuscenes_converter.py (lines 452-457): `[1, 0, 0]  # Turn Right`,
#   `[0, 1, 0]  # Turn Left`, `[0, 0, 1]  # Go Straight` (gt_ego_fut_cmd).
# - NAVSIM: the driving_command of its OpenScene data, OpenScene DriveEngine/process_data/helpers/
#   driving_command.py get_driving_command: "one-hot (left, forward, right, unknown)"; unknown where no route.
COMMANDS = ("left", "right", "straight")
_ENCODINGS = {
    "uniad": {"right": 0, "left": 1, "straight": 2},
    "vad": {"right": [1, 0, 0], "left": [0, 1, 0], "straight": [0, 0, 1]},
    "navsim": {"left": [1, 0, 0, 0], "straight": [0, 1, 0, 0], "right": [0, 0, 1, 0]},
}


def encode_command(command, model):
    """b2dr's command ("left", "right", "straight") as `model` ("uniad", "vad", "navsim") consumes it. None (no
    command in the request) is NAVSIM's unknown [0, 0, 0, 1]; UniAD and VAD have no such value: ValueError, as
    for an unknown command or model."""
    if model not in _ENCODINGS:
        raise ValueError(f"unknown model {model!r}: expected one of {sorted(_ENCODINGS)}")
    if command is None and model == "navsim":
        return [0, 0, 0, 1]
    if command not in COMMANDS:
        raise ValueError(f"command {command!r}: expected one of {COMMANDS}")
    e = _ENCODINGS[model][command]
    return list(e) if isinstance(e, list) else e


class EgoPast:
    """One history slot of a request: the ego `time_s` (negative) before the request, in the request's ego
    rear-axle frame (x, y, heading; velocity vx, vy and acceleration ax, ay rotated into it), and where it came
    from: "sim" (the run's simulated state), "log" (logged before the scenario start) or "pad" (before the start
    where the log has nothing: a copy of the oldest state available)."""

    def __init__(self, d):
        self.time_s = d["time_s"]
        self.x, self.y, self.heading = d["x"], d["y"], d["heading"]
        self.vx, self.vy, self.ax, self.ay = d["vx"], d["vy"], d["ax"], d["ay"]
        self.source = d["from"]

    def __repr__(self):
        return f"EgoPast(t={self.time_s}, x={self.x:.3f}, y={self.y:.3f}, from={self.source})"


def ego_to_lidar(req, p_ego):
    """A rear-axle ego-frame point (x forward, y left, z up) -> the request's lidar frame."""
    return transform(req.ego_in_lidar, p_ego)


def reply(poses, dt_s=None, frame=None, xy_only=False):
    """A plan reply: `poses` are [x, y, heading] or [x, y] (headings derived by b2dr from the path), all of one
    kind, `dt_s` apart (None: 0.5 s), in `frame` "ego_rear_axle" (None: the default) or "lidar" (the lidar frame
    of the request time); `xy_only=True` drops the headings of [x, y, heading] poses. At least 2 s of horizon
    (len(poses) * dt_s). Raises ValueError on what b2dr would refuse."""
    if frame not in (None, "ego_rear_axle", "lidar"):
        raise ValueError(f"frame {frame!r}: expected 'ego_rear_axle' or 'lidar'")
    if dt_s is not None and not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and 0.01 <= dt_s <= 2.0):
        raise ValueError(f"dt_s {dt_s!r}: the pose spacing must be in [0.01, 2] s")
    out = []
    for i, p in enumerate(poses):
        p = [float(v) for v in p]
        if xy_only:
            p = p[:2]
        if len(p) not in (2, 3) or not all(math.isfinite(v) for v in p):
            raise ValueError(f"poses[{i}] = {p}: expected finite [x, y] or [x, y, heading]")
        if out and len(p) != len(out[0]):
            raise ValueError(f"poses[{i}] has {len(p)} values, poses[0] {len(out[0])}: mix of [x, y] and [x, y, heading]")
        out.append(p)
    if len(out) * (0.5 if dt_s is None else dt_s) < 2.0 - 1e-9:
        raise ValueError(f"{len(out)} poses x {0.5 if dt_s is None else dt_s} s: at least 2 s of horizon are required")
    r = {"poses": out}
    if dt_s is not None:
        r["dt_s"] = float(dt_s)
    if frame is not None:
        r["frame"] = frame
    return r


def _read_exact(stream, n):
    buf = b""
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise EOFError("b2dr closed the input mid-message")
        buf += chunk
    return buf


def serve(plan, images="paths", size=None, on_start=None, on_end=None, load=None):
    """Serves one b2dr process: `plan(Request) -> list of [x, y, heading]` (ego frame, 0.5 s apart) or a dict
    reply (`reply(...)`: declared dt_s, lidar frame, xy-only poses); `images`: "paths", "inline" or "none";
    `size`: (height, width) or None (the renderer's size); `load()`: called once before the first session (a
    resident planner's `hello`, else the first `start`). Sessions (start, plan..., end) repeat until stdin
    ends: a resident process (`b2dr run --planner resident:...`) serves every scenario of a batch."""
    inp, out = sys.stdin.buffer, sys.stdout
    start = None
    loaded = load is None
    while True:
        line = inp.readline()
        if not line:
            return
        line = line.strip()
        if not line:
            continue
        msg = json.loads(line)
        kind = msg.get("type", "plan")
        if kind == "hello":
            # resident mode: the load runs under b2dr's start timeout, not the per-call one
            try:
                if not loaded:
                    load()
                    loaded = True
                answer = {"ready": True}
            except Exception as e:  # the load failed: say why, b2dr ends the scenario with it
                answer = {"error": f"load failed: {type(e).__name__}: {e}"}
            out.write(json.dumps(answer) + "\n")
            out.flush()
            continue
        if kind == "start":
            if not loaded:
                load()
                loaded = True
            start = msg
            if on_start:
                on_start(msg)
            reply = {"images": images}
            if size:
                reply["size"] = list(size)
            out.write(json.dumps(reply) + "\n")
            out.flush()
            continue
        if kind == "end":
            if on_end:
                on_end(msg)
            continue
        inline = _read_exact(inp, msg.get("inline_bytes", 0)) if msg.get("inline_bytes") else b""
        r = plan(Request(msg, inline, start))
        answer = r if isinstance(r, dict) else {"poses": r}
        # echo the request's step: b2dr then knows the reply answers this request (not an earlier one)
        answer.setdefault("step", msg.get("step"))
        out.write(json.dumps(answer) + "\n")
        out.flush()


def _cv(req):
    v = max(0.0, req.ego["vx"])
    return [[v * req.dt * (k + 1), 0.0, 0.0] for k in range(req.poses)]


def main():
    mode = sys.argv[sys.argv.index("--mode") + 1] if "--mode" in sys.argv else "cv"
    images = sys.argv[sys.argv.index("--images") + 1] if "--images" in sys.argv else "paths"
    size = None
    if "--size" in sys.argv:
        h, w = sys.argv[sys.argv.index("--size") + 1].split("x")
        size = (int(h), int(w))
    if mode == "noread":
        import time

        time.sleep(3600)
    if mode == "closeout":
        import os
        import time

        os.close(1)
        sys.stdin.buffer.readline()
        time.sleep(3600)

    def plan(req):
        if mode == "checksum":
            for c in req.cameras:
                got = fnv1a64(c.rgb())
                if got != c.checksum:
                    return {"error": f"{c.name}: checksum {got} != {c.checksum}"}
        if mode == "project":
            # where the ego point (10, 0, 0.5) lands in each camera, for the test to compare with b2dr's own
            # projection at the delivered size; the same point through the lidar frame and lidar2img
            dump = sys.argv[sys.argv.index("--dump") + 1]
            p_lidar = ego_to_lidar(req, [10.0, 0.0, 0.5])
            with open(dump, "a") as f:
                for c in req.cameras:
                    f.write(json.dumps({"step": req.step, "camera": c.name, "size": [c.height, c.width],
                                        "uv": c.project([10.0, 0.0, 0.5]), "uv_lidar": c.project_lidar(p_lidar),
                                        "lidar2ego": req.lidar2ego}) + "\n")
        if mode == "dumpreq":
            # the command, its encodings and the history as this module reads them, for b2dr's tests
            dump = sys.argv[sys.argv.index("--dump") + 1]
            with open(dump, "a") as f:
                f.write(json.dumps({"step": req.step, "command": req.command, "command_def": req.command_def,
                                    "encoded": {m: req.command_as(m) for m in ("uniad", "vad", "navsim")},
                                    "history": [[h.time_s, h.x, h.y, h.heading, h.vx, h.source]
                                                for h in req.history]}) + "\n")
        v = max(2.0, req.ego["vx"])
        if mode == "lidarxy":
            # 6 points 0.5 s apart on a gentle left curve, ego frame (v dt k, 0.02 k^2) on the ground, sent
            # as xy in the lidar frame
            pts = [ego_to_lidar(req, [v * 0.5 * k, 0.02 * k * k, 0.0]) for k in range(1, 7)]
            return reply([p[:2] for p in pts], dt_s=0.5, frame="lidar")
        if mode == "dt1":
            return reply([[v * k, 0.0, 0.0] for k in range(1, 4)], dt_s=1.0)
        # replies b2dr must refuse, written without the helper (which refuses them too)
        if mode == "badframe":
            return {"poses": _cv(req), "frame": "camera"}
        if mode == "baddt":
            return {"poses": _cv(req), "dt_s": 0}
        if mode == "mixed":
            return {"poses": [[1.0, 0.0]] + _cv(req)[1:]}
        if mode == "short":
            return {"poses": _cv(req)[:3]}
        if mode == "tworeplies":
            sys.stdout.write(json.dumps({"poses": _cv(req)}) + "\n")
        if mode == "manyposes":
            return [[0.5 * k, 0.0, 0.0] for k in range(1, 100001)]
        return _cv(req)

    serve(plan, images=images, size=size)


if __name__ == "__main__":
    main()
