"""The planner base class, shaped like NAVSIM's AbstractAgent and nuPlan's AbstractPlanner: a subclass declares
the images it wants and the trajectory it returns, loads its weights in `initialize()` (once per process:
outside the per-call timeout when resident), and implements `step(request) -> Trajectory`. The base class times
every call and checks each returned trajectory against the declaration and b2dr's rules before it is sent.

    class MyAgent(Agent):
        images, size = "inline", (224, 400)         # what `start` asks b2dr for
        poses, dt_s, frame = 6, 0.5, "lidar"        # what `step` returns (None: not checked)
        def initialize(self): self.net = load_weights(...)
        def step(self, req): return Trajectory(self.net(img_metas(req)), dt_s=0.5, frame="lidar")

    serve_agent(MyAgent())                          # b2dr_planner.service
"""
from __future__ import annotations

import sys
import time
from typing import Dict, List, Optional, Tuple

from .records import PlanRequest, StartInfo
from .trajectory import FRAMES, Trajectory, TrajectoryError


class Agent:
    #: "paths" (PNG files), "inline" (raw bytes after the request) or "none"
    images: str = "none"
    #: (height, width) the images (and intrinsics, lidar2img) are delivered at; None: the renderer's size
    size: Optional[Tuple[int, int]] = None
    #: cameras `step` needs (checked in every request; b2dr run --cameras picks what is rendered)
    cameras: Tuple[str, ...] = ()
    #: the declared output: pose count, spacing (s), frame; None leaves that property unchecked
    poses: Optional[int] = None
    dt_s: Optional[float] = None
    frame: Optional[str] = None

    def __init__(self):
        if self.images not in ("paths", "inline", "none"):
            raise ValueError(f"{type(self).__name__}.images {self.images!r}: expected paths, inline or none")
        if self.frame is not None and self.frame not in FRAMES:
            raise ValueError(f"{type(self).__name__}.frame {self.frame!r}: expected one of {FRAMES}")
        #: wall seconds of every call, per method ("initialize", "start", "step", "end")
        self.timings: Dict[str, List[float]] = {"initialize": [], "start": [], "step": [], "end": []}
        self.session: Optional[StartInfo] = None
        self.initialized = False
        self._session_steps = 0  # index of this session's first step in timings["step"]

    # --- what a planner implements -------------------------------------------------------------------
    def initialize(self) -> None:
        """Load weights (once per process)."""

    def start(self, session: StartInfo) -> None:
        """A scenario begins (reset per-scenario state: previous frames, BEV history)."""

    def step(self, request: PlanRequest) -> Trajectory:
        raise NotImplementedError(f"{type(self).__name__} must implement step(request) -> Trajectory")

    def end(self) -> None:
        """The scenario ended (no reply is sent)."""

    # --- what the service loop calls ------------------------------------------------------------------
    def _timed(self, name, fn, *args):
        t0 = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.timings[name].append(time.perf_counter() - t0)

    def run_initialize(self) -> None:
        if not self.initialized:
            self._timed("initialize", self.initialize)
            self.initialized = True

    def run_start(self, session: StartInfo) -> dict:
        """The reply to `start` (after `start(session)`)."""
        self.session = session
        self._session_steps = len(self.timings["step"])
        self._timed("start", self.start, session)
        answer = {"images": self.images}
        if self.size is not None:
            answer["size"] = [int(self.size[0]), int(self.size[1])]
        return answer

    def run_step(self, request: PlanRequest) -> dict:
        """The reply to a `plan` request: the checked trajectory, echoing the request's step."""
        missing = [c for c in self.cameras if c not in {v.name for v in request.cameras}]
        if missing:
            raise ValueError(f"the request lacks camera(s) {missing} (b2dr run --cameras)")
        t = self._timed("step", self.step, request)
        self.check(t, request)
        return t.to_reply(request.step)

    def run_end(self) -> None:
        self._timed("end", self.end)
        s = self.timings["step"][self._session_steps:]
        if s and self.session is not None:
            print(f"{type(self).__name__}: {self.session.scenario}: {len(s)} steps, step mean "
                  f"{1e3 * sum(s) / len(s):.1f} ms, max {1e3 * max(s):.1f} ms", file=sys.stderr, flush=True)
        self.session = None

    def check(self, t: Trajectory, request: PlanRequest) -> None:
        """The returned trajectory against the declaration and the request's minimum horizon."""
        name = type(self).__name__
        if not isinstance(t, Trajectory):
            raise TrajectoryError(f"{name}.step returned {type(t).__name__}, expected a Trajectory")
        if self.poses is not None and len(t.poses) != self.poses:
            raise TrajectoryError(f"{name}.step returned {len(t.poses)} poses, it declares {self.poses}")
        if self.dt_s is not None and abs(t.dt_s - self.dt_s) > 1e-9:
            raise TrajectoryError(f"{name}.step returned dt_s {t.dt_s}, it declares {self.dt_s}")
        if self.frame is not None and t.frame != self.frame:
            raise TrajectoryError(f"{name}.step returned frame {t.frame!r}, it declares {self.frame!r}")
        need = request.reply.min_horizon_s
        if need is not None and t.horizon_s < need - 1e-9:
            raise TrajectoryError(f"{name}.step covers {t.horizon_s:g} s, the request needs {need:g} s")
