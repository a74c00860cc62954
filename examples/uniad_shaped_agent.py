#!/usr/bin/env python3
"""A "UniAD-shaped" example agent (issue #34): a fixed rule whose inputs are built the way an mmdet3d model's are
(`b2dr_planner.adapters.img_metas`: lidar2img, can_bus, command in UniAD's int encoding, img_shape) and whose
output is what UniAD / VAD emit: 6 xy points 0.5 s apart in the nuScenes lidar frame. A stand-in for a real
model when checking the plumbing (resident service, lidar frame, xy-only trajectories); it needs numpy.

- Free space: ground points on the ego's path 6-25 m ahead are taken into the lidar frame and projected into
  CAM_FRONT with the adapter's `lidar2img`; pixels around them that do not look like road (asphalt grey or lane
  paint) mean something stands ahead, and the agent brakes, harder the nearer they are.
- Speed from `can_bus[13:15]` (ego-frame velocity), heading change from UniAD's command (0 right, 1 left,
  2 forward) on an arc of fixed radius.

    b2dr run --scenario builtin:town --renderer groundtruth --cameras CAM_FRONT \
        --planner "resident:python3 examples/uniad_shaped_agent.py" --out runs/uniad-shaped

    --loads FILE        append a line per model load (tests count them)
    --load-sleep S      the load takes S seconds (a big model's load, outside --planner-timeout when resident)
"""
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "python"))
from b2dr_planner import Agent, Trajectory, serve_agent  # noqa: E402
from b2dr_planner.adapters import img_metas, project  # noqa: E402

V_MAX, ACCEL, BRAKE, TURN_RADIUS = 8.0, 1.5, 4.0, 11.0  # m/s, m/s^2, m/s^2, m
AHEAD_M = np.linspace(6.0, 25.0, 12)  # free-space probes on the path (m ahead of the rear axle)
LATERAL_M = np.linspace(-0.8, 0.8, 5)


def arg(name, default=None):
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


def looks_like_road(rgb):
    """(N, 3) uint8 -> (N,) bool: asphalt grey or white / yellow paint."""
    c = rgb.astype(np.int16)
    mx, mn = c.max(1), c.min(1)
    grey = (mx - mn < 28) & (mx >= 25) & (mx <= 150)
    paint = (mn > 170) | ((c[:, 0] > 150) & (c[:, 1] > 120) & (c[:, 2] < 90))
    return grey | paint


class UniADShapedAgent(Agent):
    images = "inline"
    cameras = ("CAM_FRONT",)
    poses, dt_s, frame = 6, 0.5, "lidar"

    def initialize(self):
        # a real model loads its weights here: once per process (resident: under --planner-start-timeout)
        time.sleep(float(arg("--load-sleep", "0")))
        if arg("--loads"):
            with open(arg("--loads"), "a") as f:
                f.write(f"{os.getpid()}\n")

    def start(self, session):
        self.lidar_from_ego = np.linalg.inv(np.asarray(session.lidar2ego))

    def blocked(self, metas, image):
        """Weighted fraction of non-road pixels at the path probes (nearer probes weigh more)."""
        (h, w, _), l2i = metas["img_shape"][0], metas["lidar2img"][0]
        ego = np.array([[x, y, 0.0] for x in AHEAD_M for y in LATERAL_M])
        lidar = ego @ self.lidar_from_ego[:3, :3].T + self.lidar_from_ego[:3, 3]
        uv = project(l2i, lidar)[:, :2]
        weight = np.repeat(1.0 + 2.0 * (AHEAD_M[-1] - AHEAD_M) / (AHEAD_M[-1] - AHEAD_M[0]), len(LATERAL_M))
        ok = np.isfinite(uv).all(1)
        ok[ok] &= (uv[ok, 0] >= 0) & (uv[ok, 0] <= w - 1) & (uv[ok, 1] >= 0) & (uv[ok, 1] <= h - 1)
        if not ok.any():
            return 0.0
        px = np.rint(uv[ok]).astype(int)
        off_road = ~looks_like_road(image[px[:, 1], px[:, 0]])
        return float((weight[ok] * off_road).sum() / weight[ok].sum())

    def step(self, req):
        metas = img_metas(req, cameras=["CAM_FRONT"], family="uniad")
        v = max(0.0, float(math.hypot(metas["can_bus"][13], metas["can_bus"][14])))
        blocked = self.blocked(metas, req.camera("CAM_FRONT").array())
        target = 0.0 if blocked > 0.25 else (V_MAX * (1.0 - 2.0 * blocked) if blocked > 0.08 else V_MAX)
        curv = {1: 1.0 / TURN_RADIUS, 0: -1.0 / TURN_RADIUS}.get(metas["command"], 0.0)
        x = y = yaw = 0.0
        ego = []
        for _ in range(self.poses):
            a = ACCEL if v < target else -BRAKE
            v_next = min(target, v + a * self.dt_s) if a > 0 else max(target, v + a * self.dt_s)
            s = 0.5 * (v + v_next) * self.dt_s
            v, yaw_next = v_next, yaw + curv * s
            x += s * math.cos(0.5 * (yaw + yaw_next))
            y += s * math.sin(0.5 * (yaw + yaw_next))
            yaw = yaw_next
            ego.append([x, y, 0.0])
        lidar = np.asarray(ego) @ self.lidar_from_ego[:3, :3].T + self.lidar_from_ego[:3, 3]
        return Trajectory(lidar[:, :2], dt_s=self.dt_s, frame="lidar")


if __name__ == "__main__":
    serve_agent(UniADShapedAgent())
