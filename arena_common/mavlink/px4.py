"""PX4 (v1.14–v1.16) and MAVLink facts shared by the gateway and the simulated vehicle: the one home of the
MAVLink numbers the arena writes down (elsewhere pymavlink's own names; ``python -m tools.mavlint``).

Pure data and arithmetic, no I/O and no pymavlink import: flight-mode encoding in ``custom_mode``,
PX4's bytewise parameter encoding, the default and arena-required parameter values, setpoint and
ODOMETRY constants, and a helper building ODOMETRY arguments from an arena pose.

PX4 packs its flight mode in HEARTBEAT.custom_mode as ``reserved:u16 | main_mode:u8 | sub_mode:u8``
(little-endian), so ``main = (cm >> 16) & 0xFF`` and ``sub = (cm >> 24) & 0xFF``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any, Final

from arena_common.geometry.quat import FrameError, quat_normalize, quat_rotate_inverse

__all__ = [
    "ARENA_REQUIRED_PARAMS",
    "PX4_DEFAULTS",
    "Px4Error",
    "base_mode_flags",
    "decode_custom_mode",
    "decode_param_value",
    "encode_custom_mode",
    "encode_param_value",
    "int_to_param_float",
    "mode_from_name",
    "mode_name",
    "odometry_args",
    "param_float_to_int",
    "result_name",
]


class Px4Error(ValueError):
    """Bad input to a PX4/MAVLink helper (unknown mode name, out-of-range value, unknown type)."""


# --- PX4 main modes (px4_custom_mode.h) -------------------------------------------------------------
MAIN_MANUAL: Final = 1
MAIN_ALTCTL: Final = 2
MAIN_POSCTL: Final = 3
MAIN_AUTO: Final = 4
MAIN_ACRO: Final = 5
MAIN_OFFBOARD: Final = 6
MAIN_STABILIZED: Final = 7
MAIN_RATTITUDE_LEGACY: Final = 8
MAIN_SIMPLE: Final = 9
MAIN_TERMINATION: Final = 10

# --- PX4 AUTO sub modes -----------------------------------------------------------------------------
AUTO_READY: Final = 1
AUTO_TAKEOFF: Final = 2
AUTO_LOITER: Final = 3
AUTO_MISSION: Final = 4
AUTO_RTL: Final = 5
AUTO_LAND: Final = 6
AUTO_RTGS: Final = 7
AUTO_FOLLOW_TARGET: Final = 8
AUTO_PRECLAND: Final = 9
AUTO_VTOL_TAKEOFF: Final = 10

# --- PX4 POSCTL sub modes ---------------------------------------------------------------------------
POSCTL_POSCTL: Final = 0
POSCTL_ORBIT: Final = 1
POSCTL_SLOW: Final = 2

_MAIN_NAMES: Final[dict[int, str]] = {
    MAIN_MANUAL: "MANUAL",
    MAIN_ALTCTL: "ALTCTL",
    MAIN_POSCTL: "POSCTL",
    MAIN_AUTO: "AUTO",
    MAIN_ACRO: "ACRO",
    MAIN_OFFBOARD: "OFFBOARD",
    MAIN_STABILIZED: "STABILIZED",
    MAIN_RATTITUDE_LEGACY: "RATTITUDE",
    MAIN_SIMPLE: "SIMPLE",
    MAIN_TERMINATION: "TERMINATION",
}
_AUTO_NAMES: Final[dict[int, str]] = {
    AUTO_READY: "AUTO.READY",
    AUTO_TAKEOFF: "AUTO.TAKEOFF",
    AUTO_LOITER: "AUTO.LOITER",
    AUTO_MISSION: "AUTO.MISSION",
    AUTO_RTL: "AUTO.RTL",
    AUTO_LAND: "AUTO.LAND",
    AUTO_RTGS: "AUTO.RTGS",
    AUTO_FOLLOW_TARGET: "AUTO.FOLLOW_TARGET",
    AUTO_PRECLAND: "AUTO.PRECLAND",
    AUTO_VTOL_TAKEOFF: "AUTO.VTOL_TAKEOFF",
}
_POSCTL_NAMES: Final[dict[int, str]] = {POSCTL_ORBIT: "POSCTL.ORBIT", POSCTL_SLOW: "POSCTL.SLOW"}

_NAME_TO_MODE: Final[dict[str, tuple[int, int]]] = {
    **{name: (main, 0) for main, name in _MAIN_NAMES.items() if main != MAIN_AUTO},
    **{name: (MAIN_AUTO, sub) for sub, name in _AUTO_NAMES.items()},
    **{name: (MAIN_POSCTL, sub) for sub, name in _POSCTL_NAMES.items()},
}


def encode_custom_mode(main: int, sub: int = 0) -> int:
    """Return HEARTBEAT.custom_mode for a PX4 ``main``/``sub`` mode pair."""
    if not (0 <= main <= 0xFF and 0 <= sub <= 0xFF):
        raise Px4Error(f"PX4 mode out of range: main={main} sub={sub} (each must be 0..255)")
    return (main << 16) | (sub << 24)


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """Return ``(main, sub)`` from HEARTBEAT.custom_mode."""
    if not 0 <= custom_mode <= 0xFFFFFFFF:
        raise Px4Error(f"custom_mode out of uint32 range: {custom_mode}")
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(main: int, sub: int = 0) -> str:
    """Return PX4's (and mavros') name of a mode, e.g. ``"OFFBOARD"`` or ``"AUTO.LAND"``.

    A pair this module does not know (a newer PX4) yields ``"CUSTOM(main=M,sub=S)"`` rather than an
    error, so a gateway keeps working when a vehicle reports a mode added after this table.
    """
    if main == MAIN_AUTO:
        name = _AUTO_NAMES.get(sub)
    elif main == MAIN_POSCTL and sub in _POSCTL_NAMES:
        name = _POSCTL_NAMES[sub]
    else:
        name = _MAIN_NAMES.get(main)
    return name if name is not None else f"CUSTOM(main={main},sub={sub})"


def mode_from_name(name: str) -> tuple[int, int]:
    """Return ``(main, sub)`` for a PX4 mode name (case-insensitive), e.g. ``"AUTO.LOITER"`` → (4, 3)."""
    key = name.strip().upper()
    try:
        return _NAME_TO_MODE[key]
    except KeyError:
        raise Px4Error(f"unknown PX4 mode name {name!r}; known: {', '.join(sorted(_NAME_TO_MODE))}") from None


# --- HEARTBEAT base_mode / system_status ------------------------------------------------------------
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED: Final = 1
MAV_MODE_FLAG_TEST_ENABLED: Final = 2
MAV_MODE_FLAG_AUTO_ENABLED: Final = 4
MAV_MODE_FLAG_GUIDED_ENABLED: Final = 8
MAV_MODE_FLAG_STABILIZE_ENABLED: Final = 16
MAV_MODE_FLAG_HIL_ENABLED: Final = 32
MAV_MODE_FLAG_MANUAL_INPUT_ENABLED: Final = 64
MAV_MODE_FLAG_SAFETY_ARMED: Final = 128

MAV_STATE_UNINIT: Final = 0
MAV_STATE_BOOT: Final = 1
MAV_STATE_CALIBRATING: Final = 2
MAV_STATE_STANDBY: Final = 3
MAV_STATE_ACTIVE: Final = 4
MAV_STATE_CRITICAL: Final = 5
MAV_STATE_EMERGENCY: Final = 6
MAV_STATE_POWEROFF: Final = 7
MAV_STATE_FLIGHT_TERMINATION: Final = 8

MAV_TYPE_QUADROTOR: Final = 2
MAV_TYPE_GCS: Final = 6  # the gateway's HEARTBEAT: PX4 sends STATUSTEXT only where it hears a ground station
MAV_AUTOPILOT_PX4: Final = 12
MAV_AUTOPILOT_INVALID: Final = 8  # a HEARTBEAT of no autopilot (a ground station, a companion)
MAV_COMP_ID_AUTOPILOT1: Final = 1
MAV_COMP_ID_ONBOARD_COMPUTER: Final = 191

MAV_LANDED_STATE_UNDEFINED: Final = 0
MAV_LANDED_STATE_ON_GROUND: Final = 1
MAV_LANDED_STATE_IN_AIR: Final = 2
MAV_LANDED_STATE_TAKEOFF: Final = 3
MAV_LANDED_STATE_LANDING: Final = 4

MAV_BATTERY_CHARGE_STATE_UNDEFINED: Final = 0
MAV_BATTERY_CHARGE_STATE_OK: Final = 1
MAV_BATTERY_CHARGE_STATE_LOW: Final = 2
MAV_BATTERY_CHARGE_STATE_CRITICAL: Final = 3
MAV_BATTERY_CHARGE_STATE_EMERGENCY: Final = 4
MAV_BATTERY_CHARGE_STATE_FAILED: Final = 5

# Message ids read where pymavlink is not loaded (the signing rules, the benchmarks' frame parsing);
# elsewhere pymavlink's own ``MAVLINK_MSG_ID_…`` (``arena_common.mavlink.link.MSG``, ``mavlink2``) name them.
MAVLINK_MSG_ID_ODOMETRY: Final = 331
MAVLINK_MSG_ID_RADIO_STATUS: Final = 109
MAVLINK_MSG_ID_ADSB_VEHICLE: Final = 246
MAVLINK_MSG_ID_COLLISION: Final = 247


def base_mode_flags(main: int, sub: int, armed: bool) -> int:
    """HEARTBEAT.base_mode as PX4 fills it for a mode: custom mode enabled, armed flag, mode-class flags."""
    flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        flags |= MAV_MODE_FLAG_SAFETY_ARMED
    if main in (MAIN_AUTO, MAIN_OFFBOARD):
        flags |= MAV_MODE_FLAG_AUTO_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
    elif main == MAIN_POSCTL:
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
        flags |= MAV_MODE_FLAG_GUIDED_ENABLED
    elif main in (MAIN_ALTCTL, MAIN_STABILIZED, MAIN_RATTITUDE_LEGACY):
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
    elif main in (MAIN_MANUAL, MAIN_ACRO):
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    return flags


# --- Parameters -------------------------------------------------------------------------------------
MAV_PARAM_TYPE_UINT8: Final = 1
MAV_PARAM_TYPE_INT8: Final = 2
MAV_PARAM_TYPE_UINT16: Final = 3
MAV_PARAM_TYPE_INT16: Final = 4
MAV_PARAM_TYPE_UINT32: Final = 5
MAV_PARAM_TYPE_INT32: Final = 6
MAV_PARAM_TYPE_UINT64: Final = 7
MAV_PARAM_TYPE_INT64: Final = 8
MAV_PARAM_TYPE_REAL32: Final = 9
MAV_PARAM_TYPE_REAL64: Final = 10

_INT_FORMATS: Final[dict[int, tuple[str, int, int]]] = {
    MAV_PARAM_TYPE_UINT8: ("<B", 0, 0xFF),
    MAV_PARAM_TYPE_INT8: ("<b", -0x80, 0x7F),
    MAV_PARAM_TYPE_UINT16: ("<H", 0, 0xFFFF),
    MAV_PARAM_TYPE_INT16: ("<h", -0x8000, 0x7FFF),
    MAV_PARAM_TYPE_UINT32: ("<I", 0, 0xFFFFFFFF),
    MAV_PARAM_TYPE_INT32: ("<i", -0x80000000, 0x7FFFFFFF),
}

ParamValue = int | float


def int_to_param_float(value: int) -> float:
    """Put an INT32 parameter's four bytes into the float PARAM_SET/PARAM_VALUE carry (PX4's encoding).

    Note: the few values whose bytes form a *signalling* NaN (0x7F800001–0x7FBFFFFF and their negative
    twins) cannot survive a float64 round trip in CPython; no PX4 parameter uses them.
    """
    if not -0x80000000 <= value <= 0x7FFFFFFF:
        raise Px4Error(f"INT32 parameter value out of range: {value}")
    return float(struct.unpack("<f", struct.pack("<i", value))[0])


def param_float_to_int(value: float) -> int:
    """Recover an INT32 parameter from the float of a PARAM_VALUE (bytewise, as PX4 sends it)."""
    return int(struct.unpack("<i", struct.pack("<f", value))[0])


def encode_param_value(value: ParamValue, mav_param_type: int) -> float:
    """Return the float to put in PARAM_SET.param_value for ``value`` of ``mav_param_type``.

    Integer types are encoded bytewise (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE, what PX4 uses):
    the integer's little-endian bytes occupy the float's low bytes. REAL32 is sent as is.
    """
    if mav_param_type == MAV_PARAM_TYPE_REAL32:
        if isinstance(value, bool):
            raise Px4Error(f"REAL32 parameter value must be a number, not {value!r}")
        return float(value)
    fmt = _INT_FORMATS.get(mav_param_type)
    if fmt is None:
        raise Px4Error(f"MAV_PARAM_TYPE {mav_param_type} cannot travel in a float parameter")
    code, lo, hi = fmt
    if isinstance(value, float):
        if not value.is_integer():
            raise Px4Error(f"integer parameter (MAV_PARAM_TYPE {mav_param_type}) given non-integer {value!r}")
        value = int(value)
    if not lo <= int(value) <= hi:
        raise Px4Error(f"value {value} out of range {lo}..{hi} for MAV_PARAM_TYPE {mav_param_type}")
    raw = struct.pack(code, int(value)).ljust(4, b"\0")
    return float(struct.unpack("<f", raw)[0])


def decode_param_value(value: float, mav_param_type: int) -> ParamValue:
    """Inverse of :func:`encode_param_value`: the parameter's value from PARAM_VALUE.param_value."""
    if mav_param_type == MAV_PARAM_TYPE_REAL32:
        return float(value)
    fmt = _INT_FORMATS.get(mav_param_type)
    if fmt is None:
        raise Px4Error(f"MAV_PARAM_TYPE {mav_param_type} cannot travel in a float parameter")
    code = fmt[0]
    raw = struct.pack("<f", value)
    return int(struct.unpack(code, raw[: struct.calcsize(code)])[0])


def param_name_bytes(name: str) -> bytes:
    """A parameter name as MAVLink's 16-byte param_id field wants it (ASCII, at most 16 characters)."""
    try:
        raw = name.encode("ascii")
    except UnicodeEncodeError:
        raise Px4Error(f"parameter name must be ASCII: {name!r}") from None
    if not 0 < len(raw) <= 16:
        raise Px4Error(f"parameter name must have 1..16 characters: {name!r}")
    return raw


def param_name_from_field(field: str | bytes) -> str:
    """Decode a received param_id field (NUL-padded when shorter than 16 characters)."""
    if isinstance(field, bytes):
        field = field.decode("ascii", errors="replace")
    return field.split("\0", 1)[0]


_I: Final = MAV_PARAM_TYPE_INT32
_F: Final = MAV_PARAM_TYPE_REAL32

#: PX4 v1.16 defaults (name → (value, MAV_PARAM_TYPE)) of the parameters the arena reads or sets, as the
#: build's own metadata (parameters.json) gives them (checked by the tests when a build is at hand);
#: SYS_AUTOSTART is the airframe's, not the metadata's 0.
PX4_DEFAULTS: Final[Mapping[str, tuple[ParamValue, int]]] = {
    "EKF2_EV_CTRL": (0, _I),  # bitmask: 0 hor. pos, 1 vert. pos, 2 vel, 3 yaw
    "EKF2_HGT_REF": (1, _I),  # 0 baro, 1 GNSS, 2 range, 3 vision
    "EKF2_EV_DELAY": (0.0, _F),  # ms
    "EKF2_EV_QMIN": (0, _I),
    "EKF2_GPS_CTRL": (7, _I),
    "EKF2_MAG_TYPE": (0, _I),  # 0 automatic, 1 heading, 5 none, 6 init
    "EKF2_BARO_CTRL": (1, _I),
    "COM_OBL_RC_ACT": (
        0,
        _I,
    ),  # 0 Position, 1 Altitude, 2 Stabilized, 3 Return, 4 Land, 5 Hold, 6 Term., 7 Disarm
    "COM_OF_LOSS_T": (1.0, _F),  # s
    "COM_RC_IN_MODE": (3, _I),  # 0 RC only, 1 joystick only, 2 fallback, 3 keep first, 4 stick input disabled
    "COM_POSCTL_NAVL": (0, _I),  # 0 Altitude, 1 Land (descend)
    "EKF2_NOAID_TOUT": (5_000_000, _I),  # µs of inertial dead reckoning before position is invalid
    "EKF2_EVP_NOISE": (0.1, _F),  # m
    "EKF2_EVA_NOISE": (0.1, _F),  # rad
    "EKF2_DELAY_MAX": (200.0, _F),  # ms: how far behind now the EKF fuses (its horizon)
    "EKF2_TAU_POS": (0.25, _F),  # s: how tightly the output predictor follows the EKF's position
    "EKF2_TAU_VEL": (0.25, _F),  # s: ... and its velocity
    "COM_DISARM_LAND": (2.0, _F),  # s
    "COM_DISARM_PRFLT": (10.0, _F),  # s
    "COM_LOW_BAT_ACT": (0, _I),  # 0 warning, 2 land, 3 return at critical / land at emergency
    "NAV_RCL_ACT": (2, _I),  # 0 disabled, 1 hold, 2 return, 3 land, 5 terminate, 6 disarm
    "MPC_LAND_SPEED": (0.7, _F),
    "MPC_XY_VEL_MAX": (12.0, _F),
    "MPC_Z_VEL_MAX_UP": (3.0, _F),
    "MPC_Z_VEL_MAX_DN": (1.5, _F),
    "MPC_XY_P": (0.95, _F),
    "MPC_Z_P": (1.0, _F),
    "MPC_THR_HOVER": (0.5, _F),
    "MPC_TILTMAX_AIR": (45.0, _F),  # deg
    "MPC_YAWRAUTO_MAX": (45.0, _F),  # deg/s
    "MPC_XY_CRUISE": (5.0, _F),
    "MPC_ACC_HOR": (3.0, _F),  # m/s², with MPC_JERK_AUTO: where Hold brakes to (navigator's braking stop)
    "MPC_JERK_AUTO": (4.0, _F),  # m/s³
    "MPC_TKO_RAMP_T": (3.0, _F),  # s of takeoff thrust ramp
    "COM_SPOOLUP_TIME": (1.0, _F),  # s from arming before the controllers may lift off
    "NAV_MC_ALT_RAD": (0.8, _F),  # m: a takeoff is complete (→ Hold) this close to its altitude
    "BAT_LOW_THR": (0.15, _F),
    "BAT_CRIT_THR": (0.07, _F),
    "BAT_EMERGEN_THR": (0.05, _F),
    "MAV_SYS_ID": (1, _I),
    "MIS_TAKEOFF_ALT": (2.5, _F),
    "RTL_RETURN_ALT": (60.0, _F),
    "RTL_MIN_DIST": (10.0, _F),
    "SYS_AUTOSTART": (4001, _I),
}

#: What the arena sets on every vehicle (name → (value, MAV_PARAM_TYPE)).
#:
#: EKF2_EV_CTRL 15 fuses vision horizontal and vertical position, velocity (used only when the sender
#: fills it) and yaw; 11 (no velocity) would also do. COM_LOW_BAT_ACT 2 and NAV_RCL_ACT 3 implement the
#: arena's safety set-up (land at critical battery, land on RC loss).  EKF2_NOAID_TOUT 1 s: when mocap
#: stops, PX4 dead-reckons for this long before it declares its position invalid and fails safe (5 s by
#: default: in a 7 × 4 m room the vehicle left it in 4 of 6 tries; with 1 s it moved 0.24–0.54 m);
#: COM_POSCTL_NAVL 1 lands (descends) on position loss in Position mode too.  EKF2_EV_DELAY 0 ms and
#: EKF2_EVP_NOISE 0.02 m were chosen by measurement against PX4 SITL (docs/px4.md, tests/px4/tune_vision.py):
#: the arena stamps the camera's mid-exposure time, which PX4 maps with TIMESYNC, so EKF2_EV_DELAY holds only
#: what the stamps miss (the original arena's 20 ms, measured with arrival stamps, would count the delay
#: twice); PX4's default 0.1 m noise let its estimate trail the truth by 260–440 ms and the vehicle wander
#: 33–36 cm around a held point, 0.02 m: 160–170 ms and 5–13 cm; 0.01 m jittered more (14–20 cm).
#: EKF2_DELAY_MAX 100 ms and EKF2_TAU_POS / EKF2_TAU_VEL 0.1 s, measured from PX4's ULog (docs/px4.md,
#: "Issue 25: the arena's EKF2 horizon and output predictor"): the arena's vision reaches PX4 a few ms
#: late (mocap stamps mapped by TIMESYNC; no GNSS, whose 110 ms delay sets the default 200 ms horizon), so
#: the EKF may fuse nearer now, and the output predictor may follow it tightly; PX4's estimate then trails
#: the truth by 70–85 ms instead of 190–195, 3 cm rms off it instead of 7, and the vehicle wanders 17–24 cm
#: (max) around a held point instead of 36–40.  PX4 v1.16 raises a smaller EKF2_DELAY_MAX to its largest
#: sensor delay, EKF2_ASP_DELAY's 100 ms (asked for 20, 30 or 50 ms, it stored 100).
ARENA_REQUIRED_PARAMS: Final[Mapping[str, tuple[ParamValue, int]]] = {
    "EKF2_EV_CTRL": (15, _I),
    "EKF2_HGT_REF": (3, _I),
    "EKF2_GPS_CTRL": (0, _I),
    "EKF2_MAG_TYPE": (5, _I),
    "EKF2_BARO_CTRL": (1, _I),
    "EKF2_EV_DELAY": (0.0, _F),
    "EKF2_EVP_NOISE": (0.02, _F),
    "EKF2_EVA_NOISE": (0.05, _F),
    "EKF2_NOAID_TOUT": (1_000_000, _I),
    "EKF2_DELAY_MAX": (100.0, _F),
    "EKF2_TAU_POS": (0.1, _F),
    "EKF2_TAU_VEL": (0.1, _F),
    "COM_POSCTL_NAVL": (1, _I),
    "COM_OBL_RC_ACT": (4, _I),
    "COM_OF_LOSS_T": (1.0, _F),
    "COM_RC_IN_MODE": (4, _I),
    "COM_LOW_BAT_ACT": (2, _I),
    "NAV_RCL_ACT": (3, _I),
    "BAT_LOW_THR": (0.15, _F),
    "BAT_CRIT_THR": (0.07, _F),
    "MPC_LAND_SPEED": (0.7, _F),
}

#: COM_OBL_RC_ACT values (offboard loss action, PX4 v1.14+).
OBL_POSITION: Final = 0
OBL_ALTITUDE: Final = 1
OBL_STABILIZED: Final = 2
OBL_RETURN: Final = 3
OBL_LAND: Final = 4
OBL_HOLD: Final = 5
OBL_TERMINATE: Final = 6
OBL_DISARM: Final = 7

#: EKF2_EV_CTRL bits.
EV_CTRL_HPOS: Final = 1
EV_CTRL_VPOS: Final = 2
EV_CTRL_VEL: Final = 4
EV_CTRL_YAW: Final = 8

EKF2_MAG_TYPE_NONE: Final = 5
EKF2_HGT_REF_VISION: Final = 3
COM_RC_IN_MODE_DISABLED: Final = 4

# --- Commands and results ---------------------------------------------------------------------------
# The one home of the MAVLink numbers the arena uses (pymavlink's common dialect has them all: a test
# checks every MAV_* name here against it; the dialect itself is not imported by the user's API).
MAV_CMD_NAV_RETURN_TO_LAUNCH: Final = 20
MAV_CMD_NAV_LAND: Final = 21
MAV_CMD_NAV_TAKEOFF: Final = 22
MAV_CMD_DO_SET_MODE: Final = 176
MAV_CMD_DO_CHANGE_SPEED: Final = 178
MAV_CMD_DO_SET_HOME: Final = 179
MAV_CMD_DO_FLIGHTTERMINATION: Final = 185
MAV_CMD_DO_REPOSITION: Final = 192
MAV_CMD_DO_SET_MISSION_CURRENT: Final = 224
MAV_CMD_PREFLIGHT_STORAGE: Final = 245  # param1 0: read, 1: write the parameters to permanent storage
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: Final = 246
MAV_CMD_MISSION_START: Final = 300
MAV_CMD_COMPONENT_ARM_DISARM: Final = 400
MAV_CMD_SET_MESSAGE_INTERVAL: Final = 511
MAV_CMD_REQUEST_MESSAGE: Final = 512
MAV_CMD_REQUEST_PROTOCOL_VERSION: Final = 519
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: Final = 520

#: param2 of MAV_CMD_COMPONENT_ARM_DISARM that forces arming/disarming (a forced disarm in the air kills
#: the motors).
ARM_DISARM_FORCE_MAGIC: Final = 21196

MAV_RESULT_ACCEPTED: Final = 0
MAV_RESULT_TEMPORARILY_REJECTED: Final = 1
MAV_RESULT_DENIED: Final = 2
MAV_RESULT_UNSUPPORTED: Final = 3
MAV_RESULT_FAILED: Final = 4
MAV_RESULT_IN_PROGRESS: Final = 5
MAV_RESULT_CANCELLED: Final = 6

_RESULT_NAMES: Final[dict[int, str]] = {
    MAV_RESULT_ACCEPTED: "ACCEPTED",
    MAV_RESULT_TEMPORARILY_REJECTED: "TEMPORARILY_REJECTED",
    MAV_RESULT_DENIED: "DENIED",
    MAV_RESULT_UNSUPPORTED: "UNSUPPORTED",
    MAV_RESULT_FAILED: "FAILED",
    MAV_RESULT_IN_PROGRESS: "IN_PROGRESS",
    MAV_RESULT_CANCELLED: "CANCELLED",
}


def result_name(result: int) -> str:
    """Name of a MAV_RESULT value (``"ACCEPTED"``, ``"TEMPORARILY_REJECTED"``, …)."""
    return _RESULT_NAMES.get(result, f"MAV_RESULT({result})")


MAV_SEVERITY_EMERGENCY: Final = 0
MAV_SEVERITY_ALERT: Final = 1
MAV_SEVERITY_CRITICAL: Final = 2
MAV_SEVERITY_ERROR: Final = 3
MAV_SEVERITY_WARNING: Final = 4
MAV_SEVERITY_NOTICE: Final = 5
MAV_SEVERITY_INFO: Final = 6

# --- Frames, estimator types ------------------------------------------------------------------------
MAV_FRAME_LOCAL_NED: Final = 1
MAV_FRAME_LOCAL_ENU: Final = 4
MAV_FRAME_LOCAL_OFFSET_NED: Final = 7
MAV_FRAME_BODY_NED: Final = 8
MAV_FRAME_BODY_OFFSET_NED: Final = 9
MAV_FRAME_BODY_FRD: Final = 12
MAV_FRAME_LOCAL_FRD: Final = 20
MAV_FRAME_LOCAL_FLU: Final = 21

MAV_ESTIMATOR_TYPE_UNKNOWN: Final = 0
MAV_ESTIMATOR_TYPE_NAIVE: Final = 1
MAV_ESTIMATOR_TYPE_VISION: Final = 2
MAV_ESTIMATOR_TYPE_VIO: Final = 3
MAV_ESTIMATOR_TYPE_GPS: Final = 4
MAV_ESTIMATOR_TYPE_GPS_INS: Final = 5
MAV_ESTIMATOR_TYPE_MOCAP: Final = 6
MAV_ESTIMATOR_TYPE_LIDAR: Final = 7
MAV_ESTIMATOR_TYPE_AUTOPILOT: Final = 8

#: Estimator types PX4's MAVLink receiver forwards to EKF2 as external vision (MOCAP is not fused).
EV_FUSED_ESTIMATOR_TYPES: Final = frozenset(
    {MAV_ESTIMATOR_TYPE_UNKNOWN, MAV_ESTIMATOR_TYPE_NAIVE, MAV_ESTIMATOR_TYPE_VISION, MAV_ESTIMATOR_TYPE_VIO}
)

# --- ESTIMATOR_STATUS flags (MAVLink ESTIMATOR_STATUS_FLAGS) ---------------------------------------
ESTIMATOR_ATTITUDE: Final = 1
ESTIMATOR_VELOCITY_HORIZ: Final = 2
ESTIMATOR_VELOCITY_VERT: Final = 4
ESTIMATOR_POS_HORIZ_REL: Final = 8
ESTIMATOR_POS_HORIZ_ABS: Final = 16
ESTIMATOR_POS_VERT_ABS: Final = 32
ESTIMATOR_POS_VERT_AGL: Final = 64
ESTIMATOR_CONST_POS_MODE: Final = 128
ESTIMATOR_PRED_POS_HORIZ_REL: Final = 256
ESTIMATOR_GPS_GLITCH: Final = 1024
ESTIMATOR_ACCEL_ERROR: Final = 2048

# --- SET_POSITION_TARGET_LOCAL_NED type_mask --------------------------------------------------------
TYPEMASK_X_IGNORE: Final = 1
TYPEMASK_Y_IGNORE: Final = 2
TYPEMASK_Z_IGNORE: Final = 4
TYPEMASK_VX_IGNORE: Final = 8
TYPEMASK_VY_IGNORE: Final = 16
TYPEMASK_VZ_IGNORE: Final = 32
TYPEMASK_AX_IGNORE: Final = 64
TYPEMASK_AY_IGNORE: Final = 128
TYPEMASK_AZ_IGNORE: Final = 256
TYPEMASK_FORCE_SET: Final = 512
TYPEMASK_YAW_IGNORE: Final = 1024
TYPEMASK_YAW_RATE_IGNORE: Final = 2048

TYPEMASK_POSITION: Final = TYPEMASK_X_IGNORE | TYPEMASK_Y_IGNORE | TYPEMASK_Z_IGNORE
TYPEMASK_VELOCITY: Final = TYPEMASK_VX_IGNORE | TYPEMASK_VY_IGNORE | TYPEMASK_VZ_IGNORE
TYPEMASK_ACCELERATION: Final = TYPEMASK_AX_IGNORE | TYPEMASK_AY_IGNORE | TYPEMASK_AZ_IGNORE

#: SET_ATTITUDE_TARGET type_mask bits (ATTITUDE_TARGET_TYPEMASK).
ATTITUDE_TARGET_BODY_RATES_IGNORE: Final = 1 | 2 | 4  # roll, pitch, yaw rate ignored
ATTITUDE_TARGET_THROTTLE_IGNORE: Final = 64
ATTITUDE_TARGET_ATTITUDE_IGNORE: Final = 128

#: Position + yaw (velocity, acceleration and yaw rate ignored).
TYPEMASK_POS_YAW: Final = TYPEMASK_VELOCITY | TYPEMASK_ACCELERATION | TYPEMASK_YAW_RATE_IGNORE  # 2552
#: Velocity + yaw.
TYPEMASK_VEL_YAW: Final = TYPEMASK_POSITION | TYPEMASK_ACCELERATION | TYPEMASK_YAW_RATE_IGNORE  # 2503
#: Velocity + yaw rate.
TYPEMASK_VEL_YAWRATE: Final = TYPEMASK_POSITION | TYPEMASK_ACCELERATION | TYPEMASK_YAW_IGNORE  # 1479
#: Position + yaw rate.
TYPEMASK_POS_YAWRATE: Final = TYPEMASK_VELOCITY | TYPEMASK_ACCELERATION | TYPEMASK_YAW_IGNORE  # 1528

# --- TIMESYNC (PX4 src/modules/mavlink/mavlink_timesync / lib/timesync) -----------------------------
TIMESYNC_CONVERGENCE_WINDOW: Final = 500
TIMESYNC_MAX_RTT_US: Final = 10_000
TIMESYNC_MAX_DEVIATION_US: Final = 100_000
TIMESYNC_MAX_CONSECUTIVE_HIGH_DEVIATION: Final = 5
TIMESYNC_MAX_CONSECUTIVE_HIGH_RTT: Final = 5

#: EKF2 stops fusing external vision this long after the last sample, and needs samples this close
#: together to (re)start.
EV_TIMEOUT_S: Final = 0.4
EV_START_MAX_INTERVAL_S: Final = 0.2

_NAN21: Final = (math.nan,) * 21


def odometry_args(
    time_usec: int,
    position_ned: Sequence[float],
    q_frd: Sequence[float],
    velocity_ned: Sequence[float] | None = None,
    *,
    reset_counter: int = 0,
    frame_id: int = MAV_FRAME_LOCAL_NED,
    angular_velocity_frd: Sequence[float] | None = None,
    estimator_type: int = MAV_ESTIMATOR_TYPE_VISION,
    quality: int = 0,
) -> dict[str, Any]:
    """Keyword arguments for pymavlink's ``mav.odometry_send``/``odometry_encode`` carrying an arena pose.

    ``position_ned`` (m) and ``q_frd`` (w, x, y, z; body FRD → arena) are in the arena frame, sent with
    ``frame_id`` LOCAL_NED (default: the calibrated arena frame is NED, so PX4 aligns its yaw to it) or
    LOCAL_FRD (PX4 v1.16 then treats the heading as arbitrary: it fuses the pose but never aligns yaw, so
    it publishes no global position and refuses to arm). The child frame is BODY_FRD, so ``velocity_ned``
    (m/s, arena frame) is rotated into the body frame here; ``None`` sends NaN (unknown), as do the
    angular velocity when not given and all covariances. ``reset_counter`` must change whenever the
    pose jumps. ``time_usec`` is the measurement time in the sender's clock (the one it answers
    TIMESYNC with).
    """
    if frame_id not in (MAV_FRAME_LOCAL_FRD, MAV_FRAME_LOCAL_NED):
        raise Px4Error(f"ODOMETRY frame_id must be LOCAL_FRD (20) or LOCAL_NED (1), not {frame_id}")
    if len(position_ned) != 3 or len(q_frd) != 4:
        raise Px4Error("position_ned needs 3 values and q_frd 4 (w, x, y, z)")
    if time_usec < 0:
        raise Px4Error(f"time_usec must be >= 0, got {time_usec}")
    try:
        w, x, y, z = quat_normalize(q_frd)
    except FrameError:
        raise Px4Error(f"q_frd is not a rotation quaternion: {tuple(q_frd)}") from None
    if not all(map(math.isfinite, (w, x, y, z))):
        raise Px4Error(f"q_frd is not a rotation quaternion: {tuple(q_frd)}")
    if velocity_ned is None:
        vx = vy = vz = math.nan
    else:
        if len(velocity_ned) != 3:
            raise Px4Error("velocity_ned needs 3 values")
        vx, vy, vz = quat_rotate_inverse((w, x, y, z), [float(c) for c in velocity_ned])
    if angular_velocity_frd is None:
        rs = ps = ys = math.nan
    else:
        rs, ps, ys = (float(c) for c in angular_velocity_frd)
    return {
        "time_usec": int(time_usec),
        "frame_id": frame_id,
        "child_frame_id": MAV_FRAME_BODY_FRD,
        "x": float(position_ned[0]),
        "y": float(position_ned[1]),
        "z": float(position_ned[2]),
        "q": [w, x, y, z],
        "vx": vx,
        "vy": vy,
        "vz": vz,
        "rollspeed": rs,
        "pitchspeed": ps,
        "yawspeed": ys,
        "pose_covariance": list(_NAN21),
        "velocity_covariance": list(_NAN21),
        "reset_counter": int(reset_counter) & 0xFF,
        "estimator_type": estimator_type,
        "quality": int(quality),
    }
