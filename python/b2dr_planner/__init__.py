"""b2dr_planner: write a planner for b2dr's closed loop (protocol v2, docs/planner_protocol.md).

Typed records of what b2dr sends (`StartInfo` per scenario, `PlanRequest` per step; one parser,
`parse_message`), the `Agent` base class (initialize / start / step -> Trajectory / end, timed and checked),
the service loop (`serve_agent`; `serve(plan)` for a plain function) over stdin/stdout for `cmd:` and
`resident:` planners, the shared `Command` enum with each family's encoding, and pure-function adapters to
model inputs (`b2dr_planner.adapters`: mmdet3d `img_metas`, NAVSIM agent input; numpy).

The core imports the standard library only (a planner script runs on a bare python3); the adapters need numpy.

    from b2dr_planner import Agent, Trajectory, serve_agent
    from b2dr_planner.adapters import img_metas

    class MyAgent(Agent):
        images, size, poses, dt_s, frame = "inline", (224, 400), 6, 0.5, "lidar"
        def initialize(self): ...                  # weights; under --planner-start-timeout when resident
        def step(self, req):
            metas = img_metas(req)                  # lidar2img, can_bus, img_shape, command, ...
            return Trajectory(xy, dt_s=0.5, frame="lidar")

    if __name__ == "__main__":
        serve_agent(MyAgent())
"""
from .agent import Agent
from .command import FAMILIES, NAVSIM, UNIAD, VAD, Command, encode_command
from .images import fnv1a64, read_png_rgb
from .records import (CameraView, EgoParams, EgoPast, EgoState, End, Hello, PlanRequest, ProtocolError,
                      ReplySpec, RigCamera, Route, StartInfo, message_kind, parse_message, parse_plan, parse_start,
                      transform)
from .service import FunctionAgent, serve, serve_agent
from .trajectory import Trajectory, TrajectoryError, reply

# version-1 era names of examples/b2dr_planner.py
Request = PlanRequest
Camera = CameraView


def ego_to_lidar(req: PlanRequest, p_ego):
    """A rear-axle ego-frame point -> the request's lidar frame (`PlanRequest.ego_to_lidar`)."""
    return req.ego_to_lidar(p_ego)


__all__ = ["Agent", "CameraView", "Camera", "Command", "EgoParams", "EgoPast", "EgoState", "End", "FAMILIES",
           "FunctionAgent", "Hello", "NAVSIM", "PlanRequest", "ProtocolError", "ReplySpec", "Request", "RigCamera",
           "Route", "StartInfo", "Trajectory", "TrajectoryError", "UNIAD", "VAD", "ego_to_lidar", "encode_command",
           "fnv1a64", "message_kind", "parse_message", "parse_plan", "parse_start", "read_png_rgb", "reply", "serve",
           "serve_agent", "transform"]
