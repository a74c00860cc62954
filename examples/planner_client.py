#!/usr/bin/env python3
"""Example external planner for `b2dr sim --planner "cmd:python3 examples/planner_client.py"`.

Speaks the JSON-lines protocol of docs/planner_protocol.md over stdin/stdout (plain python3, no
dependencies): one request per line in, one reply per line out. This client keeps the current speed and
follows a gentle arc towards zero heading change (a constant-velocity baseline).

Test modes (for b2dr's tests): --mode crash | hang | nan | short | empty | cv.
"""
import json
import math
import sys
import time


def plan(req, mode):
    ego = req["ego"]
    n = req.get("reply", {}).get("poses", 8)
    dt = req.get("reply", {}).get("dt_s", 0.5)
    v = max(0.0, ego["vx"])
    poses = [[v * dt * (k + 1), 0.0, 0.0] for k in range(n)]
    if mode == "nan":
        poses[3][1] = float("nan")
    elif mode == "short":
        poses = poses[:3]
    elif mode == "empty":
        poses = []
    return {"poses": poses}


def main():
    mode = "cv"
    if "--mode" in sys.argv:
        mode = sys.argv[sys.argv.index("--mode") + 1]
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        req = json.loads(line)
        if mode == "crash" and req["step"] >= 10:
            sys.exit(3)
        if mode == "hang" and req["step"] >= 10:
            time.sleep(3600)
        reply = plan(req, mode)
        # json.dumps writes NaN as the bare token NaN, which is not JSON: b2dr rejects such a reply.
        sys.stdout.write(json.dumps(reply) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
