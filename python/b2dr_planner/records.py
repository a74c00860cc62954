"""Typed records of protocol v2 (docs/planner_protocol.md) and their ONE parser: `parse_message` turns each
JSON line b2dr sends (hello, start, plan, end; a version-1 request too) into a record. Matrices stay tuples of
row tuples (`m[r][c]`, 4x4 or 3x3), as on the wire; `b2dr_planner.adapters` turns them into numpy arrays.

Errors name the field: `ProtocolError("plan.cameras[2].lidar2img: expected a 4x4 matrix of rows")`.
Standard library only (numpy only for `CameraView.array()`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

from .command import Command, encode_command
from .images import read_png_rgb

Matrix = Tuple[Tuple[float, ...], ...]


class ProtocolError(ValueError):
    """A message that does not follow the protocol (the field named)."""


def _field(d: dict, key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise ProtocolError(f"{where}: expected an object, got {type(d).__name__}")
    if key not in d:
        raise ProtocolError(f"{where}.{key}: missing")
    return d[key]


def _num(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ProtocolError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _int(v: Any, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ProtocolError(f"{where}: expected a non-negative integer, got {v!r}")
    return v


def _str(v: Any, where: str) -> str:
    if not isinstance(v, str):
        raise ProtocolError(f"{where}: expected a string, got {v!r}")
    return v


def _matrix(v: Any, n: int, where: str) -> Matrix:
    if not (isinstance(v, list) and len(v) == n and all(isinstance(r, list) and len(r) == n for r in v)):
        raise ProtocolError(f"{where}: expected a {n}x{n} matrix of rows")
    return tuple(tuple(_num(x, f"{where}[{i}][{j}]") for j, x in enumerate(r)) for i, r in enumerate(v))


def transform(m: Matrix, p: Sequence[float]) -> List[float]:
    """A 4x4 matrix of rows applied to the 3D point `p` (w = 1; b2dr's matrices end in [0, 0, 0, 1])."""
    return [sum(m[r][c] * p[c] for c in range(3)) + m[r][3] for r in range(3)]


@dataclass(frozen=True)
class Hello:
    """Resident mode's first message: the model may load for up to `start_timeout_s`."""

    version: int
    timeout_s: float
    start_timeout_s: float


@dataclass(frozen=True)
class End:
    scenario: str


@dataclass(frozen=True)
class RigCamera:
    """A camera of the scenario's rig at its native size (`start.rig`)."""

    name: str
    width: int
    height: int
    intrinsic: Matrix  # 3x3 rows, native size
    cam2ego: Matrix  # 4x4 rows: camera (x right, y down, z forward) -> ego rear axle


@dataclass(frozen=True)
class EgoParams:
    length: float
    width: float
    wheel_base: float
    rear_axle_to_center: float


@dataclass(frozen=True)
class Route:
    roadblock_ids: Tuple[str, ...]
    lane_ids: Tuple[str, ...]
    # {"x", "y", "heading"} (rear axle, global frame) where the log names a goal, else None
    mission_goal: Optional[Dict[str, float]]


@dataclass(frozen=True)
class StartInfo:
    """The `start` message: start-up data of one scenario (a session)."""

    version: int
    scenario: str
    map: str
    dt_s: float
    rig: Tuple[RigCamera, ...]
    lidar2ego: Matrix  # 4x4 rows: the rig's top lidar -> ego rear axle
    ego: EgoParams
    route: Route


@dataclass(frozen=True)
class EgoState:
    """The simulated ego at the request time: rear-axle pose in the global frame (m, rad), rear-axle
    velocity / acceleration in the ego frame (x forward, y left; m/s, m/s^2), front-wheel angle, yaw rate."""

    x: float
    y: float
    heading: float
    vx: float
    vy: float
    ax: float
    ay: float
    steering: float
    yaw_rate: float


@dataclass(frozen=True)
class EgoPast:
    """A history slot: the ego `time_s` (< 0) before the request, in the request's ego rear-axle frame; `source`
    "sim", "log" or "pad" (docs/planner_protocol.md "History")."""

    time_s: float
    x: float
    y: float
    heading: float
    vx: float
    vy: float
    ax: float
    ay: float
    source: str


@dataclass(frozen=True)
class ReplySpec:
    """What b2dr expects back (`reply`): version 1's pose count and spacing; version 2's minimum horizon."""

    poses: int
    dt_s: float
    frame: str
    min_horizon_s: Optional[float]


@dataclass
class CameraView:
    """One delivered camera of a `plan` request: calibration at the delivered size and the image."""

    name: str
    width: int
    height: int
    intrinsic: Matrix  # 3x3 rows at (width, height)
    cam2ego: Matrix
    ego2global: Matrix  # the image's ego pose (the simulated one for rendered frames)
    lidar2img: Matrix  # lidar (request time) -> pixel at (width, height)
    checksum: int  # FNV-1a 64 of the RGB bytes
    path: Optional[str] = None
    _rgb: Optional[bytes] = field(default=None, repr=False)

    def rgb(self) -> bytes:
        """RGB bytes, row-major (height, width, 3). Raises when the planner asked for no images."""
        if self._rgb is None:
            if not self.path:
                raise ValueError(f"{self.name}: no image in the request (the planner answered start with images none)")
            w, h, self._rgb = read_png_rgb(self.path)
            if (w, h) != (self.width, self.height):
                raise ValueError(f"{self.path}: {w}x{h}, the request says {self.width}x{self.height}")
        return self._rgb

    def array(self):
        """The image as a numpy (height, width, 3) uint8 array."""
        import numpy as np

        return np.frombuffer(self.rgb(), dtype=np.uint8).reshape(self.height, self.width, 3)

    def project(self, p_ego: Sequence[float]) -> Optional[Tuple[float, float]]:
        """An ego-frame point -> pixel (u, v), or None behind the camera."""
        m = self.cam2ego
        d = [p_ego[i] - m[i][3] for i in range(3)]
        pc = [sum(m[r][c] * d[r] for r in range(3)) for c in range(3)]  # R^T (p - t)
        if pc[2] <= 1e-6:
            return None
        k = self.intrinsic
        return ((k[0][0] * pc[0] + k[0][1] * pc[1] + k[0][2] * pc[2]) / pc[2],
                (k[1][1] * pc[1] + k[1][2] * pc[2]) / pc[2])

    def project_lidar(self, p_lidar: Sequence[float]) -> Optional[Tuple[float, float]]:
        """A lidar-frame point of the request -> pixel (u, v) through `lidar2img`, or None behind."""
        q = transform(self.lidar2img, p_lidar)
        if q[2] <= 1e-6:
            return None
        return q[0] / q[2], q[1] / q[2]


@dataclass
class PlanRequest:
    """A `plan` message (per-step data); `start`: its session's start-up data (None in version 1)."""

    version: int
    scenario: str
    step: int
    time_s: float
    ego: EgoState
    ego_params: EgoParams
    route: Route
    reply: ReplySpec
    command: Optional[Command] = None  # version 2
    command_def: Optional[str] = None  # "route20" or "nuscenes"
    history: Tuple[EgoPast, ...] = ()  # newest first
    cameras: Tuple[CameraView, ...] = ()
    ego_in_lidar: Optional[Matrix] = None  # inv(lidar2ego)
    start: Optional[StartInfo] = None
    raw: Dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def lidar2ego(self) -> Optional[Matrix]:
        return self.start.lidar2ego if self.start else None

    def camera(self, name: str) -> CameraView:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera {name} in the request ({[c.name for c in self.cameras]})")

    def command_as(self, family: str) -> Union[int, List[int]]:
        """The command as `family` ("uniad", "vad", "navsim") consumes it."""
        return encode_command(self.command, family)

    def ego_to_lidar(self, p_ego: Sequence[float]) -> List[float]:
        """A rear-axle ego-frame point (x forward, y left, z up) -> the request's lidar frame."""
        if self.ego_in_lidar is None:
            raise ValueError("version-1 requests have no lidar frame")
        return transform(self.ego_in_lidar, p_ego)


Message = Union[Hello, StartInfo, PlanRequest, End]


def _rig_camera(d: dict, w: str) -> RigCamera:
    return RigCamera(_str(_field(d, "camera", w), f"{w}.camera"), _int(_field(d, "width", w), f"{w}.width"),
                     _int(_field(d, "height", w), f"{w}.height"), _matrix(_field(d, "intrinsic", w), 3, f"{w}.intrinsic"),
                     _matrix(_field(d, "cam2ego", w), 4, f"{w}.cam2ego"))


def _ego_params(d: dict, w: str) -> EgoParams:
    return EgoParams(*(_num(_field(d, k, w), f"{w}.{k}") for k in ("length", "width", "wheel_base",
                                                                       "rear_axle_to_center")))


def _route(d: Any, w: str) -> Route:
    ids = []
    for k in ("roadblock_ids", "lane_ids"):
        v = _field(d, k, w)
        if not isinstance(v, list):
            raise ProtocolError(f"{w}.{k}: expected a list of ids")
        ids.append(tuple(_str(x, f"{w}.{k}[{i}]") for i, x in enumerate(v)))
    goal = d.get("mission_goal")
    if goal is not None:
        goal = {k: _num(_field(goal, k, f"{w}.mission_goal"), f"{w}.mission_goal.{k}") for k in ("x", "y", "heading")}
    return Route(ids[0], ids[1], goal)


def parse_start(d: dict) -> StartInfo:
    w = "start"
    rig = _field(d, "rig", w)
    if not isinstance(rig, list):
        raise ProtocolError("start.rig: expected a list of cameras")
    return StartInfo(_int(_field(d, "version", w), "start.version"), _str(_field(d, "scenario", w), "start.scenario"),
                     _str(_field(d, "map", w), "start.map"), _num(_field(d, "dt_s", w), "start.dt_s"),
                     tuple(_rig_camera(c, f"start.rig[{i}]") for i, c in enumerate(rig)),
                     _matrix(_field(d, "lidar2ego", w), 4, "start.lidar2ego"),
                     _ego_params(_field(d, "ego", w), "start.ego"), _route(_field(d, "route", w), "start.route"))


def _camera_view(d: dict, w: str, inline: bytes) -> CameraView:
    rgb = None
    if "offset" in d:
        off, n = _int(d["offset"], f"{w}.offset"), _int(_field(d, "bytes", w), f"{w}.bytes")
        if off + n > len(inline):
            raise ProtocolError(f"{w}: bytes {off}..{off + n} beyond the {len(inline)} inline bytes")
        rgb = inline[off:off + n]
    c = CameraView(_str(_field(d, "camera", w), f"{w}.camera"), _int(_field(d, "width", w), f"{w}.width"),
                   _int(_field(d, "height", w), f"{w}.height"), _matrix(_field(d, "intrinsic", w), 3, f"{w}.intrinsic"),
                   _matrix(_field(d, "cam2ego", w), 4, f"{w}.cam2ego"),
                   _matrix(_field(d, "ego2global", w), 4, f"{w}.ego2global"),
                   _matrix(_field(d, "lidar2img", w), 4, f"{w}.lidar2img"),
                   int(_str(_field(d, "fnv1a64", w), f"{w}.fnv1a64")), d.get("path"), rgb)
    if rgb is not None and len(rgb) != c.width * c.height * 3:
        raise ProtocolError(f"{w}: {len(rgb)} bytes for a {c.width}x{c.height} RGB image")
    return c


def _ego_past(d: dict, w: str) -> EgoPast:
    v = [_num(_field(d, k, w), f"{w}.{k}") for k in ("time_s", "x", "y", "heading", "vx", "vy", "ax", "ay")]
    src = _str(_field(d, "from", w), f"{w}.from")
    if src not in ("sim", "log", "pad"):
        raise ProtocolError(f"{w}.from: {src!r} (expected sim, log or pad)")
    return EgoPast(*v, src)


def parse_plan(d: dict, inline: bytes = b"", start: Optional[StartInfo] = None) -> PlanRequest:
    """A `plan` message (or a version-1 request); `inline`: the raw bytes after its line (`inline_bytes`)."""
    w = "plan"
    version = _int(_field(d, "version", w), "plan.version")
    e = _field(d, "ego", w)
    ego = EgoState(*(_num(_field(e, k, "plan.ego"), f"plan.ego.{k}") for k in (
        "x", "y", "heading", "vx", "vy", "ax", "ay", "steering", "yaw_rate")))
    r = _field(d, "reply", w)
    frame = _str(r.get("frame", "ego_rear_axle"), "plan.reply.frame")
    spec = ReplySpec(_int(_field(r, "poses", "plan.reply"), "plan.reply.poses"),
                     _num(_field(r, "dt_s", "plan.reply"), "plan.reply.dt_s"), frame,
                     _num(r["min_horizon_s"], "plan.reply.min_horizon_s") if "min_horizon_s" in r else None)
    req = PlanRequest(version, _str(_field(d, "scenario", w), "plan.scenario"), _int(_field(d, "step", w), "plan.step"),
                      _num(_field(d, "time_s", w), "plan.time_s"), ego, _ego_params(e, "plan.ego"),
                      _route(_field(d, "route", w), "plan.route"), spec, start=start, raw=d)
    if version < 2:
        return req
    cams = _field(d, "cameras", w)
    hist = _field(d, "history", w)
    if not isinstance(cams, list) or not isinstance(hist, list):
        raise ProtocolError("plan.cameras and plan.history: expected lists")
    n_inline = _int(d.get("inline_bytes", 0), "plan.inline_bytes")
    if n_inline != len(inline):
        raise ProtocolError(f"plan.inline_bytes: {n_inline}, but {len(inline)} bytes were read")
    try:
        req.command = Command.parse(_field(d, "command", w))
    except ValueError as e:
        raise ProtocolError(f"plan.command: {e}") from None
    req.command_def = _str(_field(d, "command_def", w), "plan.command_def")
    req.history = tuple(_ego_past(h, f"plan.history[{i}]") for i, h in enumerate(hist))
    req.cameras = tuple(_camera_view(c, f"plan.cameras[{i}]", inline) for i, c in enumerate(cams))
    req.ego_in_lidar = _matrix(_field(d, "ego_in_lidar", w), 4, "plan.ego_in_lidar")
    return req


def message_kind(d: dict) -> str:
    """"hello", "start", "plan" or "end" (a version-1 request has no `type`: "plan")."""
    kind = d.get("type", "plan") if isinstance(d, dict) else None
    if kind not in ("hello", "start", "plan", "end"):
        raise ProtocolError(f"message type {kind!r}: expected hello, start, plan or end")
    return kind


def parse_message(d: dict, inline: bytes = b"", start: Optional[StartInfo] = None) -> Message:
    """Any message b2dr sends, as its record (`start`: the session's StartInfo, for plan requests)."""
    kind = message_kind(d)
    if kind == "hello":
        return Hello(_int(_field(d, "version", "hello"), "hello.version"),
                     _num(_field(d, "timeout_s", "hello"), "hello.timeout_s"),
                     _num(_field(d, "start_timeout_s", "hello"), "hello.start_timeout_s"))
    if kind == "start":
        return parse_start(d)
    if kind == "end":
        return End(_str(_field(d, "scenario", "end"), "end.scenario"))
    return parse_plan(d, inline, start)
