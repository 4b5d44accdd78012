"""Typed readings of a vehicle: flight mode, landed state, status, poses with their source and age,
IMU, battery and estimator status.

Every reading carries ``t``, the time it describes (ns on the arena's wall clock: a mocap pose's
measurement time, a message's receive time), and ``received``, when this program got it
(``time.monotonic()``); ``age`` is the seconds since then.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from arena_common.core import wire
from arena_common.geometry.quat import quat_yaw
from arena_common.mavlink import px4

__all__ = [
    "Battery",
    "EstimatorStatus",
    "FlightMode",
    "Imu",
    "LandedState",
    "PoseReading",
    "Status",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
G = 9.80665


class FlightMode(enum.StrEnum):
    """PX4's flight modes by PX4's (and mavros') names; compares equal to those strings."""

    MANUAL = "MANUAL"
    ALTCTL = "ALTCTL"
    POSCTL = "POSCTL"
    POSCTL_ORBIT = "POSCTL.ORBIT"
    POSCTL_SLOW = "POSCTL.SLOW"
    AUTO_MISSION = "AUTO.MISSION"
    AUTO_LOITER = "AUTO.LOITER"
    AUTO_RTL = "AUTO.RTL"
    AUTO_LAND = "AUTO.LAND"
    AUTO_TAKEOFF = "AUTO.TAKEOFF"
    AUTO_READY = "AUTO.READY"
    AUTO_RTGS = "AUTO.RTGS"
    AUTO_FOLLOW_TARGET = "AUTO.FOLLOW_TARGET"
    AUTO_PRECLAND = "AUTO.PRECLAND"
    AUTO_VTOL_TAKEOFF = "AUTO.VTOL_TAKEOFF"
    OFFBOARD = "OFFBOARD"
    STABILIZED = "STABILIZED"
    ACRO = "ACRO"
    RATTITUDE = "RATTITUDE"
    SIMPLE = "SIMPLE"
    TERMINATION = "TERMINATION"
    UNKNOWN = "UNKNOWN"
    CUSTOM = "CUSTOM"  # a mode this version does not know (a newer PX4): ``Status.mode_name`` has it

    HOLD = "AUTO.LOITER"  # MAVSDK's name for the same mode

    @classmethod
    def parse(cls, name: str) -> FlightMode:
        """The mode of a name as the gateway reports it (``"CUSTOM(main=…)"`` → :attr:`CUSTOM`)."""
        try:
            return cls(name)
        except ValueError:
            return cls.CUSTOM if name.startswith("CUSTOM") else cls.UNKNOWN


class LandedState(enum.StrEnum):
    """MAV_LANDED_STATE; compares equal to the gateway's strings (``"on_ground"``…)."""

    UNDEFINED = "undefined"
    ON_GROUND = "on_ground"
    IN_AIR = "in_air"
    TAKEOFF = "takeoff"
    LANDING = "landing"

    @classmethod
    def parse(cls, name: str) -> LandedState:
        try:
            return cls(name)
        except ValueError:
            return cls.UNDEFINED


class _Timed:
    __slots__ = ()
    received: float

    @property
    def age(self) -> float:
        """Seconds since this program received it."""
        return time.monotonic() - self.received


@dataclass(frozen=True, slots=True)
class Status(_Timed):
    """The vehicle's state as its gateway reports it (``arena/<drone>/state``), typed."""

    t: int
    received: float
    link: bool
    armed: bool
    mode: FlightMode
    mode_name: str
    landed: LandedState
    battery: float | None  # remaining, 0–1
    voltage: float | None  # V
    offboard: bool  # setpoints are being streamed to the autopilot
    vision_fused: bool
    vision_rate: float  # Hz
    setup_ok: bool
    failsafes: tuple[str, ...]
    heartbeat_age: float | None  # s, at the gateway
    rtt: float | None  # s, link round trip
    holder: str = ""  # who holds the vehicle: a stream, the gateway's goto, "" (the autopilot's mode)

    @classmethod
    def from_wire(cls, s: wire.State, received: float) -> Status:
        return cls(
            t=s.t,
            received=received,
            link=s.link,
            armed=s.armed,
            mode=FlightMode.parse(s.mode),
            mode_name=s.mode,
            landed=LandedState.parse(s.landed),
            battery=s.bat,
            voltage=s.volt,
            offboard=s.ofb,
            vision_fused=s.vis_fused,
            vision_rate=s.vis_rate,
            setup_ok=s.setup_ok,
            failsafes=tuple(s.fs),
            heartbeat_age=s.hb_age,
            rtt=s.rtt,
            holder=s.auth,
        )


@dataclass(frozen=True, slots=True)
class PoseReading(_Timed):
    """A pose from one named source — ``"mocap"`` (``arena/<drone>/pose``) or ``"estimate"`` (the
    autopilot's) — with its validity at the moment it was read and, when not valid, why."""

    source: str
    t: int  # ns: a mocap pose's measurement time; the gateway's snapshot time for an estimate
    received: float
    p: Vec3
    q: Quat | None
    v: Vec3 | None  # None when the source gives no valid velocity
    valid: bool
    problem: str = ""  # why not valid, in words

    @property
    def yaw(self) -> float | None:
        """Heading [rad] from the attitude (None without one)."""
        if self.q is None:
            return None
        return quat_yaw(self.q)


def _vec(fields: Mapping[str, Any], *names: str, scale: float = 1.0) -> Vec3:
    return (
        float(fields.get(names[0], math.nan)) * scale,
        float(fields.get(names[1], math.nan)) * scale,
        float(fields.get(names[2], math.nan)) * scale,
    )


@dataclass(frozen=True, slots=True)
class Imu(_Timed):
    """An IMU reading in the body FRD frame, from HIGHRES_IMU (or SCALED_IMU, converted)."""

    t: int
    received: float
    accel: Vec3  # m/s²
    gyro: Vec3  # rad/s
    mag: Vec3  # gauss
    temperature: float  # °C (NaN when unknown)
    source: str  # the MAVLink message

    @classmethod
    def from_telemetry(cls, tm: wire.Telemetry, received: float) -> Imu:
        f = tm.f
        if tm.msg == "HIGHRES_IMU":
            return cls(
                tm.t,
                received,
                _vec(f, "xacc", "yacc", "zacc"),
                _vec(f, "xgyro", "ygyro", "zgyro"),
                _vec(f, "xmag", "ymag", "zmag"),
                float(f.get("temperature", math.nan)),
                tm.msg,
            )
        # SCALED_IMU*: mG, mrad/s, mgauss, cdegC
        temp = f.get("temperature")
        return cls(
            tm.t,
            received,
            _vec(f, "xacc", "yacc", "zacc", scale=G / 1000.0),
            _vec(f, "xgyro", "ygyro", "zgyro", scale=1e-3),
            _vec(f, "xmag", "ymag", "zmag", scale=1e-3),
            float(temp) / 100.0 if temp else math.nan,
            tm.msg,
        )


_CHARGE_STATES = ("undefined", "ok", "low", "critical", "emergency", "failed", "unhealthy", "charging")


@dataclass(frozen=True, slots=True)
class Battery(_Timed):
    """A battery reading (BATTERY_STATUS; the vehicle state's figures until one arrives)."""

    t: int
    received: float
    remaining: float | None  # 0–1
    voltage: float | None  # V, whole pack
    current: float | None  # A
    temperature: float | None  # °C
    charge_state: str  # ok, low, critical, emergency, failed… ("undefined" when not reported)

    @classmethod
    def from_telemetry(cls, tm: wire.Telemetry, received: float) -> Battery:
        f = tm.f
        cells = [c for c in f.get("voltages", ()) if isinstance(c, int) and c not in (0xFFFF, 0)]
        ext = [c for c in f.get("voltages_ext", ()) if isinstance(c, int) and c not in (0, 0xFFFF)]
        volt = sum(cells + ext) / 1000.0 if cells else None
        rem = f.get("battery_remaining", -1)
        cur = f.get("current_battery", -1)
        temp = f.get("temperature", 0x7FFF)
        cs = int(f.get("charge_state", 0))
        return cls(
            tm.t,
            received,
            rem / 100.0 if isinstance(rem, int) and 0 <= rem <= 100 else None,
            volt,
            cur / 100.0 if isinstance(cur, int) and cur >= 0 else None,
            temp / 100.0 if isinstance(temp, int) and temp != 0x7FFF else None,
            _CHARGE_STATES[cs] if 0 <= cs < len(_CHARGE_STATES) else "undefined",
        )

    @classmethod
    def from_status(cls, s: Status) -> Battery:
        return cls(s.t, s.received, s.battery, s.voltage, None, None, "undefined")


_EST_REQUIRED = (
    (px4.ESTIMATOR_ATTITUDE, "attitude"),
    (px4.ESTIMATOR_VELOCITY_HORIZ, "horizontal velocity"),
    (px4.ESTIMATOR_POS_HORIZ_REL, "horizontal position"),
)


@dataclass(frozen=True, slots=True)
class EstimatorStatus(_Timed):
    """The autopilot's estimator health (ESTIMATOR_STATUS): what it says it can estimate."""

    t: int
    received: float
    flags: int
    attitude: bool
    velocity_horiz: bool
    velocity_vert: bool
    pos_horiz_rel: bool
    pos_vert: bool
    const_pos_mode: bool
    test_ratios: Mapping[str, float] = field(default_factory=dict)

    @property
    def problem(self) -> str:
        """Why the local position estimate is not usable ('' when it is)."""
        missing = [name for bit, name in _EST_REQUIRED if not self.flags & bit]
        if not self.pos_vert:
            missing.append("vertical position")
        return "estimator: no " + ", ".join(missing) if missing else ""

    @property
    def position_ok(self) -> bool:
        """The autopilot marks its local position estimate valid."""
        return not self.problem

    @classmethod
    def from_telemetry(cls, tm: wire.Telemetry, received: float) -> EstimatorStatus:
        f = tm.f
        flags = int(f.get("flags", 0))
        ratios = {k: float(v) for k, v in f.items() if k.endswith("_ratio") and isinstance(v, (int, float))}
        return cls(
            tm.t,
            received,
            flags,
            bool(flags & px4.ESTIMATOR_ATTITUDE),
            bool(flags & px4.ESTIMATOR_VELOCITY_HORIZ),
            bool(flags & px4.ESTIMATOR_VELOCITY_VERT),
            bool(flags & px4.ESTIMATOR_POS_HORIZ_REL),
            bool(flags & (px4.ESTIMATOR_POS_VERT_ABS | px4.ESTIMATOR_POS_VERT_AGL)),
            bool(flags & px4.ESTIMATOR_CONST_POS_MODE),
            ratios,
        )
