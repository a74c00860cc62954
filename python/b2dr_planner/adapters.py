"""Pure functions from a `PlanRequest` to the inputs of the model families b2dr's users bring (numpy):

- `img_metas(request)`: the per-sample meta dict of mmdet3d-based models (UniAD, VAD, SparseDrive, BEVFormer):
  `lidar2img` per camera at the delivered image size, `can_bus` (18 values, patch angle included),
  `img_shape`, `scene_token`, the command in the family's encoding, ...
- `navsim_agent_input(request)`: NAVSIM's AgentInput as plain data: `ego_statuses` (history, oldest first, the
  current frame last), `cameras` with `sensor2lidar`, `lidars`.

docs/planner_protocol.md "Model inputs" maps each protocol field to these names and units. Nothing here reads
or writes the wire; the records come from `b2dr_planner.records.parse_message`.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence

import numpy as np

from .command import NAVSIM, NAVSIM_UNKNOWN, UNIAD, VAD, encode_command
from .records import PlanRequest

# the nuScenes camera order of UniAD / VAD data infos (b2dr's rigs deliver them in this order too)
NUSCENES_CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
# NAVSIM (nuPlan) camera names of the nuScenes cameras: f0 front, l0 / r0 front-left / -right, l2 / r2 back-left /
# -right, b0 back (nuPlan's side cameras l1 / r1 have no nuScenes counterpart)
NAVSIM_CAMERAS = {"CAM_FRONT": "cam_f0", "CAM_FRONT_LEFT": "cam_l0", "CAM_FRONT_RIGHT": "cam_r0",
                  "CAM_BACK_LEFT": "cam_l2", "CAM_BACK_RIGHT": "cam_r2", "CAM_BACK": "cam_b0"}


def ego2global(request: PlanRequest) -> np.ndarray:
    """The request's ego pose (rear axle, on the ground plane z = 0) as a 4x4 ego -> global matrix: b2dr's
    `scene::import::ego2global`, the pose every rendered image of the request was taken from."""
    c, s = math.cos(request.ego.heading), math.sin(request.ego.heading)
    return np.array([[c, -s, 0, request.ego.x], [s, c, 0, request.ego.y], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)


def viewpad(k: Sequence[Sequence[float]]) -> np.ndarray:
    """The 3x3 intrinsic padded to 4x4 (mmdet3d's `viewpad`)."""
    v = np.eye(4)
    v[:3, :3] = np.asarray(k, np.float64)
    return v


def _lidar2ego(request: PlanRequest) -> np.ndarray:
    if request.start is None:
        raise ValueError("the request has no session (`start`): version-1 requests have no lidar frame")
    return np.asarray(request.start.lidar2ego, np.float64)


def _cameras(request: PlanRequest, cameras: Optional[Sequence[str]]):
    return [request.camera(n) for n in cameras] if cameras is not None else list(request.cameras)


def can_bus(request: PlanRequest) -> np.ndarray:
    """BEVFormer / UniAD / VAD's 18-value `can_bus` of a nuScenes sample, from the request's ego:
    [0:3] ego translation (global, m: rear axle x, y and z = 0), [3:7] ego rotation quaternion (w, x, y, z; a yaw
    about +z), [7:10] acceleration (ego frame, m/s^2: ax, ay, 0; nuScenes' CAN value includes gravity in z, b2dr
    has none), [10:13] rotation rate (rad/s: 0, 0, yaw_rate), [13:16] velocity (ego frame, m/s: vx, vy, 0),
    [16] patch angle (rad), [17] patch angle (deg): the ego yaw in [0, 360) deg (mmdet3d's nuscenes dataset:
    `patch_angle = quaternion_yaw(rotation) / pi * 180`, +360 when negative). Absolute values, as the dataset
    gives them; the models subtract the previous frame's [:3] and [-1] themselves."""
    e = request.ego
    deg = math.degrees(e.heading) % 360.0
    return np.array([e.x, e.y, 0.0, math.cos(e.heading / 2), 0.0, 0.0, math.sin(e.heading / 2),
                     e.ax, e.ay, 0.0, 0.0, 0.0, e.yaw_rate, e.vx, e.vy, 0.0, math.radians(deg), deg], np.float64)


def img_metas(request: PlanRequest, cameras: Optional[Sequence[str]] = None, family: str = UNIAD) -> Dict:
    """The mmdet3d-style meta dict of one request (module docs; docs/planner_protocol.md "Model inputs").
    `cameras`: names in the model's order (default: the request's, in b2dr's rig order, nuScenes' for the
    nuScenes rig); `family`: "uniad" (command an int) or "vad" (one-hot [right, left, straight])."""
    if family not in (UNIAD, VAD):
        raise ValueError(f"img_metas: family {family!r}: expected {UNIAD!r} or {VAD!r}")
    cams = _cameras(request, cameras)
    if not cams:
        raise ValueError("img_metas: the request has no cameras")
    l2e = _lidar2ego(request)
    e2g = ego2global(request)
    lidar2img, lidar2cam, intrinsics = [], [], []
    for c in cams:
        l2i = np.asarray(c.lidar2img, np.float64)
        # lidar -> camera through the image's own ego pose (mmdet3d's sensor2lidar chain via the global frame)
        l2c = np.linalg.inv(np.asarray(c.cam2ego)) @ np.linalg.inv(np.asarray(c.ego2global)) @ e2g @ l2e
        lidar2img.append(l2i)
        lidar2cam.append(l2c)
        intrinsics.append(viewpad(c.intrinsic))
    shapes = [(c.height, c.width, 3) for c in cams]
    return {
        "scene_token": request.scenario,
        "sample_idx": f"{request.scenario}:{request.step}",
        "frame_idx": request.step,
        "timestamp": request.time_s,
        "cameras": [c.name for c in cams],
        "lidar2img": lidar2img,
        "lidar2cam": lidar2cam,
        "cam_intrinsic": intrinsics,
        "img_shape": shapes,
        "ori_shape": shapes,
        "pad_shape": shapes,
        "can_bus": can_bus(request),
        "command": encode_command(request.command, family),
        "ego2global": e2g,
        "lidar2ego": l2e,
        "lidar2global": e2g @ l2e,
    }


def project(lidar2img: np.ndarray, points_lidar: np.ndarray) -> np.ndarray:
    """(N, 3) lidar-frame points -> (N, 3): pixel u, v and camera depth (u, v are NaN where depth <= 0)."""
    p = np.asarray(points_lidar, np.float64)
    q = np.c_[p, np.ones(len(p))] @ np.asarray(lidar2img, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = q[:, :2] / q[:, 2:3]
    uv[q[:, 2] <= 0] = np.nan
    return np.c_[uv, q[:, 2]]


def navsim_agent_input(request: PlanRequest, num_history_frames: int = 4) -> Dict:
    """NAVSIM's AgentInput of one request, as plain data (navsim/common/dataclasses.py names):

    - `ego_statuses`: `num_history_frames` dicts, oldest first, the current frame last (NAVSIM: 4 frames,
      1.5 s at 2 Hz), each `ego_pose` (x, y, heading in the CURRENT rear-axle frame: NAVSIM's local
      coordinates), `ego_velocity` / `ego_acceleration` (m/s, m/s^2 in that frame's own ego frame),
      `driving_command` (one-hot [left, straight, right, unknown]; past frames: unknown, b2dr sends only the
      current command), `in_global_frame` False. Needs `--history` >= num_history_frames - 1.
    - `cameras`: one dict per frame (oldest first), NAVSIM camera name -> `image` ((H, W, 3) uint8 at the
      delivered size; None when not delivered: past frames, images "none"), `sensor2lidar_rotation` (3x3),
      `sensor2lidar_translation` (3,), `intrinsics` (3x3 at the delivered size), `distortion` (zeros: b2dr's
      images are undistorted).
    - `lidars`: None per frame (b2dr renders no point clouds).
    """
    if num_history_frames < 1:
        raise ValueError(f"num_history_frames {num_history_frames}: at least 1 (the current frame)")
    past = list(request.history[:num_history_frames - 1])
    if len(past) < num_history_frames - 1:
        raise ValueError(f"navsim_agent_input: {num_history_frames} frames need {num_history_frames - 1} history "
                         f"states, the request has {len(request.history)} (b2dr run --history)")
    statuses: List[Dict] = []
    for h in reversed(past):  # oldest first
        c, s = math.cos(h.heading), math.sin(h.heading)
        rot = np.array([[c, s], [-s, c]])  # current frame -> that frame's own ego frame
        statuses.append({"ego_pose": np.array([h.x, h.y, h.heading]), "ego_velocity": rot @ [h.vx, h.vy],
                         "ego_acceleration": rot @ [h.ax, h.ay],
                         "driving_command": np.array(NAVSIM_UNKNOWN, np.int64), "in_global_frame": False,
                         "time_s": h.time_s, "source": h.source})
    e = request.ego
    statuses.append({"ego_pose": np.zeros(3), "ego_velocity": np.array([e.vx, e.vy]),
                     "ego_acceleration": np.array([e.ax, e.ay]),
                     "driving_command": np.array(encode_command(request.command, NAVSIM), np.int64),
                     "in_global_frame": False, "time_s": 0.0, "source": "now"})
    lidar_from_ego = np.linalg.inv(_lidar2ego(request))
    current = {}
    for c in request.cameras:
        s2l = lidar_from_ego @ np.asarray(c.cam2ego, np.float64)
        image = c.array() if (c.path or c._rgb is not None) else None
        current[NAVSIM_CAMERAS.get(c.name, c.name)] = {
            "image": image, "sensor2lidar_rotation": s2l[:3, :3], "sensor2lidar_translation": s2l[:3, 3],
            "intrinsics": np.asarray(c.intrinsic, np.float64), "distortion": np.zeros(5)}
    empty = {k: dict(v, image=None) for k, v in current.items()}
    cameras = [dict(empty) for _ in past] + [current]
    return {"ego_statuses": statuses, "cameras": cameras, "lidars": [None] * len(statuses)}
