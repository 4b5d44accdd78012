"""The golden vectors: representative payloads of every wire type, checked by their own round trip
(written to ``tests/golden/`` by :mod:`tools.wiredoc`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError

__all__ = ["Vector", "WireDocError", "vectors"]


class WireDocError(ArenaError):
    """A golden vector that fails its own round trip, or msgpack bytes the annotator cannot read."""


# -- golden vectors ------------------------------------------------------------------------------------

# A fixed instant (2023-11-14T22:13:20.123456789Z) keeps every vector deterministic; it is above 2^53, as
# every real arena time is, so decoders must keep 64-bit integers exact.
_T = 1_700_000_000_123_456_789


@dataclass(frozen=True, slots=True)
class Vector:
    """One golden vector: a named payload, the key it travels on and what it illustrates."""

    name: str
    key: str
    payload: wire.Payload
    note: str

    @property
    def type_name(self) -> str:
        return type(self.payload).SCHEMA

    def raw(self) -> bytes:
        """The msgpack bytes."""
        return self.payload.encode()

    def as_json(self) -> dict[str, Any]:
        """The vector file's content."""
        cls = type(self.payload)
        return {
            "name": self.name,
            "type": cls.SCHEMA,
            "schema": f"arena.{cls.SCHEMA}/{cls.VERSION}",
            "encoding": cls.encoding(),
            "key": self.key,
            "note": self.note,
            "hex": self.raw().hex(),
            "json": wire.to_jsonable(self.payload),
        }


VECTORS: tuple[Vector, ...] = (
    Vector(
        "mocappose_tracked",
        keys.mocap("d1"),
        wire.MocapPose(
            t=_T,
            fn=123456,
            id=1,
            p=(0.512, 1.2085, -0.75),
            q=(0.9238795325112867, 0.0, 0.3826834323650898, 0.0),
            ok=True,
            name="cf1",
            err=0.00021,
            lat=4_250_000,
            mts=1234.5678,
            tsrc="echo",
            tp=_T + 180_000,
        ),
        "A tracked rigid body in Motive's Y-up frame, time from the clock-sync echo exchange.",
    ),
    Vector(
        "mocappose_untracked",
        keys.mocap("d2"),
        wire.MocapPose(t=_T, fn=123457, id=2, p=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 0.0), ok=False),
        "An untracked body: `ok` false (its p and q mean nothing), unknown marker error (NaN, JSON null), "
        "unknown latency (-1).",
    ),
    Vector(
        "mocapframe_two_bodies",
        keys.FRAMES,
        wire.MocapFrame(
            t=_T,
            fn=123456,
            b=(
                wire.MocapBody(
                    v="d1",
                    id=1,
                    p=(0.512, 1.2085, -0.75),
                    q=(0.9238795325112867, 0.0, 0.3826834323650898, 0.0),
                    ok=True,
                    name="cf1",
                    err=0.00021,
                ),
                wire.MocapBody(v="d2", id=2, p=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 0.0), ok=False, name="cf2"),
            ),
            lat=4_250_000,
            mts=1234.5678,
            tsrc="echo",
            tp=_T + 150_000,
        ),
        "One Motive frame with two vehicles' bodies: d1 tracked (as in `mocappose_tracked`), d2 untracked "
        "(`ok` false, its p and q mean nothing; unknown marker error: NaN, JSON null).",
    ),
    Vector(
        "mocapframe_empty",
        keys.FRAMES,
        wire.MocapFrame(t=_T, fn=123458, b=()),
        "A frame without bodies: `b` is an empty array (valid; decoders must accept it); other fields at "
        "their defaults.",
    ),
    Vector(
        "pose_tracked",
        keys.pose("d1"),
        wire.Pose(
            t=_T,
            p=(1.25, -0.5, -1.0),
            q=(0.9659258262890683, 0.0, 0.0, 0.25881904510252074),
            ok=True,
            fn=123456,
            v=(0.1, -0.0, 0.0),
            w=(0.0, 0.0, 0.05),
            vok=True,
            rc=2,
            tp=_T + 250_000,
        ),
        "A tracked pose in the arena frame: 1 m above the floor, yaw 30°, moving north at 0.1 m/s "
        "(the east velocity is a negative zero).",
    ),
    Vector(
        "pose_vision",
        keys.vision("d1"),
        wire.Pose(t=_T, p=(0.0, 0.0, -0.02), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=42),
        "A decimated pose as sent to the autopilot, velocities not estimated (defaults).",
    ),
    Vector(
        "state_flying",
        keys.state("d1"),
        wire.State(
            t=_T,
            sysid=1,
            link=True,
            armed=True,
            mode="OFFBOARD",
            landed="in_air",
            p=(1.2, -0.48, -0.99),
            v=(0.1, 0.0, 0.0),
            q=(0.9659258262890683, 0.0, 0.0, 0.25881904510252074),
            mp=(1.25, -0.5, -1.0),
            bat=0.82,
            volt=11.7,
            rtt=0.0042,
            rtt_jit=0.0003,
            stamps="ours",
            hb_age=0.3,
            vis_rate=50.0,
            vis_age=0.012,
            vis_fused=True,
            ofb=True,
            setup_ok=True,
            fs=(),
            tp=_T + 90_000,
        ),
        "A vehicle flying offboard with every optional field known.",
    ),
    Vector(
        "state_no_link",
        keys.state("d2"),
        wire.State(t=_T, sysid=2, hb_age=4.2, fs=("link lost", "no vision")),
        "A gateway whose autopilot stopped answering: optional fields it does not know are omitted.",
    ),
    Vector(
        "telemetry_heartbeat",
        keys.telemetry("d1", "HEARTBEAT"),
        wire.Telemetry(
            t=_T,
            msg="HEARTBEAT",
            f={
                "type": 2,
                "autopilot": 12,
                "base_mode": 157,
                "custom_mode": 393216,
                "system_status": 4,
                "mavlink_version": 3,
            },
        ),
        "A raw MAVLink HEARTBEAT (custom_mode 393216 = OFFBOARD).",
    ),
    Vector(
        "telemetry_attitude",
        keys.telemetry("d1", "ATTITUDE_QUATERNION"),
        wire.Telemetry(
            t=_T,
            msg="ATTITUDE_QUATERNION",
            f={
                "time_boot_ms": 5_000_123,
                "q1": 0.9659258,
                "q2": 0.0,
                "q3": 0.0,
                "q4": 0.258819,
                "rollspeed": -0.001,
                "pitchspeed": 0.002,
                "yawspeed": 0.0,
                "repr_offset_q": [0.0, 0.0, 0.0, 0.0],
            },
        ),
        "A raw MAVLink message with float fields and an array field.",
    ),
    Vector(
        "telemetry_system_time",
        keys.telemetry("d1", "SYSTEM_TIME"),
        wire.Telemetry(
            t=_T, msg="SYSTEM_TIME", f={"time_unix_usec": 1_700_000_000_123_456, "time_boot_ms": 5_000}
        ),
        "A raw MAVLink message with a 64-bit unsigned field.",
    ),
    Vector(
        "event_statustext",
        keys.events("d1"),
        wire.Event(t=_T, kind="statustext", text="Takeoff detected", sev=6),
        "A status text forwarded from the autopilot.",
    ),
    Vector(
        "event_failsafe",
        keys.events("d1"),
        wire.Event(
            t=_T,
            kind="failsafe",
            text="vision lost: landing",
            sev=2,
            data={"cause": "vision", "action": "land", "age": 0.45},
        ),
        "A failsafe with details.",
    ),
    Vector(
        "command_takeoff",
        keys.cmd("d1"),
        wire.Command(op="takeoff", args={"height": 1.0}, src="lab-pc/user.py", timeout=10.0, t=_T),
        "Take off to 1 m; the caller waits up to 10 s.",
    ),
    Vector(
        "command_goto",
        keys.cmd("d1"),
        wire.Command(op="goto", args={"p": [1.0, 0.5, -1.2], "yaw": 1.5707963267948966}, t=_T),
        "Fly to a point of the arena (NED) facing east.",
    ),
    Vector(
        "command_param_set",
        keys.cmd("d1"),
        wire.Command(op="param_set", args={"name": "EKF2_EV_DELAY", "value": 20.0}, src="arena", t=_T),
        "Set an autopilot parameter.",
    ),
    Vector(
        "commandresult_accepted",
        keys.cmd("d1"),
        wire.CommandResult(ok=True, result="ACCEPTED", t=_T + 35_000_000),
        "The autopilot accepted the command (the reply to a query on arena/d1/cmd).",
    ),
    Vector(
        "commandresult_refused",
        keys.cmd("d1"),
        wire.CommandResult(
            ok=False,
            result="REFUSED",
            reason="no valid pose for 2.0 s: will not arm",
            t=_T + 1_000_000,
        ),
        "The gateway refused under the arena's safety rules.",
    ),
    Vector(
        "commandresult_param",
        keys.cmd("d1"),
        wire.CommandResult(
            ok=True, result="ACCEPTED", value={"EKF2_EV_DELAY": 20.0, "EKF2_EV_CTRL": 15}, t=_T + 80_000_000
        ),
        "A reply carrying data (parameter values).",
    ),
    Vector(
        "setpoint_position",
        keys.setpoint("d1"),
        wire.Setpoint(t=_T, lease=0.5, p=(1.0, 0.5, -1.2), yaw=0.0, src="lab-pc/user.py"),
        "Hold a position with a yaw, valid for 0.5 s.",
    ),
    Vector(
        "setpoint_velocity",
        keys.setpoint("d1"),
        wire.Setpoint(t=_T, lease=0.2, v=(0.5, 0.0, -0.1), yr=-0.25),
        "Fly a velocity with a yaw rate, valid for 0.2 s.",
    ),
    Vector(
        "estop_land",
        keys.ESTOP,
        wire.Estop(t=_T, reason="operator pressed stop", src="ground/arena"),
        "Land every vehicle.",
    ),
    Vector(
        "estop_kill",
        keys.ESTOP,
        wire.Estop(t=_T, kill=True, reason="fly-away", src="ground/arena"),
        "Cut every vehicle's motors.",
    ),
    Vector(
        "stats_gateway",
        keys.stats("ground", "gateway.d1"),
        wire.Stats(
            t=_T,
            service="gateway.d1",
            host="ground",
            pid=4242,
            up=3600.25,
            counts={"in": 648000, "out": 180000},
            rejected={"stale": 3, "invalid": 1},
            rates={"in": 180.0, "out": 50.0},
            lat={"p50": 0.00011, "p99": 0.0009, "max": 0.0031},
            cpu=2.5,
            rss=52_428_800,
            vehicle="d1",
        ),
        "One second of a gateway's counters.",
    ),
    Vector(
        "clockoffset_companion",
        keys.clock("cc1", "gateway.d1"),
        wire.ClockOffset(
            t=_T,
            host="cc1",
            service="gateway.d1",
            state="ok",
            ref="ground",
            off=-0.30025,
            unc=0.0007,
            rtt=0.0016,
            n=120,
        ),
        "A companion computer whose clock is 0.300 s ahead of the mocap host's, known to ±0.7 ms.",
    ),
    Vector(
        "fleet_two",
        keys.FLEET,
        wire.Fleet(
            t=_T,
            b=(
                wire.FleetVehicle("d1", (-1.0, 0.0, -1.0), (0.4, 0.0, 0.0)),
                wire.FleetVehicle("d2", (0.5, 0.25, -1.2), (0.0, 0.0, 0.0)),
            ),
        ),
        "Two vehicles: d1 flying north at 0.4 m/s toward d2, which hovers.",
    ),
    Vector(
        "vision_frame_two",
        keys.VISIONS,
        wire.VisionFrame(
            fn=123456,
            b=(
                wire.VisionBody(
                    "d1",
                    _T,
                    (-1.0, 0.0, -1.0),
                    (1.0, 0.0, 0.0, 0.0),
                    True,
                    123456,
                    (0.4, 0.0, 0.0),
                    vok=True,
                    tp=_T + 1_200_000,
                ),
                wire.VisionBody("d2", _T, (0.5, 0.25, -0.05), (1.0, 0.0, 0.0, 0.0), False, 123456),
            ),
            tp=_T + 1_300_000,
        ),
        "One mocap frame's vision: d1 flying north at 0.4 m/s, d2 lost by Motive (never sent to its autopilot).",
    ),
)


def vectors() -> tuple[Vector, ...]:
    """The golden vectors, each checked to survive its own decode and re-encode."""
    for vec in VECTORS:
        cls = type(vec.payload)
        raw = vec.raw()
        back = cls.decode(raw, vec.key)
        if wire.to_jsonable(back) != wire.to_jsonable(vec.payload):
            raise WireDocError(f"golden vector {vec.name!r} does not decode to itself")
        if back.encode() != raw:
            raise WireDocError(f"golden vector {vec.name!r} does not re-encode to the same bytes")
        if cls is not wire.CommandResult and wire.type_for_key(vec.key) is not cls:
            raise WireDocError(f"golden vector {vec.name!r}: key {vec.key} does not carry {cls.SCHEMA}")
    return VECTORS
