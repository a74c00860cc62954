"""A planned trajectory as a model emits it, and the reply b2dr accepts (docs/planner_protocol.md "Reply
(version 2)"): 1-1000 poses, all [x, y, heading] or all [x, y], `dt_s` in [0.01, 2] apart, in the ego
rear-axle frame or the lidar frame, finite, covering at least 2 s. Standard library only."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Optional, Sequence, Tuple

FRAMES = ("ego_rear_axle", "lidar")
MAX_POSES = 1000
MIN_HORIZON_S = 2.0
DT_RANGE = (0.01, 2.0)
MAX_COORD_M = 10_000.0


class TrajectoryError(ValueError):
    """A trajectory b2dr would refuse (the reason named)."""


@dataclass(frozen=True)
class Trajectory:
    """`poses[k]` is the pose at `time_s + dt_s (k + 1)` in `frame` (the current pose is implied)."""

    poses: Tuple[Tuple[float, ...], ...]
    dt_s: float = 0.5
    frame: str = "ego_rear_axle"

    def __init__(self, poses: Iterable[Sequence[float]], dt_s: float = 0.5, frame: str = "ego_rear_axle",
                 min_horizon_s: float = MIN_HORIZON_S):
        if frame not in FRAMES:
            raise TrajectoryError(f"frame {frame!r}: expected one of {FRAMES}")
        if isinstance(dt_s, bool) or not isinstance(dt_s, (int, float)) or not (
                math.isfinite(dt_s) and DT_RANGE[0] <= dt_s <= DT_RANGE[1]):
            raise TrajectoryError(f"dt_s {dt_s!r}: the pose spacing must be in [{DT_RANGE[0]}, {DT_RANGE[1]}] s")
        out = []
        for i, p in enumerate(poses):
            p = tuple(float(v) for v in p)
            if len(p) not in (2, 3):
                raise TrajectoryError(f"poses[{i}] has {len(p)} values: expected [x, y] or [x, y, heading]")
            if not all(math.isfinite(v) for v in p):
                raise TrajectoryError(f"poses[{i}] = {list(p)}: not finite")
            if out and len(p) != len(out[0]):
                raise TrajectoryError(f"poses[0] has {len(out[0])} values but poses[{i}] has {len(p)}")
            if max(abs(p[0]), abs(p[1])) > MAX_COORD_M or (len(p) == 3 and abs(p[2]) > 1000.0):
                raise TrajectoryError(f"poses[{i}] = {list(p)}: beyond {MAX_COORD_M:.0f} m or 1000 rad")
            out.append(p)
        if not 1 <= len(out) <= MAX_POSES:
            raise TrajectoryError(f"{len(out)} poses: 1 to {MAX_POSES} are accepted")
        if len(out) * dt_s < min_horizon_s - 1e-9:
            raise TrajectoryError(f"{len(out)} poses x {dt_s} s cover {len(out) * dt_s:g} s; at least "
                                  f"{min_horizon_s:g} s are required")
        object.__setattr__(self, "poses", tuple(out))
        object.__setattr__(self, "dt_s", float(dt_s))
        object.__setattr__(self, "frame", frame)

    @property
    def xy_only(self) -> bool:
        return len(self.poses[0]) == 2

    @property
    def horizon_s(self) -> float:
        return len(self.poses) * self.dt_s

    def to_reply(self, step: Optional[int] = None) -> dict:
        r = {"poses": [list(p) for p in self.poses], "dt_s": self.dt_s, "frame": self.frame}
        if step is not None:
            r["step"] = step
        return r


def reply(poses, dt_s=None, frame=None, xy_only=False) -> dict:
    """A plan reply dict (`Trajectory` checks): `poses` [x, y, heading] or [x, y], `dt_s` apart (None: 0.5 s,
    not written), in `frame` (None: the ego rear-axle default, not written); `xy_only=True` drops headings.
    Raises ValueError (TrajectoryError) on what b2dr would refuse."""
    pts = [list(p)[:2] if xy_only else p for p in poses]
    t = Trajectory(pts, 0.5 if dt_s is None else dt_s, "ego_rear_axle" if frame is None else frame)
    r = {"poses": [list(p) for p in t.poses]}
    if dt_s is not None:
        r["dt_s"] = t.dt_s
    if frame is not None:
        r["frame"] = t.frame
    return r
