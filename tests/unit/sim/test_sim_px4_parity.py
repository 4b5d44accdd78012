"""The simulated autopilot does what PX4 v1.16 SITL was measured doing (docs/px4.md, one test per row).

Vision frames and heading alignment, STATUSTEXT only to a ground station, reboot-required parameters,
data-link loss, PX4's answers to mode changes and odd commands, DO_REPOSITION / DO_CHANGE_SPEED,
body-frame and global setpoints, the mission protocol. The vehicle runs at ``SPEED`` times real time and
the test plays the gateway with :class:`tests.unit.sim.test_sim_autopilot.Gcs`; assertions are on order, counts
and the vehicle's own clock, never on the test's timing.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from arena_common.mavlink import px4
from arena_common.sim import params as sim_params
from arena_common.sim.autopilot import SimAutopilot, SimAutopilotError
from arena_common.sim.base import MapProjection
from arena_common.sim.estimator import PX4_SIH_ESTIMATE_LAG_S
from arena_common.sim.telemetry import CAPABILITIES, FLIGHT_SW_VERSION
from tests.unit.sim.test_sim_autopilot import (
    ARENA,
    DISARM_AFTER_TOUCHDOWN_S,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    ORIGIN,
    SYSID,
    Gcs,
    Made,
    free_port,
    start_vehicle,
)

Maker = Callable[..., tuple[SimAutopilot, Gcs]]


@pytest.fixture
def vehicle() -> Iterator[Maker]:
    made: Made = []
    yield functools.partial(start_vehicle, made)
    for ap, gcs, loop in made:
        loop.stop()
        ap.close()
        gcs.close()
        assert not ap.input_errors and not ap.output_errors and not ap.internal_errors


def take_off(gcs: Gcs, height: float = 1.5) -> None:
    """Origin, vision, NAV_TAKEOFF and arm: hovering in Hold at ``height``."""
    gcs.mocap = True
    gcs.set_origin()
    gcs.wait_for(lambda: bool(gcs.ap and gcs.ap.global_position_valid), 2.0, "global position")
    assert gcs.command(px4.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, height) == 0
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    # As PX4 v1.16 SITL: ~4 s on the ground, Hold 0.8 m short, then a slow approach (docs/px4.md).
    gcs.wait_for(lambda: gcs.mode == "AUTO.LOITER" and gcs.height > height - 0.1, 20.0, "takeoff, then hold")


# --- vision frames ----------------------------------------------------------------------------------


def test_local_ned_vision_aligns_heading_and_gives_a_global_position(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)  # EKF2_MAG_TYPE 5 from boot: the heading can only come from vision
    gcs.keep |= {"GLOBAL_POSITION_INT", "HOME_POSITION"}
    gcs.mocap = True
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
    assert ap.sim.estimator.north_aligned
    gcs.run_for(1.0)
    assert "GLOBAL_POSITION_INT" not in gcs.messages  # no EKF origin yet: no global position (PX4 too)
    gcs.set_origin()
    gcs.wait_for(lambda: bool(gcs.messages.get("GLOBAL_POSITION_INT")), 1.0, "GLOBAL_POSITION_INT")
    gcs.wait_for(lambda: bool(gcs.messages.get("HOME_POSITION")), 3.0, "HOME_POSITION")
    gp, home = gcs.messages["GLOBAL_POSITION_INT"][-1], gcs.messages["HOME_POSITION"][-1]
    assert gp.lat * 1e-7 == pytest.approx(ORIGIN[0], abs=1e-6) and gp.lon * 1e-7 == pytest.approx(
        ORIGIN[1], abs=1e-6
    )
    assert home.latitude * 1e-7 == pytest.approx(ORIGIN[0], abs=1e-6)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    assert gcs.texts_with("Armed by external command")


def test_local_frd_vision_is_fused_but_never_aligns_and_arming_is_refused(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)
    gcs.keep.add("GLOBAL_POSITION_INT")
    gcs.mocap_frame = px4.MAV_FRAME_LOCAL_FRD
    gcs.mocap = True
    gcs.set_origin()
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
    gcs.run_for(2.0)
    assert ap.sim.estimator.xy_valid and ap.sim.estimator.yaw_aligned and not ap.sim.estimator.north_aligned
    assert "GLOBAL_POSITION_INT" not in gcs.messages and not ap.global_position_valid
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    # PX4's own words, in two chunks of one STATUSTEXT id, after the reason.
    assert gcs.texts_with("Arming denied: Resolve system health failures first")
    assert gcs.texts_with("heading not aligned")
    # The same vehicle with LOCAL_NED aligns at once and arms.
    gcs.mocap_frame = px4.MAV_FRAME_LOCAL_NED
    gcs.wait_for(lambda: ap.global_position_valid, 1.0, "global position")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED


def test_mocap_messages_are_not_fused(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)
    for i in range(40):
        gcs.conn.mav.att_pos_mocap_send(i * 25_000, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)
        gcs.run_for(0.025)
    gcs.run_for(0.2)
    assert ap.ignored_mocap == 40 and not ap.sim.estimator.vision_fusing


# --- STATUSTEXT -------------------------------------------------------------------------------------


def test_statustext_only_on_a_link_with_a_ground_station(vehicle: Maker) -> None:
    ap, gcs = vehicle(hb_type=MAV_TYPE_ONBOARD_CONTROLLER, params=ARENA)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.run_for(1.0)
    assert gcs.statustexts == [] and len(ap.statustexts) >= 3  # said, but not to an onboard controller
    gcs.hb_type = MAV_TYPE_GCS  # a ground station appears: the texts of the last 5 s follow
    gcs.wait_for(lambda: gcs.texts_with("Resolve system health") != [], 2.0, "queued texts")
    gcs.wait_for(lambda: any(seq == 1 for _, seq in gcs.text_ids), 2.0, "the long text's second chunk")
    assert gcs.statustexts[0] == "Preflight Fail: No valid position estimate"
    ids = [i for i, seq in gcs.text_ids if seq == 0]
    assert ids == list(range(ids[0], ids[0] + len(ids)))  # one id per text, counting up
    assert [seq for i, seq in gcs.text_ids if i == ids[-1]] == [0, 1]  # 51 characters and a tab: 2 chunks
    # Gone again for longer than 2.5 s: texts wait, and those older than 5 s are never sent.
    gcs.hb_type = None
    gcs.run_for(3.0)
    n = len(gcs.statustexts)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.run_for(6.0)
    assert len(gcs.statustexts) == n
    gcs.hb_type = MAV_TYPE_GCS
    assert gcs.command(px4.MAV_CMD_NAV_LAND) == px4.MAV_RESULT_ACCEPTED  # a fresh text
    gcs.wait_for(lambda: gcs.texts_with("Landing at current position") != [], 2.0, "a fresh text")
    assert len(gcs.statustexts) == n + 1  # the stale refusal was dropped


# --- parameters that need a reboot ------------------------------------------------------------------


def test_reboot_required_parameters_come_from_px4_metadata(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    names, source = sim_params.reboot_required_names()
    assert {"EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_MAG_TYPE", "MAV_SYS_ID"} <= names
    assert "EKF2_EV_CTRL" not in names and "EKF2_NOAID_TOUT" not in names
    data = sim_params.load_reboot_required(sim_params.DATA_FILE)
    build = sim_params.px4_sitl_dir() / "parameters.json"
    if build.is_file():
        assert source == str(build) and data == names  # the committed copy is the build's list
    # Without a build: the committed copy, computed the same way.
    monkeypatch.setenv("PX4_SITL_DIR", str(tmp_path))
    assert sim_params.reboot_required_names() == (data, str(sim_params.DATA_FILE))
    # The copy is regenerated from a parameters.json, keeping only names and flags.
    src = tmp_path / "parameters.json"
    src.write_text(json.dumps({"version": 1, "parameters": [
        {"name": "A_REBOOT", "rebootRequired": True, "default": 1, "type": "Int32"},
        {"name": "B_LIVE", "default": 2.0, "type": "Float"},
    ]}))  # fmt: skip
    dest = tmp_path / "copy.json"
    assert sim_params.write_reboot_data(src, dest) == 1
    assert sim_params.load_reboot_required(dest) == frozenset({"A_REBOOT"})
    assert json.loads(dest.read_text())["parameters"] == [{"name": "A_REBOOT", "rebootRequired": True}]


def test_reboot_required_parameters_take_effect_after_a_reboot(vehicle: Maker) -> None:
    ap, gcs = vehicle()
    gcs.set_params({"EKF2_EV_DELAY": 50.0, "EKF2_MAG_TYPE": 5, "EKF2_NOAID_TOUT": 2_000_000})
    assert px4.param_float_to_int(gcs.read_param("EKF2_MAG_TYPE").param_value) == 5  # stored, reported
    assert ap.param_in_effect("EKF2_EV_DELAY") == 0.0 and ap.sim.estimator.ev_delay_s == 0.0
    assert ap.sim.estimator.mag_enabled
    assert ap.sim.estimator.noaid_timeout_s == pytest.approx(2.0)  # not reboot-required: at once
    assert ap.params.pending_reboot() == ["EKF2_EV_DELAY", "EKF2_MAG_TYPE"]
    boots = ap.boots
    assert gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: ap.boots == boots + 1, 3.0, "reboot")
    gcs.wait_for(
        lambda: gcs.local_position is not None and gcs.local_position.time_boot_ms < 800, 2.0, "boot clock"
    )
    assert ap.sim.estimator.ev_delay_s == pytest.approx(0.05) and not ap.sim.estimator.mag_enabled
    assert ap.params.pending_reboot() == []


def test_reboot_command_answers(vehicle: Maker) -> None:
    ap, gcs = vehicle()
    boots = ap.boots
    assert gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0) == px4.MAV_RESULT_ACCEPTED  # nothing to do
    for param1 in (2.0, 3.0, math.nan, math.inf):  # shutdown and the rest: refused (SITL's 2 exits)
        assert gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, param1) == px4.MAV_RESULT_DENIED
    gcs.run_for(1.5)
    assert ap.boots == boots


# --- data link loss ---------------------------------------------------------------------------------


def test_datalink_loss_holds_then_lands_and_refuses_arming_without_gcs(vehicle: Maker) -> None:
    params = {**ARENA, "NAV_DLL_ACT": 3, "COM_DL_LOSS_T": 5, "COM_FAIL_ACT_T": 2.0}
    ap, gcs = vehicle(hb_type=MAV_TYPE_ONBOARD_CONTROLLER, params=params)
    gcs.mocap = True
    gcs.set_origin()
    gcs.wait_for(lambda: ap.global_position_valid, 2.0, "global position")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    assert any("No connection to the ground control station" in t for _, t in ap.statustexts)
    gcs.hb_type = MAV_TYPE_GCS
    gcs.wait_for(ap.gcs_connected, 2.0, "a ground station heard")
    take_off(gcs)
    gcs.hb_type = None  # the ground station goes quiet
    gcs.wait_for(lambda: gcs.mode == "AUTO.LAND", 15.0, "data link loss: Land")
    failsafe = ap.failsafe
    assert failsafe is not None and failsafe[:2] == ("land", "datalink")
    texts = [t for _, t in ap.statustexts]
    assert "Failsafe activated" in texts and any("no ground station, landing in 2 s" in t for t in texts)
    assert ap._gcs_lost  # what PX4 calls gcs_connection_lost
    gcs.hb_type = MAV_TYPE_GCS
    gcs.wait_for(lambda: gcs.texts_with("GCS connection regained") != [], 3.0, "regained")


def test_datalink_loss_hold_phase_ends_when_the_gcs_returns(vehicle: Maker) -> None:
    ap, gcs = vehicle(params={**ARENA, "NAV_DLL_ACT": 3, "COM_DL_LOSS_T": 5, "COM_FAIL_ACT_T": 20.0})
    gcs.wait_for(ap.gcs_connected, 2.0, "a ground station heard")
    take_off(gcs)
    gcs.hb_type = None
    gcs.wait_for(lambda: ap.failsafe is not None, 10.0, "data link loss")
    assert gcs.mode == "AUTO.LOITER" or ap.mode_name == "AUTO.LOITER"
    gcs.hb_type = MAV_TYPE_GCS
    gcs.wait_for(lambda: ap.failsafe is None, 3.0, "failsafe cleared")
    assert ap.mode_name == "AUTO.LOITER" and ap.armed


# --- position loss and offboard loss ------------------------------------------------------------


def test_position_loss_with_px4_default_no_aid_timeout(
    vehicle: Maker,
) -> None:
    """EKF2_NOAID_TOUT 5 s (PX4's default): 4.6 s of dead reckoning, ESTIMATOR_STATUS says so, then the
    offboard-loss action without a position (COM_OBL_RC_ACT 0, COM_POSCTL_NAVL 0: Altitude mode)."""
    ap, gcs = vehicle(
        params={**ARENA, "EKF2_NOAID_TOUT": 5_000_000, "COM_OBL_RC_ACT": 0, "COM_POSCTL_NAVL": 0}
    )
    gcs.set_origin()
    gcs.fly_offboard_to(1.0)
    gcs.set_params(
        {"EKF2_NOAID_TOUT": 5_000_000, "COM_OBL_RC_ACT": 0, "COM_POSCTL_NAVL": 0}
    )  # not the arena's
    gcs.keep.add("ESTIMATOR_STATUS")
    gcs.wait_for(lambda: any(m.flags == 383 for m in gcs.messages.get("ESTIMATOR_STATUS", [])), 2.0, "383")
    gcs.mocap = False
    gcs.wait_for(lambda: gcs.texts_with("no position estimate") != [], 6.0, "position-loss failsafe")
    assert ap.failsafe is not None and ap.failsafe[:2] == ("altctl_descend", "position")
    since_vision = ap.failsafe[2] - ap.sim.estimator.ev_hpos_fused_at
    assert (
        4.6 <= since_vision <= 4.6 + ap.CONTROL_PERIOD + ap.sim.dt + ap.skipped_time_s + 1e-6
    )  # NOAID − 0.4 s
    gcs.wait_for(lambda: gcs.mode == "ALTCTL", 1.5, "Altitude mode")
    gcs.wait_for(lambda: gcs.messages["ESTIMATOR_STATUS"][-1].flags == 101, 1.5, "ESTIMATOR_STATUS 101")
    flags = [m.flags for m in gcs.messages["ESTIMATOR_STATUS"]]
    seen = [f for i, f in enumerate(flags) if i == 0 or flags[i - 1] != f]
    assert seen[:3] == [383, 127, 101]  # fused, dead reckoning, position lost (as PX4 v1.16 SITL)
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 4.0, "descend to the floor")
    gcs.wait_for(lambda: not gcs.armed, DISARM_AFTER_TOUCHDOWN_S, "disarmed")  # 3.7-3.8 s here


@pytest.mark.parametrize("action", [px4.OBL_LAND, px4.OBL_HOLD])
def test_offboard_signal_back_returns_to_offboard(vehicle: Maker, action: int) -> None:
    _ap, gcs = vehicle()
    gcs.set_origin()  # Hold needs a global position
    gcs.fly_offboard_to(1.0)
    gcs.set_params({"COM_OBL_RC_ACT": action})
    sp = gcs.setpoint
    gcs.setpoint = None
    want = "AUTO.LAND" if action == px4.OBL_LAND else "AUTO.LOITER"
    gcs.wait_for(lambda: gcs.mode == want, 3.0, want)
    gcs.setpoint = sp  # the stream is back: PX4 returns to offboard
    gcs.wait_for(lambda: gcs.mode == "OFFBOARD", 2.0, "offboard regained")
    assert gcs.armed


# --- modes and odd commands as PX4 answers them -----------------------------------------------------


def test_mode_changes_are_acknowledged_as_px4_does(vehicle: Maker) -> None:
    _ap, gcs = vehicle(params=ARENA)
    # Disarmed: every PX4 mode is taken (PX4 v1.16 SITL did), arming then says what is missing.
    for main, sub, name in (
        (px4.MAIN_POSCTL, 0, "POSCTL"),
        (px4.MAIN_MANUAL, 0, "MANUAL"),
        (px4.MAIN_AUTO, px4.AUTO_MISSION, "AUTO.MISSION"),
        (px4.MAIN_AUTO, px4.AUTO_RTL, "AUTO.RTL"),
        (px4.MAIN_OFFBOARD, 0, "OFFBOARD"),
        (px4.MAIN_AUTO, px4.AUTO_LOITER, "AUTO.LOITER"),
    ):
        assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, main, sub) == px4.MAV_RESULT_ACCEPTED
        gcs.wait_for(lambda n=name: gcs.mode == n, 1.2, name)  # type: ignore[misc]
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, 42) == px4.MAV_RESULT_DENIED  # not a PX4 mode
    # Armed: a mode that cannot run is acknowledged but not entered.
    take_off(gcs)
    for main, sub in ((px4.MAIN_OFFBOARD, 0), (px4.MAIN_POSCTL, 0), (px4.MAIN_AUTO, px4.AUTO_MISSION)):
        assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, main, sub) == px4.MAV_RESULT_ACCEPTED
        gcs.run_for(1.1)
        assert gcs.mode == "AUTO.LOITER"
    assert gcs.texts_with("Switching to Offboard is currently not available")
    assert gcs.command(300, 0, 0) == px4.MAV_RESULT_DENIED  # MISSION_START without a mission
    assert gcs.texts_with("Mission start denied! No valid mission")


def test_odd_arm_disarm_and_request_commands(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, math.nan) == px4.MAV_RESULT_ACCEPTED  # read as 0
    n = len(gcs.acks)
    gcs.conn.mav.command_long_send(SYSID, 1, px4.MAV_CMD_COMPONENT_ARM_DISARM, 0, 2, 0, 0, 0, 0, 0, 0)
    gcs.wait_for(lambda: gcs.texts_with("Unsupported ARM_DISARM param: 2.000") != [], 1.0, "the refusal")
    gcs.run_for(0.5)
    assert len(gcs.acks) == n  # and no acknowledgement, as PX4
    assert gcs.command(px4.MAV_CMD_REQUEST_MESSAGE, 9999) == px4.MAV_RESULT_DENIED
    assert gcs.command(px4.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100_000) == px4.MAV_RESULT_FAILED
    assert gcs.command(px4.MAV_CMD_SET_MESSAGE_INTERVAL, math.nan, 100_000) == px4.MAV_RESULT_ACCEPTED
    assert gcs.command(px4.MAV_CMD_DO_FLIGHTTERMINATION, 0) == px4.MAV_RESULT_DENIED
    assert gcs.command(31000) == px4.MAV_RESULT_UNSUPPORTED
    gcs.keep.add("AUTOPILOT_VERSION")
    assert gcs.command(px4.MAV_CMD_REQUEST_MESSAGE, 148) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: bool(gcs.messages.get("AUTOPILOT_VERSION")), 1.0, "AUTOPILOT_VERSION")
    version = gcs.messages["AUTOPILOT_VERSION"][-1]
    assert version.capabilities == CAPABILITIES and version.flight_sw_version == FLIGHT_SW_VERSION
    assert not version.capabilities & 1 and version.capabilities & 64  # no MISSION_FLOAT; SET_ATTITUDE_TARGET
    # MAVSDK's arm: param2 NaN is not "force" and arms normally.
    gcs.mocap = True
    gcs.set_origin()
    gcs.wait_for(lambda: ap.global_position_valid, 2.0, "global position")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1, math.nan) == px4.MAV_RESULT_ACCEPTED


# --- auto moves, setpoints in other frames, missions -----------------------------------------------


def test_reposition_and_change_speed(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)
    take_off(gcs)
    assert gcs.command(178, 1, 1.0, -1) == px4.MAV_RESULT_ACCEPTED  # DO_CHANGE_SPEED 1 m/s
    lat, lon = MapProjection(*ORIGIN).reproject(1.0, 0.5)
    n = len(gcs.acks)
    gcs.conn.mav.command_int_send(
        SYSID, 1, 6, 192, 0, 0, -1, 1, 0, math.nan, round(lat * 1e7), round(lon * 1e7), 1.5
    )  # DO_REPOSITION, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 1.5 m above home
    gcs.wait_for(lambda: any(a.command == 192 for a in gcs.acks[n:]), 1.0, "ack")
    assert next(a for a in gcs.acks[n:] if a.command == 192).result == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: math.dist(ap.true_pose().position, (1.0, 0.5, -1.5)) < 0.1, 8.0, "reposition")
    assert gcs.mode == "AUTO.LOITER"


def test_body_frame_velocity_and_global_setpoints(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA, yaw=math.pi / 2, ideal=True)  # facing east; the frames, not the wander
    gcs.set_origin()
    gcs.mocap = True
    gcs.setpoint = {"z": -1.0, "yaw": math.pi / 2}
    gcs.run_for(0.5)
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: abs(gcs.height - 1.0) < 0.05, 8.0, "1 m")
    # Forward in BODY_NED is east for a vehicle facing east.
    gcs.setpoint = {"frame": px4.MAV_FRAME_BODY_NED, "type_mask": px4.TYPEMASK_VEL_YAWRATE, "vx": 0.5}
    gcs.wait_for(lambda: ap.true_pose().position[1] > 0.5, 4.0, "east")
    assert abs(ap.true_pose().position[0]) < 0.15
    # SET_POSITION_TARGET_GLOBAL_INT, relative altitude.
    gcs.setpoint = None
    lat, lon = MapProjection(*ORIGIN).reproject(-0.5, 0.0)
    for _ in range(int(6.0 * gcs.sp_rate)):
        gcs.conn.mav.set_position_target_global_int_send(
            0, SYSID, 1, 6, px4.TYPEMASK_POS_YAW, round(lat * 1e7), round(lon * 1e7), 1.2, 0, 0, 0, 0, 0, 0,
            math.pi / 2, 0,
        )  # fmt: skip
        gcs.run_for(1.0 / gcs.sp_rate)
        if math.dist(ap.true_pose().position, (-0.5, 0.0, -1.2)) < 0.1:
            break
    assert math.dist(ap.true_pose().position, (-0.5, 0.0, -1.2)) < 0.1
    assert gcs.mode == "OFFBOARD"


def upload_mission(gcs: Gcs, items: list[tuple[int, int, float, float, float, tuple[float, ...]]]) -> Any:
    """The mission upload protocol from the ground station side; returns the MISSION_ACK."""
    gcs.keep |= {"MISSION_REQUEST_INT", "MISSION_ACK"}
    gcs.messages["MISSION_REQUEST_INT"] = []
    gcs.messages["MISSION_ACK"] = []
    gcs.conn.mav.mission_count_send(SYSID, 1, len(items), 0)
    sent = 0
    while True:
        gcs.wait_for(
            lambda n=sent: len(gcs.messages["MISSION_REQUEST_INT"]) > n or bool(gcs.messages["MISSION_ACK"]),  # type: ignore[misc]
            2.0,
            "request",
        )
        if gcs.messages["MISSION_ACK"]:
            return gcs.messages["MISSION_ACK"][-1]
        seq = gcs.messages["MISSION_REQUEST_INT"][sent].seq
        frame, command, lat, lon, alt, params = items[seq]
        p = [*params, 0.0, 0.0, 0.0, 0.0][:4]
        gcs.conn.mav.mission_item_int_send(
            SYSID, 1, seq, frame, command, 0, 1, *p, round(lat * 1e7), round(lon * 1e7), alt, 0
        )
        sent += 1


def test_mission_upload_download_fly_and_clear(vehicle: Maker) -> None:
    ap, gcs = vehicle(params=ARENA)
    proj = MapProjection(*ORIGIN)
    wp1, wp2 = proj.reproject(1.0, 0.0), proj.reproject(1.0, 1.0)
    items = [
        (6, 16, *wp1, 1.5, (0.0, 0.2)),  # NAV_WAYPOINT, 0.2 m acceptance
        (2, 178, 0.0, 0.0, 0.0, (1.0, 2.0, -1.0)),  # DO_CHANGE_SPEED 2 m/s
        (6, 16, *wp2, 1.5, (0.0, 0.2)),
    ]
    assert upload_mission(gcs, items).type == 0  # MAV_MISSION_ACCEPTED
    # Download gives the same items back.
    gcs.keep |= {"MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM_REACHED", "MISSION_CURRENT"}
    gcs.conn.mav.mission_request_list_send(SYSID, 1, 0)
    gcs.wait_for(lambda: bool(gcs.messages.get("MISSION_COUNT")), 1.0, "MISSION_COUNT")
    assert gcs.messages["MISSION_COUNT"][-1].count == 3
    for seq in range(3):
        gcs.conn.mav.mission_request_int_send(SYSID, 1, seq, 0)
    gcs.wait_for(lambda: len(gcs.messages.get("MISSION_ITEM_INT", [])) == 3, 1.0, "items")
    got = [(m.frame, m.command, m.x, m.y) for m in gcs.messages["MISSION_ITEM_INT"]]
    assert got == [(f, c, round(la * 1e7), round(lo * 1e7)) for f, c, la, lo, _, _ in items]
    take_off(gcs)
    assert gcs.command(300, 0, 0) == px4.MAV_RESULT_ACCEPTED  # MISSION_START
    gcs.wait_for(lambda: gcs.mode == "AUTO.MISSION", 1.2, "AUTO.MISSION")
    gcs.wait_for(lambda: len(gcs.messages.get("MISSION_ITEM_REACHED", [])) == 2, 15.0, "both waypoints")
    assert [m.seq for m in gcs.messages["MISSION_ITEM_REACHED"]] == [0, 2]
    gcs.wait_for(lambda: gcs.messages["MISSION_CURRENT"][-1].mission_state == 5, 2.0, "COMPLETE")
    assert math.dist(ap.true_pose().position, (1.0, 1.0, -1.5)) < 0.4  # give or take PX4's wander
    assert ap._cruise_speed == 2.0  # the DO_CHANGE_SPEED item
    gcs.messages["MISSION_ACK"] = []
    gcs.conn.mav.mission_clear_all_send(SYSID, 1, 0)
    gcs.wait_for(lambda: bool(gcs.messages["MISSION_ACK"]), 1.0, "clear ack")
    assert ap._mission == []


def test_estimate_lag_option() -> None:
    port = free_port()
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", 1, estimate_lag=0.2)
    assert ap.sim.estimator.output_lag_s == 0.2
    ap.close()
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", 1)  # PX4's, measured on SIH
    assert ap.sim.estimator.output_lag_s == PX4_SIH_ESTIMATE_LAG_S > 0 and ap.sim.estimator.wander is not None
    ap.close()
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", 1, ideal=True)
    assert ap.sim.estimator.output_lag_s == 0.0 and ap.sim.estimator.wander is None
    ap.close()
    with pytest.raises(SimAutopilotError, match="estimate lag"):
        SimAutopilot(f"udpout:127.0.0.1:{port}", 1, estimate_lag=-1.0)


# --- takeoff timing and leaving offboard as PX4 does --------------------------------------------------


def test_takeoff_takes_as_long_as_px4s(vehicle: Maker) -> None:
    """PX4 v1.16 SITL, takeoff to 1 m (ULog, docs/px4.md): spool-up 1 s and thrust ramp 3 s on the ground,
    Hold reported NAV_MC_ALT_RAD (0.8 m) short of the height, within 10 cm of it after ~9.5 s."""
    _ap, gcs = vehicle(params=ARENA)
    gcs.mocap = True
    gcs.set_origin()
    gcs.wait_for(lambda: bool(gcs.ap and gcs.ap.global_position_valid), 2.0, "global position")
    assert gcs.command(px4.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0) == 0
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    on_ground = gcs.wait_for(lambda: gcs.height > 0.05, 20.0, "lift-off")
    hold = gcs.wait_for(lambda: gcs.mode == "AUTO.LOITER", 20.0, "Hold")
    height_at_hold = gcs.height
    within = gcs.wait_for(lambda: abs(gcs.height - 1.0) < 0.1, 20.0, "within 10 cm of 1 m")
    print(f"lift-off {on_ground:.1f} s, Hold at {height_at_hold:.2f} m, within 10 cm after {within:.1f} s")
    assert 3.5 <= on_ground <= 5.5  # PX4: 4.0-4.5 s
    assert on_ground + hold <= 7.0 and height_at_hold < 0.6  # PX4: Hold at 4.8 s, 0.2-0.33 m
    assert 7.0 <= on_ground + hold + within <= 13.0  # PX4: 9.4-10.8 s


def hover_spread(
    ap: SimAutopilot, gcs: Gcs, windows: int = 3, seconds: float = 10.0
) -> list[tuple[float, ...]]:
    """Per window of hover: the truth's distance from its median p50 and max, its north and east std (m)."""
    out = []
    for _ in range(windows):
        samples = []
        end = gcs.clock.now() + seconds
        while gcs.clock.now() < end:
            gcs.pump()
            samples.append(ap.true_pose().position)
        arr = np.array(samples)
        dist = np.linalg.norm(arr - np.median(arr, axis=0), axis=1)
        out.append((float(np.percentile(dist, 50)), float(dist.max()), *map(float, arr[:, :2].std(axis=0))))
    return out


def test_hover_wanders_as_px4s_and_ideal_holds_still(vehicle: Maker) -> None:
    """PX4 v1.16 SITL (SIH) set up by `arena px4 setup` and fed the arena's vision wandered 8-11 cm (p50) and
    17-24 cm (max) around its hover point in 10 s windows, along its roll axis (east, heading north) far
    more than north (true std 9-13 against 3 cm), its estimate 2-3 cm rms off the truth (docs/px4.md).  The
    simulation by default reproduces that size; ``ideal`` holds still.  Bounds: the spread of the
    simulation over six seeds and windows (p50 6-16 cm, max 10-58 cm), judged on the median window."""
    ap, gcs = vehicle(params=ARENA)
    gcs.fly_offboard_to(1.0)
    gcs.setpoint = {"z": -1.0}
    gcs.run_for(3.0)
    spread = hover_spread(ap, gcs)
    p50, top, north, east = np.median(np.array(spread), axis=0)
    print(
        f"hover windows (p50, max, north std, east std; cm): {np.round(np.array(spread) * 100, 1).tolist()}"
    )
    assert 0.03 <= p50 <= 0.30 and top <= 0.70, spread
    assert east > 1.5 * north, spread

    ap, gcs = vehicle(params=ARENA, ideal=True)
    gcs.fly_offboard_to(1.0)
    gcs.setpoint = {"z": -1.0}
    gcs.run_for(3.0)
    (p50, top, _, _), *_ = hover_spread(ap, gcs, windows=1, seconds=5.0)
    assert p50 < 0.01 and top < 0.02, (p50, top)


def test_hold_from_a_velocity_stops_at_px4s_braking_point(vehicle: Maker) -> None:
    """Leaving an offboard velocity of 0.45 m/s (0.34 m/s reached against SIH's drag) for Hold: PX4 v1.16
    SITL stops on a jerk-limited path (the parity tier: 14–21 cm from 0.35–0.38 m/s, the switching delay
    included) and stays: no flying back to where Hold was commanded."""
    ap, gcs = vehicle(params=ARENA)
    gcs.fly_offboard_to(1.0)
    gcs.set_origin()  # Hold needs a global position, as on PX4
    gcs.wait_for(lambda: bool(gcs.ap and gcs.ap.global_position_valid), 2.0, "global position")
    gcs.setpoint = {"vx": 0.45, "z": -1.0, "type_mask": px4.TYPEMASK_VEL_YAWRATE}
    gcs.run_for(3.0)
    speed = ap.true_pose().velocity[0]
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_AUTO, px4.AUTO_LOITER) == px4.MAV_RESULT_ACCEPTED
    start = ap._nav["brake"][1]  # where Hold began (the estimate)
    gcs.setpoint = None
    gcs.run_for(2.0)
    mid = ap.true_pose().position
    gcs.run_for(4.0)
    end = ap.true_pose().position
    coast = end[0] - start[0]
    print(f"coasted {coast * 100:.1f} cm from {speed:.2f} m/s; mid {mid[0]:.3f}, end {end[0]:.3f}")
    assert 0.08 <= coast <= 0.30, coast  # the sim: 15.5 cm
    # It stays, give or take its wander and the braking overshoot (before: it flew back 24 cm to where Hold
    # was commanded, which the coast above rules out too).
    assert end[0] >= mid[0] - 0.15
