#!/usr/bin/env python3
"""An example planner that READS THE IMAGES (protocol v2, the planner package python/b2dr_planner): a simple rule on the front
camera, for `b2dr run --planner "cmd:python3 examples/image_planner.py"`.

- Free space ahead: in the front camera's lower-centre window (the ego's lane over the next ~6-25 m) it counts
  the pixels that do not look like road (asphalt grey or lane paint); many such pixels mean something stands
  ahead, and the planner brakes, harder the lower (nearer) they are.
- Heading: straight on, with an arc when the navigation command says left or right.
Plain Python 3, no dependencies. It sees no boxes and no map: only pixels, the ego state and the command.
"""
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "python"))
from b2dr_planner import serve  # noqa: E402

V_MAX = 8.0          # cruise speed (m/s)
ACCEL = 1.5          # m/s^2
BRAKE = 4.0          # m/s^2
TURN_RADIUS = 11.0   # m


def looks_like_road(r, g, b):
    mx, mn = max(r, g, b), min(r, g, b)
    grey = mx - mn < 28 and 25 <= mx <= 150          # asphalt
    paint = mn > 170 or (r > 150 and g > 120 and b < 90)  # white or yellow markings
    return grey or paint


def obstacle_ahead(cam):
    """Fraction of non-road pixels in the lane window, weighted towards the bottom (near) rows."""
    w, h = cam.width, cam.height
    rgb = cam.rgb()
    x0, x1 = int(w * 0.44), int(w * 0.56)
    y0, y1 = int(h * 0.56), int(h * 0.80)
    score, total = 0.0, 0.0
    for y in range(y0, y1):
        wt = 1.0 + 2.0 * (y - y0) / max(1, y1 - y0)
        row = y * w * 3
        for x in range(x0, x1):
            i = row + 3 * x
            total += wt
            if not looks_like_road(rgb[i], rgb[i + 1], rgb[i + 2]):
                score += wt
    return score / max(total, 1e-9)


def plan(req):
    v = max(0.0, req.ego.vx)
    blocked = 0.0
    try:
        blocked = obstacle_ahead(req.camera("CAM_FRONT"))
    except KeyError:
        pass
    target = 0.0 if blocked > 0.25 else (V_MAX * (1.0 - 2.0 * blocked) if blocked > 0.08 else V_MAX)
    curv = {"left": 1.0 / TURN_RADIUS, "right": -1.0 / TURN_RADIUS}.get(req.command, 0.0)
    x = y = yaw = 0.0
    poses = []
    dt = req.reply.dt_s
    for _ in range(req.reply.poses):
        a = ACCEL if v < target else -BRAKE
        v_next = min(target, v + a * dt) if a > 0 else max(target, v + a * dt)
        s = 0.5 * (v + v_next) * dt
        v = v_next
        yaw_next = yaw + curv * s
        x += s * math.cos(0.5 * (yaw + yaw_next))
        y += s * math.sin(0.5 * (yaw + yaw_next))
        yaw = yaw_next
        poses.append([x, y, yaw])
    return poses


if __name__ == "__main__":
    serve(plan, images="inline")
