"""The navigation command of protocol v2 and each model family's encoding of it (docs/planner_protocol.md
"Navigation command"; b2dr's side: src/sim/command.rs, src/sim/sensors.rs `Command`).

Sources of the encodings (read 2026-12):
- UniAD: OpenDriveLab/UniAD projects/mmdet3d_plugin/datasets/data_utils/trajectory_api.py,
  get_sdc_planning_label: `command = 0 #'RIGHT'` (lidar x >= 2), `1 #'LEFT'` (x <= -2), `2 #'FORWARD'`.
- VAD: hustvl/VAD tools/data_converter/vad_nuscenes_converter.py (lines 452-457): `[1, 0, 0]  # Turn Right`,
  `[0, 1, 0]  # Turn Left`, `[0, 0, 1]  # Go Straight` (gt_ego_fut_cmd).
- NAVSIM: the driving_command of its OpenScene data, OpenScene DriveEngine/process_data/helpers/
  driving_command.py get_driving_command: "one-hot (left, forward, right, unknown)"; unknown where no route.
"""
from __future__ import annotations

import enum
from typing import List, Optional, Union

UNIAD, VAD, NAVSIM = "uniad", "vad", "navsim"
FAMILIES = (UNIAD, VAD, NAVSIM)


class Command(str, enum.Enum):
    """b2dr's three commands; the value is the wire string."""

    LEFT = "left"
    RIGHT = "right"
    STRAIGHT = "straight"

    # equal to its string AND hashed like it, so `{"left": ...}.get(command)` finds it (Enum hashes the name)
    def __hash__(self) -> int:
        return str.__hash__(self)

    def __str__(self) -> str:
        return self.value

    @classmethod
    def parse(cls, value: object) -> "Command":
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"command {value!r}: expected one of {[c.value for c in cls]}") from None

    def encode(self, family: str) -> Union[int, List[int]]:
        """This command as `family` ("uniad", "vad", "navsim") consumes it."""
        return encode_command(self, family)


_ENCODINGS = {
    UNIAD: {Command.RIGHT: 0, Command.LEFT: 1, Command.STRAIGHT: 2},
    VAD: {Command.RIGHT: [1, 0, 0], Command.LEFT: [0, 1, 0], Command.STRAIGHT: [0, 0, 1]},
    NAVSIM: {Command.LEFT: [1, 0, 0, 0], Command.STRAIGHT: [0, 1, 0, 0], Command.RIGHT: [0, 0, 1, 0]},
}
NAVSIM_UNKNOWN = [0, 0, 0, 1]


def encode_command(command: Optional[Union[Command, str]], family: str) -> Union[int, List[int]]:
    """b2dr's command (a `Command` or its string) as `family` consumes it. None (no command) is NAVSIM's unknown
    [0, 0, 0, 1]; UniAD and VAD have no such value: ValueError, as for an unknown command or family."""
    if family not in _ENCODINGS:
        raise ValueError(f"unknown model family {family!r}: expected one of {list(FAMILIES)}")
    if command is None:
        if family == NAVSIM:
            return list(NAVSIM_UNKNOWN)
        raise ValueError(f"no command: {family} has no encoding for a missing command")
    e = _ENCODINGS[family][Command.parse(command)]
    return list(e) if isinstance(e, list) else e
