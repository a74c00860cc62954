"""The planner's side of protocol v2 over stdin/stdout (docs/planner_protocol.md; b2dr's side:
src/sim/external.rs, src/sim/resident.rs): JSON lines, one reply per `hello`, `start` and `plan`, none to `end`.

- `hello` (resident mode, `b2dr run --planner resident:...`, once per process): `initialize()` runs here, under
  b2dr's start timeout; reply `{"ready": true}`, or `{"error": "load failed: ..."}`.
- `start`: (cmd: mode: `initialize()` first, once) `start(session)`; reply `{"images", "size"}`, or `{"error"}`
  (b2dr ends that scenario only).
- `plan`: the request (with its `inline_bytes`) parsed by `records.parse_message`; reply the checked trajectory
  with the request's `step` echoed, or `{"error": ...}` when `step` raises or the trajectory is refused (b2dr
  ends that scenario, with this reason, and keeps the process).
- `end`: `end()`; no reply. Sessions repeat until stdin ends.
"""
from __future__ import annotations

import json
import sys
import traceback
from typing import BinaryIO, Callable, Optional, TextIO

from .agent import Agent
from .records import End, Hello, PlanRequest, ProtocolError, StartInfo, message_kind, parse_message


def _read_exact(stream: BinaryIO, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            raise EOFError("b2dr closed the input mid-message")
        buf += chunk
    return buf


def _error(e: BaseException) -> dict:
    traceback.print_exc(file=sys.stderr)
    return {"error": f"{type(e).__name__}: {e}"}


def serve_agent(agent: Agent, inp: Optional[BinaryIO] = None, out: Optional[TextIO] = None) -> None:
    """Serves `agent` until the input ends (module docs): one `cmd:` scenario or a resident batch."""
    inp = inp if inp is not None else sys.stdin.buffer
    out = out if out is not None else sys.stdout
    start: Optional[StartInfo] = None

    def send(answer: dict) -> None:
        out.write(json.dumps(answer) + "\n")
        out.flush()

    while True:
        line = inp.readline()
        if not line:
            return
        line = line.strip()
        if not line:
            continue
        d = json.loads(line)
        inline = b""
        if message_kind(d) == "plan" and d.get("inline_bytes"):
            inline = _read_exact(inp, int(d["inline_bytes"]))
        try:
            msg = parse_message(d, inline, start)
        except ProtocolError as e:
            if message_kind(d) == "end":
                raise
            send(_error(e))
            continue
        if isinstance(msg, Hello):
            try:
                agent.run_initialize()
                send({"ready": True})
            except Exception as e:  # the load failed: b2dr fails the scenario with this
                send({"error": f"load failed: {type(e).__name__}: {e}"})
        elif isinstance(msg, StartInfo):
            start = msg
            try:
                agent.run_initialize()  # cmd: mode (resident: done at hello)
            except Exception as e:
                send({"error": f"load failed: {type(e).__name__}: {e}"})
                continue
            try:
                send(agent.run_start(msg))
            except Exception as e:
                send(_error(e))
        elif isinstance(msg, End):
            agent.run_end()
            start = None
        else:
            try:
                send(agent.run_step(msg))
            except Exception as e:
                send(_error(e) | {"step": msg.step})


class FunctionAgent(Agent):
    """`serve(plan, ...)`'s agent: `plan(request)` returns a `Trajectory`, a list of [x, y, heading] poses (ego
    frame, 0.5 s apart) or a reply dict (`reply(...)`, `{"error": ...}`), sent as returned: a list or dict is
    NOT checked (b2dr's protocol tests send replies b2dr must refuse this way)."""

    def __init__(self, plan, images="paths", size=None, on_start=None, on_end=None, load=None):
        self.images, self.size = images, (tuple(size) if size else None)
        super().__init__()
        self._plan, self._on_start, self._on_end, self._load = plan, on_start, on_end, load

    def initialize(self):
        if self._load:
            self._load()

    def start(self, session):
        if self._on_start:
            self._on_start(session)

    def end(self):
        if self._on_end:
            self._on_end()

    def run_step(self, request: PlanRequest) -> dict:
        r = self._timed("step", self._plan, request)
        if hasattr(r, "to_reply"):
            self.check(r, request)
            return r.to_reply(request.step)
        answer = r if isinstance(r, dict) else {"poses": r}
        answer.setdefault("step", request.step)
        return answer


def serve(plan: Callable, images: str = "paths", size=None, on_start=None, on_end=None, load=None) -> None:
    """Serves a plain function (`FunctionAgent`): `load()` once before the first session (at `hello` when
    resident, else at the first `start`), `on_start(StartInfo)`, `on_end()`."""
    serve_agent(FunctionAgent(plan, images, size, on_start, on_end, load))
