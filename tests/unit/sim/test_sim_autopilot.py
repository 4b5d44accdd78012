"""The simulated PX4 seen through a plain pymavlink peer on 127.0.0.1, as a gateway would see it.

The vehicle runs in a background loop at ``SPEED`` times real time; the test plays the gateway:
it answers TIMESYNC, feeds ODOMETRY from the vehicle's true pose (as the motion capture would) and
streams offboard setpoints, all at rates measured in simulated time.
"""

from __future__ import annotations

import functools
import math
import os
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from arena_common.mavlink import px4
from arena_common.sim.autopilot import (
    AutopilotLoop,
    SimAutopilot,
    SimAutopilotError,
    SimClock,
    TimesyncFilter,
    run_autopilots,
)
from arena_common.sim.params import SIM_EXTRA_DEFAULTS
from arena_common.sim.physics import BatteryParams

#: From touchdown to disarmed: PX4 SITL 6.6-7.1 s (docs/px4.md); the simulation's land detector goes
#: through PX4's three stages once the thrust has wound down (3-4 s), then COM_DISARM_LAND (2 s).
DISARM_AFTER_TOUCHDOWN_S = 8.0
SPEED = 4.0
#: Real seconds without a read of the vehicle's clock after which the process counts as paused (a busy
#: machine), not simulated: at SPEED, more would be a silence of the ground station its vehicle fails safe
#: on (EKF2_NOAID_TOUT's 0.6 s, COM_OF_LOSS_T's 1 s).  The vehicle's loop reads it at least every 50 ms.
PAUSE_S = 0.08
#: The armed state travels in the 1 Hz HEARTBEAT: a change shows within two of them (one is too tight).
HEARTBEAT_WAIT_S = 2.0
SYSID = 7
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
ORIGIN = (47.397742, 8.545594, 0.0)
ARENA = {name: value for name, (value, _) in px4.ARENA_REQUIRED_PARAMS.items()}


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Gcs:
    """A gateway stand-in: a pymavlink connection plus the periodic traffic a gateway sends."""

    def __init__(self, url: str, clock: SimClock, target: int = SYSID) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=200, source_component=191, dialect="common")
        self.clock = clock
        self.target = target
        self.ap: SimAutopilot | None = None
        self.mocap = False
        self.mocap_rate = 40.0
        self.mocap_type = px4.MAV_ESTIMATOR_TYPE_VISION
        self.mocap_frame = px4.MAV_FRAME_LOCAL_NED
        self.setpoint: dict[str, Any] | None = None
        self.sp_rate = 20.0
        self._next_mocap = 0.0
        self._next_sp = 0.0
        self.heartbeat: Any = None
        self.heartbeats = 0
        self.statustexts: list[str] = []
        self.text_ids: list[tuple[int, int]] = []
        self._text_at: dict[int, int] = {}
        self.acks: list[Any] = []
        self.params: dict[str, Any] = {}
        self.local_position: Any = None
        self.landed_state: int | None = None
        self.counts: dict[str, int] = {}
        self.timesync_requests: list[tuple[int, int, float]] = []
        self.timesync_replies: list[Any] = []
        self.sources: set[int] = set()
        self.hb_type: int | None = MAV_TYPE_GCS  # what the gateway sends; None: no heartbeat
        self._next_hb = 0.0
        self.messages: dict[str, list[Any]] = {}  # every message of the types in ``keep``
        self.keep: set[str] = set()

    def close(self) -> None:
        self.conn.close()

    # --- the vehicle as seen from here
    @property
    def mode(self) -> str:
        assert self.heartbeat is not None
        return px4.mode_name(*px4.decode_custom_mode(self.heartbeat.custom_mode))

    @property
    def armed(self) -> bool:
        return bool(self.heartbeat is not None and self.heartbeat.base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def height(self) -> float:
        return -self.local_position.z if self.local_position is not None else math.nan

    def texts_with(self, word: str) -> list[str]:
        return [t for t in self.statustexts if word.lower() in t.lower()]

    def seen(self) -> str:
        """Where the vehicle is, for a failure's message: its mode and height as heard here, its failsafe
        and the simulated time it skipped (a busy machine), the STATUSTEXTs it sent."""
        mode = self.mode if self.heartbeat is not None else "no heartbeat yet"
        ap = self.ap
        inside = f", failsafe {ap.failsafe}, {ap.skipped_time_s:.2f} s skipped" if ap is not None else ""
        return f"{mode} at {self.height:.2f} m{inside}, texts {self.statustexts}"

    # --- traffic
    def send_mocap(self) -> None:
        assert self.ap is not None
        pose = self.ap.true_pose()
        args = px4.odometry_args(
            time.monotonic_ns() // 1000, pose.position, pose.q, pose.velocity, frame_id=self.mocap_frame
        )
        args["estimator_type"] = self.mocap_type
        self.conn.mav.odometry_send(**args)

    def set_origin(self, origin: tuple[float, float, float] = ORIGIN) -> None:
        """SET_GPS_GLOBAL_ORIGIN, as the gateway gives one to an EKF without GPS; waits for the echo."""
        lat, lon, alt = origin
        self.messages.pop("GPS_GLOBAL_ORIGIN", None)
        self.keep.add("GPS_GLOBAL_ORIGIN")
        self.conn.mav.set_gps_global_origin_send(
            self.target, round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), 0
        )
        self.wait_for(lambda: bool(self.messages.get("GPS_GLOBAL_ORIGIN")), 2.0, "GPS_GLOBAL_ORIGIN")

    def send_setpoint(self) -> None:
        assert self.setpoint is not None
        sp = {"x": 0.0, "y": 0.0, "z": 0.0, "vx": 0.0, "vy": 0.0, "vz": 0.0, "yaw": 0.0, "yaw_rate": 0.0}
        sp.update(self.setpoint)
        frame = sp.get("frame", px4.MAV_FRAME_LOCAL_NED)
        mask = sp.get("type_mask", px4.TYPEMASK_POS_YAW)
        self.conn.mav.set_position_target_local_ned_send(
            0, self.target, 1, frame, mask, sp["x"], sp["y"], sp["z"], sp["vx"], sp["vy"], sp["vz"],
            0.0, 0.0, 0.0, sp["yaw"], sp["yaw_rate"],
        )  # fmt: skip

    def pump(self, wait_real: float = 0.002) -> None:
        now = self.clock.now()
        if self.hb_type is not None and now >= self._next_hb:
            self._next_hb = now + 1.0
            self.conn.mav.heartbeat_send(self.hb_type, 8, 0, 0, 4)  # MAV_AUTOPILOT_INVALID, ACTIVE
        if self.mocap and now >= self._next_mocap:
            self._next_mocap = max(self._next_mocap + 1.0 / self.mocap_rate, now - 0.05)
            self.send_mocap()
        if self.setpoint is not None and now >= self._next_sp:
            self._next_sp = max(self._next_sp + 1.0 / self.sp_rate, now - 0.1)
            self.send_setpoint()
        select.select([self.conn.port], [], [], wait_real)
        for _ in range(2000):
            msg = self.conn.recv_msg()
            if msg is None:
                break
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if kind in self.keep:
            self.messages.setdefault(kind, []).append(msg)
        self.sources.add(msg.get_srcSystem())
        if kind == "HEARTBEAT":
            self.heartbeat = msg
            self.heartbeats += 1
        elif kind == "STATUSTEXT":
            # Long texts come in 50-character chunks sharing an id (chunk_seq 0, 1, …), as from PX4.
            if msg.chunk_seq > 0 and msg.id in self._text_at:
                i = self._text_at[msg.id]
                self.statustexts[i] = (self.statustexts[i] + msg.text).rstrip("\t")
            else:
                self._text_at[msg.id] = len(self.statustexts)
                self.statustexts.append(msg.text.rstrip("\t"))
            self.text_ids.append((msg.id, msg.chunk_seq))
        elif kind == "COMMAND_ACK":
            self.acks.append(msg)
        elif kind == "PARAM_VALUE":
            self.params[msg.param_id] = msg
        elif kind == "LOCAL_POSITION_NED":
            self.local_position = msg
        elif kind == "EXTENDED_SYS_STATE":
            self.landed_state = msg.landed_state
        elif kind == "TIMESYNC":
            if msg.tc1 == 0:
                self.timesync_requests.append((msg.tc1, msg.ts1, self.clock.now()))
                self.conn.mav.timesync_send(time.monotonic_ns(), msg.ts1)
            else:
                self.timesync_replies.append(msg)

    #: A pause of the test's own thread longer than this (simulated seconds; a pump takes a few ms of real
    #: time) is a busy machine's doing: it does not count against a wait's ``timeout``.
    STALL_S = 0.1

    def wait_for(self, predicate: Callable[[], bool], timeout: float, what: str) -> float:
        """Pump until ``predicate()``; returns the simulated seconds it took. ``timeout`` is simulated.

        Simulated time runs on the wall clock: when the machine is busy this thread may not run for a while,
        and that time (each pause over :attr:`STALL_S`) extends the deadline, so the bound judges the
        vehicle, not the scheduler.  The predicate is checked once more after the deadline's last pump.
        """
        start = last = self.clock.now()
        deadline = start + timeout
        while True:
            self.pump()
            now = self.clock.now()
            if now - last > self.STALL_S:
                deadline += now - last
            last = now
            if predicate():
                return self.clock.now() - start
            if now >= deadline:
                raise AssertionError(
                    f"timed out after {timeout} s (simulated) waiting for {what}: {self.seen()}"
                )

    def run_for(self, seconds: float) -> None:
        end = self.clock.now() + seconds
        while self.clock.now() < end:
            self.pump()

    def command(self, command: int, *params: float, confirmation: int = 0, target: int | None = None) -> int:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        n = len(self.acks)
        self.conn.mav.command_long_send(
            self.target if target is None else target, 1, command, confirmation, *p
        )
        self.wait_for(
            lambda: any(a.command == command for a in self.acks[n:]), 2.0, f"ack of command {command}"
        )
        ack = next(a for a in self.acks[n:] if a.command == command)
        assert (ack.target_system, ack.target_component) == (200, 191)
        self.run_for(0.05)  # the STATUSTEXT explaining a refusal leaves the vehicle right after its ack
        return int(ack.result)

    def set_param(self, name: str, value: float, ptype: int | None = None, target: int | None = None) -> None:
        ptype = ptype if ptype is not None else px4.PX4_DEFAULTS[name][1]
        wire = px4.encode_param_value(value, ptype)
        self.params.pop(name, None)
        self.conn.mav.param_set_send(self.target if target is None else target, 1, name.encode(), wire, ptype)

    def read_param(self, name: str) -> Any:
        self.params.pop(name, None)
        self.conn.mav.param_request_read_send(self.target, 1, name.encode(), -1)
        self.wait_for(lambda: name in self.params, 2.0, f"PARAM_VALUE {name}")
        return self.params[name]

    def set_params(self, values: dict[str, float]) -> None:
        for name, value in values.items():
            self.set_param(name, value)
            self.wait_for(lambda n=name: n in self.params, 2.0, f"PARAM_VALUE {name}")  # type: ignore[misc]

    def fly_offboard_to(self, height: float) -> float:
        """Arena params, mocap, setpoint stream, OFFBOARD, arm; returns the climb time to within 5 cm."""
        self.set_params(ARENA)
        self.mocap = True
        self.wait_for(lambda: self.texts_with("vision fusion started") != [], 2.0, "vision fusion")
        self.setpoint = {"z": -height}
        self.run_for(0.5)
        assert self.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
        assert self.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
        return self.wait_for(lambda: abs(self.height - height) < 0.05, 8.0, f"climb to {height} m")


Made = list[tuple[SimAutopilot, Gcs, AutopilotLoop]]


def start_vehicle(
    made: Made, hb_type: int | None = MAV_TYPE_GCS, loop_paces: bool = True, **kwargs: Any
) -> tuple[SimAutopilot, Gcs]:
    """A simulated vehicle on a loop of its own and this thread as its ground station, on one clock both
    pace (``loop_paces=False``: the world goes on while the vehicle's loop is held up); added to ``made``."""
    port = free_port()
    clock = SimClock(speed=kwargs.pop("speed", SPEED), max_gap_s=PAUSE_S)
    clock.paces()  # time waits for the ground station's mocap
    gcs = Gcs(f"udpin:127.0.0.1:{port}", clock)
    gcs.hb_type = hb_type
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", SYSID, clock=clock, **kwargs)
    gcs.ap = ap
    loop = AutopilotLoop([ap]).start()
    if loop_paces:  # a busy machine does not make the vehicle skip time
        clock.paces(loop.thread)
    made.append((ap, gcs, loop))
    gcs.wait_for(lambda: gcs.heartbeat is not None, 2.0, "first heartbeat")
    return ap, gcs


@pytest.fixture
def make_vehicle() -> Iterator[Callable[..., tuple[SimAutopilot, Gcs]]]:
    made: Made = []
    yield functools.partial(start_vehicle, made)
    for ap, gcs, loop in made:
        loop.stop()
        ap.close()
        gcs.close()


def simulated_window(ap: SimAutopilot, gcs: Gcs, seconds: float) -> float:
    """Pump for ``seconds`` of simulated time; the simulated seconds the vehicle really ran meanwhile.

    Simulated time runs on the wall clock: on a busy machine the vehicle may skip time (it sends nothing
    for it: :attr:`~arena_common.sim.autopilot.SimAutopilot.skipped_time_s`) and this thread may overrun
    the window; rates are per second the vehicle simulated.
    """
    skipped, t0 = ap.skipped_time_s, gcs.clock.now()
    gcs.run_for(seconds)
    t1 = gcs.clock.now()
    gcs.pump(0.0)  # what arrived while the last pump's caller was away
    return (t1 - t0) - (ap.skipped_time_s - skipped)


def test_heartbeat_and_telemetry_like_px4(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle()
    hb = gcs.heartbeat
    assert hb.type == px4.MAV_TYPE_QUADROTOR and hb.autopilot == px4.MAV_AUTOPILOT_PX4
    assert hb.base_mode & px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not gcs.armed
    assert gcs.mode == "AUTO.LOITER" and hb.system_status == px4.MAV_STATE_STANDBY
    assert hb.get_srcSystem() == SYSID and hb.get_srcComponent() == 1
    assert gcs.conn.WIRE_PROTOCOL_VERSION == "2.0"
    gcs.counts.clear()
    window = simulated_window(ap, gcs, 4.0)
    rates = {k: v / window for k, v in gcs.counts.items()}
    assert rates["HEARTBEAT"] == pytest.approx(1.0, abs=0.3)
    assert 1.0 <= rates["SYS_STATUS"] <= 2.5
    assert rates["EXTENDED_SYS_STATE"] == pytest.approx(5.0, rel=0.25)
    assert rates["ATTITUDE_QUATERNION"] == pytest.approx(50.0, rel=0.2)
    assert rates["LOCAL_POSITION_NED"] == pytest.approx(30.0, rel=0.2)
    assert rates["ODOMETRY"] == pytest.approx(30.0, rel=0.2)
    assert rates["HIGHRES_IMU"] == pytest.approx(50.0, rel=0.2)
    assert rates["BATTERY_STATUS"] == pytest.approx(1.0, abs=0.3)
    assert rates["TIMESYNC"] == pytest.approx(10.0, rel=0.2)  # PX4 starts timesync itself
    assert gcs.landed_state == px4.MAV_LANDED_STATE_ON_GROUND
    # Message interval: ATTITUDE_QUATERNION down to 10 Hz.
    assert gcs.command(px4.MAV_CMD_SET_MESSAGE_INTERVAL, 31, 100_000) == px4.MAV_RESULT_ACCEPTED
    gcs.counts.clear()
    window = simulated_window(ap, gcs, 2.0)
    assert gcs.counts["ATTITUDE_QUATERNION"] / window == pytest.approx(10.0, rel=0.25)
    n = gcs.counts.get("AUTOPILOT_VERSION", 0)
    assert gcs.command(px4.MAV_CMD_REQUEST_MESSAGE, 148) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.counts.get("AUTOPILOT_VERSION", 0) > n, 1.0, "AUTOPILOT_VERSION")
    assert gcs.command(31000) == px4.MAV_RESULT_UNSUPPORTED


def test_parameters_bytewise(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle()
    pv = gcs.read_param("EKF2_EV_CTRL")
    assert pv.param_type == px4.MAV_PARAM_TYPE_INT32
    assert px4.param_float_to_int(pv.param_value) == 0  # PX4's default: nothing fused
    gcs.set_param("EKF2_EV_CTRL", 15)
    gcs.wait_for(lambda: "EKF2_EV_CTRL" in gcs.params, 2.0, "PARAM_VALUE after PARAM_SET")
    assert px4.decode_param_value(gcs.params["EKF2_EV_CTRL"].param_value, px4.MAV_PARAM_TYPE_INT32) == 15
    assert px4.param_float_to_int(gcs.read_param("EKF2_EV_CTRL").param_value) == 15
    assert ap.param("EKF2_EV_CTRL") == 15
    # A careless gateway sending the float 3.0 for an INT32 gets PX4's bytewise reading of it.
    gcs.conn.mav.param_set_send(SYSID, 1, b"EKF2_HGT_REF", 3.0, px4.MAV_PARAM_TYPE_REAL32)
    gcs.wait_for(lambda: "EKF2_HGT_REF" in gcs.params, 2.0, "PARAM_VALUE")
    assert px4.param_float_to_int(gcs.read_param("EKF2_HGT_REF").param_value) == 1077936128
    # Float parameters travel as floats.
    gcs.set_param("EKF2_EV_DELAY", 20.0)
    assert gcs.read_param("EKF2_EV_DELAY").param_value == pytest.approx(20.0)
    # The full list, with consistent indices and count.
    gcs.params.clear()
    gcs.conn.mav.param_request_list_send(SYSID, 1)
    count = len(px4.PX4_DEFAULTS) + len(SIM_EXTRA_DEFAULTS)
    gcs.wait_for(lambda: len(gcs.params) >= count, 3.0, "all parameters")
    assert {pv.param_count for pv in gcs.params.values()} == {count}
    assert sorted(pv.param_index for pv in gcs.params.values()) == list(range(count))
    assert px4.param_float_to_int(gcs.params["MAV_SYS_ID"].param_value) == SYSID
    # By index, and an unknown name.
    gcs.params.clear()
    gcs.conn.mav.param_request_read_send(SYSID, 1, b"", 0)
    gcs.wait_for(lambda: len(gcs.params) == 1, 2.0, "parameter 0")
    assert next(iter(gcs.params.values())).param_index == 0
    gcs.conn.mav.param_request_read_send(SYSID, 1, b"NO_SUCH_PARAM", -1)
    gcs.wait_for(lambda: gcs.texts_with("unknown param") != [], 2.0, "unknown parameter STATUSTEXT")


def test_arming_refused_without_vision(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    _ap, gcs = make_vehicle()
    gcs.set_params(ARENA)
    result = gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert result == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.wait_for(lambda: gcs.texts_with("Resolve system health") != [], 1.0, "PX4's refusal")
    assert gcs.texts_with("position estimate") and gcs.texts_with("ODOMETRY")  # the reasons, before it
    gcs.run_for(1.0)
    assert not gcs.armed


def test_vision_not_fused_when_ev_ctrl_is_zero_then_fused(
    make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]],
) -> None:
    _ap, gcs = make_vehicle(params={"COM_RC_IN_MODE": 4})
    gcs.mocap = True
    gcs.run_for(1.0)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.wait_for(lambda: gcs.texts_with("EKF2_EV_CTRL=0") != [], 1.0, "EKF2_EV_CTRL reason")
    gcs.set_params({"EKF2_EV_CTRL": 15})
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 1.0, "vision fusion")
    # Hold (the mode PX4 boots in) needs a global position: an EKF origin, as the gateway gives one.
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.wait_for(lambda: gcs.texts_with("needs a global position") != [], 1.0, "global position reason")
    gcs.set_origin()
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.armed, HEARTBEAT_WAIT_S, "armed heartbeat")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 0) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: not gcs.armed, HEARTBEAT_WAIT_S, "disarmed heartbeat")


def test_mocap_estimator_type_is_not_fused(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle(params=ARENA)
    gcs.mocap = True
    gcs.mocap_type = px4.MAV_ESTIMATOR_TYPE_MOCAP
    # Counted as they come (a busy machine sends fewer a second): 20 ignored, none fused.
    gcs.wait_for(lambda: ap.ignored_mocap > 20, 5.0, "20 mocap-type samples ignored")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED


def test_offboard_flight_climb_hold_land(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    """The control cascade itself, with an exact estimate (``ideal``; PX4's wander: test_sim_px4_parity)."""
    ap, gcs = make_vehicle(ideal=True)
    gcs.set_params(ARENA)
    gcs.mocap = True
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
    # No setpoint yet: disarmed, PX4 takes OFFBOARD anyway, and arming says what is missing.
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.mode == "OFFBOARD", 1.1, "OFFBOARD in the heartbeat")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.wait_for(lambda: gcs.texts_with("no offboard signal") != [], 1.0, "offboard arming refusal reason")
    gcs.setpoint = {"z": -1.0}
    gcs.run_for(0.5)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    climb = gcs.wait_for(lambda: abs(gcs.height - 1.0) < 0.05, 5.0, "climb to 1 m within 5 s")
    assert 1.0 < climb < 5.0
    gcs.wait_for(lambda: gcs.landed_state == px4.MAV_LANDED_STATE_IN_AIR, 1.0, "IN_AIR")
    # Hold (once the step response has settled): the estimate and the truth stay within 5 cm of 1 m for 3 s.
    gcs.run_for(1.0)
    end = gcs.clock.now() + 3.0
    worst = 0.0
    while gcs.clock.now() < end:
        gcs.pump()
        worst = max(worst, abs(gcs.height - 1.0), abs(-ap.true_pose().position[2] - 1.0))
    assert worst < 0.05
    # Move 1 m north and come back over the pad.
    gcs.setpoint = {"x": 1.0, "z": -1.0}
    gcs.wait_for(lambda: abs(ap.true_pose().position[0] - 1.0) < 0.05, 6.0, "1 m step north")
    gcs.setpoint = {"x": 0.0, "z": -1.0}
    gcs.wait_for(lambda: abs(ap.true_pose().position[0]) < 0.05, 6.0, "back over the pad")
    # Land: AUTO.LAND, below MPC_LAND_ALT3 (1 m) at the crawl speed as PX4 v1.16, landed, auto-disarm.
    assert gcs.command(px4.MAV_CMD_NAV_LAND) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.mode == "AUTO.LAND", 1.1, "AUTO.LAND")
    gcs.wait_for(lambda: gcs.landed_state == px4.MAV_LANDED_STATE_LANDING, 1.0, "LANDING state")
    gcs.wait_for(lambda: ap.true_pose().position[2] > -0.8, 1.0, "descending")
    t0, h0 = gcs.clock.now(), ap.true_pose().position[2]
    gcs.wait_for(lambda: ap.true_pose().position[2] > -0.3, 4.0, "descending at the crawl speed")
    rate = (ap.true_pose().position[2] - h0) / (gcs.clock.now() - t0)
    assert rate == pytest.approx(0.3, abs=0.05)  # MPC_LAND_CRWL
    gcs.wait_for(lambda: gcs.landed_state == px4.MAV_LANDED_STATE_ON_GROUND, 3.0, "on the ground")
    gcs.wait_for(lambda: not gcs.armed, 4.0, "auto-disarm after landing")
    assert ap.true_pose().position[2] == 0.0
    assert math.hypot(*ap.true_pose().position[:2]) < 0.1


def test_offboard_loss_lands_by_itself(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle()
    gcs.fly_offboard_to(1.0)
    gcs.setpoint = None  # the user program died
    took = gcs.wait_for(lambda: gcs.texts_with("no offboard signal") != [], 3.0, "offboard-loss failsafe")
    assert 0.9 <= took <= 1.0 + 0.3  # COM_OF_LOSS_T = 1 s
    gcs.wait_for(lambda: gcs.mode == "AUTO.LAND", 1.5, "AUTO.LAND in the heartbeat")
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 1.0 + 1.0 / 0.7 + 2.0, "touchdown")
    gcs.wait_for(lambda: not gcs.armed, DISARM_AFTER_TOUCHDOWN_S, "disarmed")


def test_offboard_loss_with_px4_default_lands_in_position_mode(
    make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]],
) -> None:
    """COM_OBL_RC_ACT 0 (PX4's default): Position mode, where PX4 v1.16 without sticks lands in place."""
    ap, gcs = make_vehicle()
    gcs.fly_offboard_to(1.0)
    gcs.set_params({"COM_OBL_RC_ACT": 0})
    xy = ap.true_pose().position[:2]
    gcs.setpoint = None
    gcs.wait_for(lambda: gcs.mode == "POSCTL", 3.0, "Position mode failsafe")
    assert gcs.texts_with("Failsafe activated")
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 1.0 + 1.0 / 0.7 + 2.0, "landed")
    assert math.dist(ap.true_pose().position[:2], xy) < 0.4  # where it was, give or take PX4's wander
    gcs.wait_for(lambda: not gcs.armed, DISARM_AFTER_TOUCHDOWN_S, "disarmed")


def test_position_loss_failsafe_descends(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    """EKF2_NOAID_TOUT 1 s (the arena's): position invalid 0.6 s after the last sample, then Descend."""
    ap, gcs = make_vehicle()
    gcs.fly_offboard_to(1.0)
    gcs.keep.add("LOCAL_POSITION_NED")
    gcs.mocap = False  # motion capture stops reaching the vehicle
    gcs.wait_for(lambda: gcs.texts_with("no position estimate") != [], 2.0, "position-loss failsafe")
    assert gcs.texts_with("Failsafe activated")
    assert ap.failsafe is not None and ap.failsafe[:2] == ("descend", "position")
    failsafe_at = ap.failsafe[2]
    since_vision = failsafe_at - ap.sim.estimator.ev_hpos_fused_at  # vehicle time, not the test's
    assert (
        0.6 <= since_vision <= 0.6 + ap.CONTROL_PERIOD + ap.sim.dt + ap.skipped_time_s + 1e-6
    )  # skipped: a starved CPU
    gcs.wait_for(lambda: gcs.mode == "AUTO.LAND", 1.5, "AUTO.LAND in the heartbeat")
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 4.0, "descend to the floor")
    gcs.wait_for(lambda: not gcs.armed, DISARM_AFTER_TOUCHDOWN_S, "disarmed")
    # PX4 keeps sending LOCAL_POSITION_NED while the position is invalid.
    assert len([m for m in gcs.messages["LOCAL_POSITION_NED"] if m.time_boot_ms * 1e-3 > failsafe_at]) > 30


def test_a_held_up_simulation_does_not_take_the_stall_for_lost_vision(
    make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]],
) -> None:
    """A busy machine holds the simulation's thread up for a second while mocap and setpoints keep coming,
    as they would to a real vehicle: the simulation skips the time it could not run and reads what came
    before judging anything, so no position-loss or offboard-loss failsafe, and the flight goes on."""
    ap, gcs = make_vehicle(loop_paces=False)  # the world goes on while the vehicle is held up
    gcs.fly_offboard_to(1.0)
    held = threading.Event()

    def hold_up(_pose: object) -> None:
        if not held.is_set():
            held.set()
            time.sleep(1.0)  # real seconds: more than EKF2_NOAID_TOUT's 0.6 s and COM_OF_LOSS_T

    skipped = ap.skipped_time_s
    ap.on_tick = hold_up
    gcs.wait_for(held.is_set, 2.0, "the simulation held up")
    gcs.run_for(gcs.clock.speed * 1.0 + 2.0)  # the stall, in simulated seconds, then 2 s of flight
    assert ap.skipped_time_s - skipped >= 0.6  # the stall was skipped, not simulated
    assert ap.failsafe is None and not gcs.texts_with("Failsafe"), gcs.texts_with("")
    assert gcs.mode == "OFFBOARD" and gcs.armed and abs(gcs.height - 1.0) < 0.1


def test_low_battery_warns_then_lands(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle(battery=BatteryParams(capacity_mah=200.0), soc=0.2)
    gcs.fly_offboard_to(1.0)
    gcs.wait_for(lambda: gcs.texts_with("Low battery") != [], 10.0, "low battery warning")
    assert gcs.mode == "OFFBOARD" and gcs.armed  # a warning only
    gcs.wait_for(lambda: gcs.mode == "AUTO.LAND", 10.0, "critical battery landing")
    assert gcs.texts_with("Critical battery")
    gcs.wait_for(lambda: not gcs.armed, 4.0 + DISARM_AFTER_TOUCHDOWN_S, "landed and disarmed")
    assert ap.sim.battery.soc <= 0.07


def test_forced_disarm_kills_motors_in_the_air(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle()
    gcs.fly_offboard_to(1.0)
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 0) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    gcs.wait_for(lambda: gcs.texts_with("Disarming denied: not landed") != [], 1.0, "the reason")
    result = gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 0, px4.ARM_DISARM_FORCE_MAGIC)
    assert result == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 1.0, "fall")
    assert ap.sim.body.last_impact_speed > 3.0  # fell, not landed
    gcs.wait_for(lambda: not gcs.armed, HEARTBEAT_WAIT_S, "disarmed heartbeat")


def test_takeoff_command_and_flight_termination(
    make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]],
) -> None:
    ap, gcs = make_vehicle(params=ARENA)
    gcs.mocap = True
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
    assert gcs.command(px4.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, 1.5) == px4.MAV_RESULT_ACCEPTED
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.mode == "AUTO.LOITER" and gcs.height > 1.4, 20.0, "takeoff to 1.5 m, then hold")
    assert gcs.command(px4.MAV_CMD_DO_FLIGHTTERMINATION, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.heartbeat.system_status == px4.MAV_STATE_FLIGHT_TERMINATION, 1.0, "termination")
    gcs.wait_for(lambda: ap.true_pose().position[2] == 0.0, 1.5, "fall")
    gcs.wait_for(lambda: not gcs.armed, HEARTBEAT_WAIT_S, "disarmed")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    assert gcs.texts_with("terminated")


def test_reboot_and_retry_not_executed_twice(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    _ap, gcs = make_vehicle()
    t0 = gcs.clock.now()  # before the command: the reboot begins after it was sent, whenever the ack comes
    assert gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == px4.MAV_RESULT_ACCEPTED
    n = gcs.heartbeats
    gcs.wait_for(lambda: gcs.heartbeats > n, 3.0, "heartbeat after reboot")
    assert gcs.clock.now() - t0 >= 0.9  # silent while rebooting (REBOOT_SECONDS 1.0)
    boot_ms = gcs.local_position.time_boot_ms if gcs.local_position else None
    gcs.wait_for(lambda: gcs.local_position.time_boot_ms < 1500, 1.0, "time since boot restarted")
    # The gateway did not see the ack in time and retries with confirmation 1: acked, not rebooted again.
    result = gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, confirmation=1)
    assert result == px4.MAV_RESULT_ACCEPTED
    before = gcs.heartbeats
    gcs.run_for(1.5)
    assert gcs.heartbeats > before and gcs.local_position.time_boot_ms > 1500
    assert boot_ms is not None


def test_mav_sys_id_applies_after_reboot(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    _ap, gcs = make_vehicle()
    gcs.set_params({"MAV_SYS_ID": 12})
    gcs.run_for(0.5)
    assert gcs.heartbeat.get_srcSystem() == SYSID  # needs a reboot, like PX4
    assert gcs.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.heartbeat.get_srcSystem() == 12, 3.0, "heartbeat from system 12")
    gcs.target = 12
    assert px4.param_float_to_int(gcs.read_param("MAV_SYS_ID").param_value) == 12


def test_messages_to_other_systems_are_ignored(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle(params=ARENA)
    gcs.mocap = True
    gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
    for target in (SYSID + 1, 0):
        gcs.conn.mav.command_long_send(target, 1, px4.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        gcs.set_param("COM_OF_LOSS_T", 5.0, target=target)
    gcs.conn.mav.command_long_send(SYSID, 99, px4.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    gcs.run_for(1.5)
    assert gcs.acks == [] and not gcs.armed and ap.param("COM_OF_LOSS_T") == 1.0
    # Setpoints for another system do not make a stream for this one: OFFBOARD is taken (disarmed, as
    # PX4 does) but arming in it is refused.
    gcs.setpoint = {"z": -1.0}
    gcs.target = SYSID + 1
    gcs.run_for(1.0)
    gcs.setpoint = None
    gcs.target = SYSID
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    # Manual modes can be selected but not armed in (no manual control input in the arena).
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_POSCTL) == px4.MAV_RESULT_ACCEPTED
    gcs.wait_for(lambda: gcs.mode == "POSCTL", 1.1, "POSCTL in the heartbeat")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED
    assert gcs.texts_with("No manual control input")
    # Frames PX4 does not take are refused with its text, and make no stream.
    assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
    gcs.setpoint = {"z": -1.0, "frame": px4.MAV_FRAME_LOCAL_OFFSET_NED}
    gcs.run_for(1.0)
    assert gcs.texts_with("SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported")
    assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_TEMPORARILY_REJECTED


def test_timesync_initiated_and_answered(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    ap, gcs = make_vehicle(speed=1.0)  # real time, so that round trips stay well under PX4's 10 ms
    gcs.run_for(2.0)
    reqs = gcs.timesync_requests
    assert len(reqs) == pytest.approx(20, abs=4)  # 10 Hz
    assert all(tc1 == 0 for tc1, _, _ in reqs)
    ts = [ts1 for _, ts1, _ in reqs]
    assert ts == sorted(ts) and ts[-1] - ts[0] == pytest.approx((len(ts) - 1) * 1e8, rel=0.1)  # its ns clock
    assert ap.timesync.sequence > 5  # our replies were accepted by its filter (RTT < 10 ms)
    ours = 123_456_789_000
    gcs.conn.mav.timesync_send(0, ours)
    gcs.wait_for(lambda: any(r.ts1 == ours for r in gcs.timesync_replies), 1.0, "reply to our request")
    reply = next(r for r in gcs.timesync_replies if r.ts1 == ours)
    assert reply.tc1 > 0


def test_timesync_filter_converges_and_stamps() -> None:
    f = TimesyncFilter()
    offset_us = 5_000_000_000  # local = remote + offset
    now = 1_000_000
    for i in range(px4.TIMESYNC_CONVERGENCE_WINDOW):
        assert not f.converged
        assert f.sync_stamp(42, arrival_us=now) == now  # arrival time until converged
        rtt = 400 + (i * 37) % 300
        sent = now
        now += rtt
        remote_at_echo = sent + rtt // 2 - offset_us
        assert f.update(now, remote_at_echo, sent)
        now += 100_000
    assert f.converged
    assert f.offset_us == pytest.approx(offset_us, abs=200)
    assert f.sync_stamp(1_000, arrival_us=now) == pytest.approx(1_000 + offset_us, abs=200)
    assert not f.update(now + 20_000, now - offset_us, now)  # 20 ms round trip: rejected
    for _ in range(px4.TIMESYNC_MAX_CONSECUTIVE_HIGH_DEVIATION + 1):  # the other side's clock jumped
        now += 100_000
        f.update(now + 500, now + 250 - offset_us + 10_000_000, now)
    assert not f.converged and f.resets == 1


def test_tcp_link(make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]]) -> None:
    port = free_port(socket.SOCK_STREAM)
    clock = SimClock(speed=SPEED)
    ap = SimAutopilot(f"tcpin:127.0.0.1:{port}", 3, clock=clock)
    with AutopilotLoop([ap]):
        for _ in range(2):  # connect, disconnect, connect again
            gcs = Gcs(f"tcp:127.0.0.1:{port}", clock, target=3)
            try:
                gcs.wait_for(lambda g=gcs: g.heartbeat is not None, 3.0, "heartbeat over TCP")  # type: ignore[misc]
                assert px4.param_float_to_int(gcs.read_param("MAV_SYS_ID").param_value) == 3
            finally:
                gcs.close()
    ap.close()


def test_udp_link_listens_only_on_the_address_facing_its_gateway(
    make_vehicle: Callable[..., tuple[SimAutopilot, Gcs]],
) -> None:
    """A simulated vehicle stands for a serial line or radio: its UDP port is not on every interface."""
    ap, gcs = make_vehicle()
    local = ap.conn.port.getsockname()
    assert local[0] == "127.0.0.1" and local[1] != 0
    gcs.wait_for(lambda: gcs.heartbeat is not None, 2.0, "heartbeat")


def test_several_vehicles_one_loop_and_low_cpu() -> None:
    """Five vehicles in one thread at real time, flying and streaming: CPU stays far below one core."""
    clock = SimClock(speed=1.0)
    gcss, aps = [], []
    for i in range(5):
        port = free_port()
        gcs = Gcs(f"udpin:127.0.0.1:{port}", clock, target=i + 1)
        ap = SimAutopilot(f"udpout:127.0.0.1:{port}", i + 1, clock=clock, params=ARENA, position=(i, 0, 0))
        gcs.ap = ap
        gcs.mocap = True
        gcs.setpoint = {"x": float(i), "z": -1.0}
        gcss.append(gcs)
        aps.append(ap)
    cpu: list[float] = []

    def loop() -> None:
        c0 = time.thread_time()
        run_autopilots(aps, duration=3.0)
        cpu.append(time.thread_time() - c0)

    import threading

    thread = threading.Thread(target=loop)
    t0 = time.monotonic()
    thread.start()
    armed = set()
    while thread.is_alive() and time.monotonic() - t0 < 10.0:
        for i, gcs in enumerate(gcss):
            gcs.pump(0.0005)
            if i not in armed and gcs.texts_with("vision fusion started"):
                armed.add(i)
                gcs.conn.mav.command_long_send(
                    i + 1, 1, px4.MAV_CMD_DO_SET_MODE, 0, 1, px4.MAIN_OFFBOARD, 0, 0, 0, 0, 0
                )
                gcs.conn.mav.command_long_send(
                    i + 1, 1, px4.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
                )
    thread.join()
    wall = time.monotonic() - t0
    for i, (gcs, ap) in enumerate(zip(gcss, aps, strict=True)):
        assert gcs.sources == {i + 1}  # each link carries only its own vehicle
        assert gcs.armed and -ap.true_pose().position[2] > 0.3  # all took off
        gcs.close()
        ap.close()
    core_fraction = cpu[0] / wall
    print(f"5 vehicles, real time: {core_fraction * 100:.1f} % of one core")
    assert core_fraction < 0.5


def test_bad_configuration_raises() -> None:
    with pytest.raises(SimAutopilotError, match="system id"):
        SimAutopilot("udpout:127.0.0.1:9", 0)
    with pytest.raises(SimAutopilotError, match="unknown parameter"):
        SimAutopilot("udpout:127.0.0.1:9", 1, params={"NOT_A_PARAM": 1})
    with pytest.raises(SimAutopilotError, match="EKF2_EV_CTRL"):
        SimAutopilot("udpout:127.0.0.1:9", 1, params={"EKF2_EV_CTRL": 1.5})
    with pytest.raises(SimAutopilotError, match="speed"):
        SimClock(speed=0)
    with pytest.raises(SimAutopilotError, match="stop event or a duration"):
        run_autopilots([SimAutopilot("udpout:127.0.0.1:9", 1)])
