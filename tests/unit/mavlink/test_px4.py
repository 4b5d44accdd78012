"""PX4/MAVLink facts: mode encoding, bytewise parameters, constants checked against pymavlink."""

from __future__ import annotations

import math
import os
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink

from arena_common.mavlink import px4
from arena_common.mavlink.metadata import load_parameters_json
from arena_common.runtime.px4_sitl import build_missing_reason, find_build


def test_custom_mode_layout_matches_px4() -> None:
    # OFFBOARD is main mode 6 in bits 16..23; AUTO.LAND is main 4, sub 6 in bits 24..31.
    assert px4.encode_custom_mode(px4.MAIN_OFFBOARD) == 6 << 16 == 393216
    assert px4.encode_custom_mode(px4.MAIN_AUTO, px4.AUTO_LAND) == (4 << 16) | (6 << 24) == 100925440
    assert px4.decode_custom_mode(100925440) == (4, 6)
    assert px4.decode_custom_mode(50593792) == (px4.MAIN_AUTO, px4.AUTO_LOITER)


@given(st.integers(0, 255), st.integers(0, 255))
def test_custom_mode_round_trip(main: int, sub: int) -> None:
    assert px4.decode_custom_mode(px4.encode_custom_mode(main, sub)) == (main, sub)


def test_mode_names() -> None:
    assert px4.mode_name(px4.MAIN_OFFBOARD, 0) == "OFFBOARD"
    assert px4.mode_name(4, 2) == "AUTO.TAKEOFF"
    assert px4.mode_name(4, 3) == "AUTO.LOITER"
    assert px4.mode_name(4, 5) == "AUTO.RTL"
    assert px4.mode_name(4, 6) == "AUTO.LAND"
    assert px4.mode_name(2) == "ALTCTL" and px4.mode_name(3) == "POSCTL" and px4.mode_name(1) == "MANUAL"
    assert px4.mode_name(7) == "STABILIZED"
    assert px4.mode_name(42, 1) == "CUSTOM(main=42,sub=1)"
    for name in ("MANUAL", "ALTCTL", "POSCTL", "OFFBOARD", "STABILIZED", "AUTO.TAKEOFF", "AUTO.LOITER",
                 "AUTO.RTL", "AUTO.LAND", "AUTO.MISSION", "POSCTL.ORBIT"):  # fmt: skip
        assert px4.mode_name(*px4.mode_from_name(name)) == name
    assert px4.mode_from_name(" auto.land ") == (4, 6)


def test_bad_mode_input_raises_own_error() -> None:
    with pytest.raises(px4.Px4Error, match="unknown PX4 mode name"):
        px4.mode_from_name("HOVER")
    with pytest.raises(px4.Px4Error, match="out of range"):
        px4.encode_custom_mode(256, 0)
    with pytest.raises(px4.Px4Error, match="uint32"):
        px4.decode_custom_mode(-1)


def test_base_mode_flags() -> None:
    flags = px4.base_mode_flags(px4.MAIN_OFFBOARD, 0, armed=True)
    assert flags & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert flags & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert not px4.base_mode_flags(px4.MAIN_AUTO, 3, armed=False) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED


def test_int32_param_travels_bytewise() -> None:
    # PX4 stores the float 3.0 sent for an INT32 parameter as the integer with the same bytes.
    assert px4.param_float_to_int(3.0) == 1077936128
    assert px4.int_to_param_float(1077936128) == 3.0
    f = px4.int_to_param_float(15)
    assert f != 15.0 and f == struct.unpack("<f", struct.pack("<i", 15))[0]
    assert px4.param_float_to_int(f) == 15
    assert px4.param_float_to_int(px4.int_to_param_float(-1)) == -1


@given(st.integers(-(2**31), 2**31 - 1).filter(lambda i: not (0x7F800001 <= (i & 0x7FFFFFFF) <= 0x7FBFFFFF)))
def test_int32_round_trip(value: int) -> None:
    assert px4.param_float_to_int(px4.int_to_param_float(value)) == value
    wire = px4.encode_param_value(value, px4.MAV_PARAM_TYPE_INT32)
    assert px4.decode_param_value(wire, px4.MAV_PARAM_TYPE_INT32) == value


@pytest.mark.parametrize(
    ("ptype", "value"),
    [
        (px4.MAV_PARAM_TYPE_UINT8, 200),
        (px4.MAV_PARAM_TYPE_INT8, -5),
        (px4.MAV_PARAM_TYPE_UINT16, 60000),
        (px4.MAV_PARAM_TYPE_INT16, -300),
        (px4.MAV_PARAM_TYPE_UINT32, 4000000000),
        (px4.MAV_PARAM_TYPE_INT32, 4001),
    ],
)
def test_small_int_types_round_trip(ptype: int, value: int) -> None:
    assert px4.decode_param_value(px4.encode_param_value(value, ptype), ptype) == value


def test_real32_param_is_plain_float() -> None:
    assert px4.encode_param_value(0.7, px4.MAV_PARAM_TYPE_REAL32) == 0.7
    assert px4.decode_param_value(20.0, px4.MAV_PARAM_TYPE_REAL32) == 20.0


def test_bad_param_input_raises_own_error() -> None:
    with pytest.raises(px4.Px4Error, match="out of range"):
        px4.encode_param_value(300, px4.MAV_PARAM_TYPE_UINT8)
    with pytest.raises(px4.Px4Error, match="non-integer"):
        px4.encode_param_value(1.5, px4.MAV_PARAM_TYPE_INT32)
    with pytest.raises(px4.Px4Error, match="cannot travel"):
        px4.encode_param_value(1, px4.MAV_PARAM_TYPE_INT64)
    with pytest.raises(px4.Px4Error, match="INT32 parameter value out of range"):
        px4.int_to_param_float(2**31)
    with pytest.raises(px4.Px4Error, match=r"1\.\.16"):
        px4.param_name_bytes("A_NAME_LONGER_THAN_16")


def test_defaults_and_arena_values() -> None:
    d = px4.PX4_DEFAULTS
    assert d["EKF2_EV_CTRL"] == (0, px4.MAV_PARAM_TYPE_INT32)
    assert d["EKF2_HGT_REF"] == (1, px4.MAV_PARAM_TYPE_INT32)
    assert d["EKF2_EV_DELAY"] == (0.0, px4.MAV_PARAM_TYPE_REAL32)
    assert d["EKF2_GPS_CTRL"][0] == 7 and d["EKF2_MAG_TYPE"][0] == 0 and d["EKF2_BARO_CTRL"][0] == 1
    assert d["COM_OBL_RC_ACT"][0] == 0 and d["COM_OF_LOSS_T"][0] == 1.0 and d["COM_RC_IN_MODE"][0] == 3
    assert d["NAV_RCL_ACT"][0] == 2 and d["MPC_LAND_SPEED"][0] == 0.7 and d["MIS_TAKEOFF_ALT"][0] == 2.5
    assert (d["BAT_LOW_THR"][0], d["BAT_CRIT_THR"][0], d["BAT_EMERGEN_THR"][0]) == (0.15, 0.07, 0.05)
    for name in ("COM_POSCTL_NAVL", "COM_LOW_BAT_ACT", "MAV_SYS_ID", "MPC_XY_VEL_MAX", "MPC_Z_VEL_MAX_UP"):
        assert name in d
    a = px4.ARENA_REQUIRED_PARAMS
    assert int(a["EKF2_EV_CTRL"][0]) & 0b1011 == 0b1011  # horizontal + vertical position and yaw
    assert a["EKF2_HGT_REF"][0] == 3 and a["EKF2_GPS_CTRL"][0] == 0 and a["EKF2_MAG_TYPE"][0] == 5
    assert a["COM_OBL_RC_ACT"][0] == px4.OBL_LAND and a["COM_RC_IN_MODE"][0] == 4
    assert a["EKF2_NOAID_TOUT"] == (1_000_000, px4.MAV_PARAM_TYPE_INT32)  # 1 s of dead reckoning
    for name, (_, ptype) in a.items():
        assert d[name][1] == ptype, name  # same type as the vehicle's own parameter
    for name in d:
        assert len(px4.param_name_bytes(name)) <= 16


def test_defaults_are_the_real_px4_builds() -> None:
    """PX4_DEFAULTS and the arena's values against the PX4 build's own metadata (parameters.json)."""
    reason = build_missing_reason()
    if reason is not None:
        pytest.skip(reason)
    path = find_build() / "parameters.json"
    meta = load_parameters_json(path)
    types = {"Int32": px4.MAV_PARAM_TYPE_INT32, "Float": px4.MAV_PARAM_TYPE_REAL32}
    for name, (value, ptype) in px4.PX4_DEFAULTS.items():
        assert name in meta, name
        assert types[meta[name]["type"]] == ptype, name
        if name != "SYS_AUTOSTART":  # the airframe's, not the metadata's
            assert meta[name]["default"] == pytest.approx(float(value)), name
    for name in px4.ARENA_REQUIRED_PARAMS:
        assert name in meta, name


def test_type_masks() -> None:
    assert px4.TYPEMASK_POS_YAW == 2552
    assert px4.TYPEMASK_VEL_YAW == 2503
    assert px4.TYPEMASK_VEL_YAWRATE == 1479
    assert px4.TYPEMASK_X_IGNORE == mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    assert px4.TYPEMASK_YAW_RATE_IGNORE == mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
    assert px4.TYPEMASK_FORCE_SET == mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET


def test_constants_match_pymavlink() -> None:
    names = [
        "MAV_FRAME_LOCAL_NED", "MAV_FRAME_LOCAL_FRD", "MAV_FRAME_BODY_FRD", "MAV_FRAME_LOCAL_ENU",
        "MAV_ESTIMATOR_TYPE_VISION", "MAV_ESTIMATOR_TYPE_MOCAP", "MAV_ESTIMATOR_TYPE_AUTOPILOT",
        "MAV_RESULT_ACCEPTED", "MAV_RESULT_TEMPORARILY_REJECTED", "MAV_RESULT_DENIED",
        "MAV_RESULT_UNSUPPORTED", "MAV_RESULT_FAILED", "MAV_RESULT_IN_PROGRESS",
        "MAV_CMD_COMPONENT_ARM_DISARM", "MAV_CMD_DO_SET_MODE", "MAV_CMD_NAV_TAKEOFF", "MAV_CMD_NAV_LAND",
        "MAV_CMD_DO_FLIGHTTERMINATION", "MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN", "MAV_CMD_SET_MESSAGE_INTERVAL",
        "MAV_CMD_REQUEST_MESSAGE", "MAV_PARAM_TYPE_INT32", "MAV_PARAM_TYPE_REAL32", "MAV_TYPE_QUADROTOR",
        "MAV_AUTOPILOT_PX4", "MAV_STATE_STANDBY", "MAV_STATE_ACTIVE", "MAV_LANDED_STATE_ON_GROUND",
        "MAV_LANDED_STATE_IN_AIR", "MAV_SEVERITY_CRITICAL", "MAV_MODE_FLAG_SAFETY_ARMED",
    ]  # fmt: skip
    for name in names:
        assert getattr(px4, name) == getattr(mavlink, name), name
    assert px4.result_name(1) == "TEMPORARILY_REJECTED"
    assert px4.MAV_ESTIMATOR_TYPE_MOCAP not in px4.EV_FUSED_ESTIMATOR_TYPES
    assert px4.MAV_ESTIMATOR_TYPE_VISION in px4.EV_FUSED_ESTIMATOR_TYPES


def _rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> tuple[float, ...]:
    w, x, y, z = q
    m = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return tuple(sum(m[i][j] * v[j] for j in range(3)) for i in range(3))


def test_odometry_args_encode_and_rotate_velocity() -> None:
    yaw = math.radians(90)
    q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    args = px4.odometry_args(123456, (1.0, -2.0, -0.5), q, (1.0, 0.0, 0.0), reset_counter=3)
    assert args["frame_id"] == mavlink.MAV_FRAME_LOCAL_NED  # what PX4 v1.16 aligns its yaw to
    assert args["child_frame_id"] == mavlink.MAV_FRAME_BODY_FRD
    assert args["estimator_type"] == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert (args["x"], args["y"], args["z"]) == (1.0, -2.0, -0.5)
    # Heading east, a velocity toward north is to the vehicle's left (-y in FRD).
    assert args["vx"] == pytest.approx(0.0, abs=1e-12) and args["vy"] == pytest.approx(-1.0)
    back = _rotate(q, (args["vx"], args["vy"], args["vz"]))
    assert back == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    assert all(math.isnan(c) for c in args["pose_covariance"]) and len(args["pose_covariance"]) == 21
    assert math.isnan(args["rollspeed"])
    # The arguments encode into a real MAVLink 2 ODOMETRY and decode back.
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    packed = mav.odometry_encode(**args).pack(mav)
    decoded = mavlink.MAVLink(None).decode(bytearray(packed))
    assert decoded.get_type() == "ODOMETRY" and decoded.reset_counter == 3
    assert decoded.time_usec == 123456 and math.isnan(decoded.vz) is False
    no_vel = px4.odometry_args(1, (0, 0, 0), (1, 0, 0, 0))
    assert math.isnan(no_vel["vx"])


def test_odometry_args_bad_input() -> None:
    with pytest.raises(px4.Px4Error, match="frame_id"):
        px4.odometry_args(0, (0, 0, 0), (1, 0, 0, 0), frame_id=mavlink.MAV_FRAME_BODY_FRD)
    with pytest.raises(px4.Px4Error, match="quaternion"):
        px4.odometry_args(0, (0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(px4.Px4Error, match="3 values"):
        px4.odometry_args(0, (0, 0), (1, 0, 0, 0))
