"""Arena payloads for the ROS 2 tests: one representative sample of each payload type a topic of
:data:`arena_common.ros2.topics.TOPICS` reads, with every field the conversions use set to a value that
shows a wrong sign, swap or unit (and NaN where ROS reads "unknown")."""

from __future__ import annotations

import math
from typing import Any

from arena_common.core import wire
from arena_common.ros2.topics import Topic

T0 = 1_700_000_000_123_456_789

#: docs/ros2.md's worked example: 1.25 m north, 0.5 m west, 1 m up, heading 30°, 0.1 m/s north,
#: yawing at 0.05 rad/s.
POSE = wire.Pose(
    t=T0,
    p=(1.25, -0.5, -1.0),
    q=(math.cos(math.radians(15)), 0.0, 0.0, math.sin(math.radians(15))),
    ok=True,
    v=(0.1, 0.0, 0.0),
    w=(0.0, 0.0, 0.05),
    vok=True,
)
STATE = wire.State(
    t=T0 + 1,
    link=True,
    armed=True,
    mode="OFFBOARD",
    volt=11.7,
    bat=None,
    fs=("battery low",),
    vis_fused=False,
    rtt=0.004,
    ofb=True,
)
EVENT = wire.Event(t=T0 + 2, kind="failsafe", text="RC lost", sev=2)

SAMPLES: dict[type[wire.Payload], wire.Payload] = {wire.Pose: POSE, wire.State: STATE, wire.Event: EVENT}


def sample(row: Topic) -> Any:
    """What the row's conversion takes: the sample of its payload type, or a time (the bridge's own)."""
    return T0 if row.payload is None else SAMPLES[row.payload]
