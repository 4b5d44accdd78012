"""One MAVSDK script, run against the simulated autopilot and against a real PX4 v1.16 SITL.

MAVSDK (PyPI ``mavsdk`` ≥ 4: the native binding, ``libcmavsdk.so`` inside the wheel, no server process
and nothing downloaded at run time) is the API most PX4 users script with. :func:`run_capabilities`
drives one vehicle through what such a script uses — connection, telemetry (attitude, position, home,
health, battery, flight mode), message rates, REQUEST_MESSAGE, parameters (INT32 and REAL32), arm and
disarm, takeoff, DO_CHANGE_SPEED, goto (DO_REPOSITION), offboard (position NED, velocity NED, velocity
body, global position; started after a single setpoint; stopped into Hold), a mission upload and start,
land — and records which capabilities worked.

Vision comes from a separate plain pymavlink link, as the arena's gateway would send it: ODOMETRY in
MAV_FRAME_LOCAL_NED built from the vehicle's true pose (the simulator's, or PX4 SIH's
HIL_STATE_QUATERNION on UDP 19410+i), 40 Hz. MAVSDK sets the EKF origin (SET_GPS_GLOBAL_ORIGIN).

``test_mavsdk_capabilities_sim`` runs against :class:`~arena_common.sim.autopilot.SimAutopilot` on a
free UDP port; ``test_mavsdk_capabilities_px4`` against PX4 SITL started by the tier's ``px4_sitl`` fixture
(``PX4_SITL_DIR``, else ``../shared/px4-sitl``; the tier skips with the reason when there is no build), and
``test_sim_does_what_px4_does`` asserts that every capability that works on PX4 works on the simulator (it
reuses both results, so run the module whole). By hand: ``python tests/px4/test_mavsdk.py sim|px4 [N]``.
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from arena_common.mavlink import px4  # noqa: E402
from arena_common.runtime.px4_sitl import Px4Sitl  # noqa: E402
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot, SimClock  # noqa: E402

pytestmark = pytest.mark.px4

mavsdk = pytest.importorskip("mavsdk", reason="PyPI mavsdk (>= 4, native binding) is not installed")

#: Parameters a lab's vehicle has after `arena px4 setup` (and PX4 SITL gets at boot here).
SETUP = {
    "EKF2_EV_CTRL": 15,
    "EKF2_HGT_REF": 3,
    "EKF2_GPS_CTRL": 0,
    "EKF2_MAG_TYPE": 5,
    "COM_RC_IN_MODE": 4,
    "COM_OBL_RC_ACT": 4,
}
ORIGIN = (47.397742, 8.545594, 0.0)  # SIH's default home; the EKF origin MAVSDK sets (lat, lon, alt)
EARTH_RADIUS = 6378137.0

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ned_to_global(north: float, east: float, down: float) -> Vec3:
    """Flat-earth conversion around :data:`ORIGIN` (metres → degrees, altitude AMSL)."""
    lat0, lon0, alt0 = ORIGIN
    lat = lat0 + math.degrees(north / EARTH_RADIUS)
    lon = lon0 + math.degrees(east / (EARTH_RADIUS * math.cos(math.radians(lat0))))
    return lat, lon, alt0 - down


def global_to_ned(lat: float, lon: float, alt: float) -> Vec3:
    """Inverse of :func:`ned_to_global`."""
    lat0, lon0, alt0 = ORIGIN
    north = math.radians(lat - lat0) * EARTH_RADIUS
    east = math.radians(lon - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
    return north, east, alt0 - alt


# --- vision feed ------------------------------------------------------------------------------------


class VisionFeed:
    """ODOMETRY (LOCAL_NED, BODY_FRD, VISION) from a true-pose source, sent to ``dest`` at 40 Hz."""

    def __init__(self, dest: tuple[str, int], truth: Callable[[], tuple[Vec3, Quat] | None]) -> None:
        self.conn = mavutil.mavlink_connection(
            f"udpout:{dest[0]}:{dest[1]}", source_system=200, source_component=197, dialect="common"
        )
        self.truth = truth
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="vision-feed", daemon=True)

    def start(self) -> VisionFeed:
        self._thread.start()
        return self

    def _run(self) -> None:
        nan21 = [math.nan] * 21
        while not self._stop.wait(0.025):
            pose = self.truth()
            if pose is not None:
                p, q = pose
                self.conn.mav.odometry_send(
                    time.monotonic_ns() // 1000, px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_BODY_FRD,
                    p[0], p[1], p[2], list(q), math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                    nan21, nan21, 0, px4.MAV_ESTIMATOR_TYPE_VISION, 0,
                )  # fmt: skip
                self.sent += 1
            with contextlib.suppress(OSError):
                while self.conn.recv_msg() is not None:  # PX4's GCS link talks back: drain it
                    pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


class SihTruth:
    """PX4 SIH ground truth (HIL_STATE_QUATERNION on UDP ``port``: 19410+i) as NED around :data:`ORIGIN`.

    Down is measured from the first sample's altitude (the vehicle on the ground at boot), so that the
    vision PX4 gets puts the floor at down = 0, as the arena's calibrated frame does.
    """

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
        self._lock = threading.Lock()
        self._latest: tuple[Vec3, Quat] | None = None
        self._ground_alt: float | None = None

    def __call__(self) -> tuple[Vec3, Quat] | None:
        with self._lock:
            while True:
                try:
                    msg = self.conn.recv_msg()
                except OSError:
                    break
                if msg is None:
                    break
                if msg.get_type() == "HIL_STATE_QUATERNION":
                    alt = msg.alt * 1e-3
                    if self._ground_alt is None:
                        self._ground_alt = alt
                    ned = global_to_ned(msg.lat * 1e-7, msg.lon * 1e-7, alt - self._ground_alt + ORIGIN[2])
                    q = msg.attitude_quaternion
                    self._latest = (ned, (q[0], q[1], q[2], q[3]))
            return self._latest

    def close(self) -> None:
        self.conn.close()


# --- targets ----------------------------------------------------------------------------------------


@dataclass
class Target:
    """A vehicle to run the script against: MAVSDK's URL, a vision feed, and how to tear it down."""

    name: str
    url: str
    sysid: int
    truth: Callable[[], tuple[Vec3, Quat] | None]
    vision_dest: tuple[str, int]
    closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        for close in reversed(self.closers):
            with contextlib.suppress(Exception):
                close()


@contextlib.contextmanager
def sim_target(sysid: int = 1) -> Iterator[Target]:
    """A :class:`SimAutopilot` (real time, arena parameters) sending to a free port MAVSDK listens on."""
    port = free_udp_port()
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", sysid, clock=SimClock(1.0), params=SETUP)
    loop = AutopilotLoop([ap]).start()
    # MAVSDK listens where the vehicle sends; the vision feed sends to the vehicle's own socket.
    ap.conn.mav.heartbeat_send(px4.MAV_TYPE_QUADROTOR, px4.MAV_AUTOPILOT_PX4, 0, 0, 0)  # binds the socket
    dest = ap.conn.port.getsockname()

    def truth() -> tuple[Vec3, Quat]:
        pose = ap.true_pose()
        return pose.position, pose.q

    target = Target("sim", f"udpin://127.0.0.1:{port}", sysid, truth, (dest[0], dest[1]))
    target.closers += [ap.close, loop.stop]
    try:
        yield target
    finally:
        target.close()


@contextlib.contextmanager
def px4_target(px4_sim: Px4Sitl) -> Iterator[Target]:
    """A running PX4 SITL instance (:class:`~arena_common.runtime.px4_sitl.Px4Sitl`, booted with :data:`SETUP`).

    MAVSDK sends first to PX4's offboard port (PX4 latches its first peer); the vision feed goes to the
    ground-station port, the SIH truth comes from the truth port.
    """
    ports = px4_sim.ports
    truth = SihTruth(ports.truth)
    target = Target(
        "px4",
        f"udpout://127.0.0.1:{ports.px4_offboard}",
        ports.system_id,
        truth,
        ("127.0.0.1", ports.px4_gcs),
    )
    target.closers.append(truth.close)
    try:
        yield target
    finally:
        target.close()


# --- the script -------------------------------------------------------------------------------------


class Script:
    """The capability checks, each recorded by name as ``"ok"`` or the reason it failed."""

    def __init__(self, target: Target, log: Callable[[str], None] = lambda _s: None) -> None:
        self.target = target
        self.results: dict[str, str] = {}
        self.log = log
        self.system: Any = None
        self.plugins: dict[str, Any] = {}

    # helpers
    def check(self, name: str, fn: Callable[[], object]) -> bool:
        try:
            outcome = fn()
        except Exception as exc:  # every failure is a finding, never a crash of the script
            self.results[name] = f"{type(exc).__name__}: {exc}"
        else:
            self.results[name] = "failed" if outcome is False else "ok"
        self.log(f"{self.target.name}: {name}: {self.results[name]}")
        return self.results[name] == "ok"

    @staticmethod
    def wait(predicate: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            time.sleep(0.05)
        raise TimeoutError(f"no {what} within {timeout} s")

    def truth(self) -> Vec3:
        pose = self.target.truth()
        assert pose is not None, "no true pose"
        return pose[0]

    def telemetry(self) -> Any:
        return self.plugins["telemetry"]

    def mode(self) -> Any:
        return self.telemetry().flight_mode()

    def in_air(self) -> bool:
        return bool(self.telemetry().in_air())

    def settled(self) -> bool:
        """Nearly at rest: the true position moved less than 5 cm in 0.25 s (under 0.2 m/s)."""
        a = self.truth()
        time.sleep(0.25)
        return math.dist(a, self.truth()) < 0.05

    def near(self, north: float, east: float, height: float, tol: float = 0.3) -> bool:
        p = self.truth()
        return math.dist((p[0], p[1], -p[2]), (north, east, height)) < tol

    # the run
    def run(self) -> dict[str, str]:
        from mavsdk import ComponentType, Configuration, Mavsdk
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.info import Info
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.mission import Mission
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry

        feed = VisionFeed(self.target.vision_dest, self.target.truth).start()
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            if not self.check("connect", lambda: sdk.add_any_connection(self.target.url).name == "SUCCESS"):
                return self.results

            def first() -> bool:
                self.system = sdk.first_autopilot(20.0)
                return self.system is not None

            if not self.check("discover autopilot", first):
                return self.results
            system = self.system
            self.plugins = {
                "telemetry": Telemetry(system),
                "action": Action(system),
                "offboard": Offboard(system),
                "param": Param(system),
                "info": Info(system),
                "mission": Mission(system),
                "direct": MavlinkDirect(system),
            }
            self._run_steps()
        finally:
            for plugin in self.plugins.values():
                with contextlib.suppress(Exception):
                    plugin.destroy()
            with contextlib.suppress(Exception):
                sdk.destroy()
            feed.close()
        return self.results

    def command(self, command: int, *params: float) -> int:
        """A COMMAND_LONG through MavlinkDirect; returns the MAV_RESULT of its ack."""
        import json

        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        fields: dict[str, float] = {
            "target_system": self.target.sysid,
            "target_component": 1,
            "command": command,
        }
        fields.update({f"param{i + 1}": v for i, v in enumerate(p)})
        fields["confirmation"] = 0
        msg = MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=0,
            component_id=0,
            target_system_id=self.target.sysid,
            target_component_id=1,
            fields_json=json.dumps(fields),
        )
        ack = self.plugins["direct"].send_command(msg)
        return int(json.loads(ack.fields_json)["result"])

    def _run_steps(self) -> None:
        from mavsdk.plugins.mission import MissionItem, MissionPlan
        from mavsdk.plugins.offboard import (
            PositionGlobalYaw,
            PositionNedYaw,
            VelocityBodyYawspeed,
            VelocityNedYaw,
        )

        tel = self.telemetry()
        action = self.plugins["action"]
        offboard = self.plugins["offboard"]
        param = self.plugins["param"]
        check, wait = self.check, self.wait

        # --- on the ground: identity, telemetry, rates, parameters
        check("info.get_version (AUTOPILOT_VERSION)", lambda: info_version_ok(self.plugins["info"]))
        check(
            "action.set_gps_global_origin",
            lambda: action.set_gps_global_origin(ORIGIN[0], ORIGIN[1], ORIGIN[2]) is not None,
        )
        check(
            "telemetry.heartbeat flight_mode", lambda: wait(lambda: self.mode().name != "UNKNOWN", 5, "mode")
        )
        check(
            "telemetry.attitude_euler (ATTITUDE)",
            lambda: wait(lambda: tel.attitude_euler().timestamp_us > 0, 5, "ATTITUDE"),
        )
        check(
            "telemetry.attitude_quaternion",
            lambda: wait(lambda: abs(tel.attitude_quaternion().w) > 0.1, 5, "ATTITUDE_QUATERNION"),
        )
        check(
            "telemetry.velocity_ned",
            lambda: wait(lambda: tel.position_velocity_ned().position.down_m != 0.0, 5, "LOCAL_POSITION_NED"),
        )
        check("telemetry.battery", lambda: wait(lambda: tel.battery().voltage_v > 1.0, 5, "BATTERY_STATUS"))
        check(
            "telemetry.health local position ok",
            lambda: wait(lambda: tel.health().is_local_position_ok, 20, "local position ok in health"),
        )
        self.log(f"{self.target.name}: health {vars(tel.health())}")
        check(
            "telemetry.position (GLOBAL_POSITION_INT)",
            lambda: wait(
                lambda: abs(tel.position().latitude_deg - ORIGIN[0]) < 0.001, 10, "GLOBAL_POSITION_INT"
            ),
        )
        check(
            "telemetry.home (HOME_POSITION)",
            lambda: wait(lambda: abs(tel.home().latitude_deg - ORIGIN[0]) < 0.001, 10, "HOME_POSITION"),
        )
        check("telemetry.health is_armable", lambda: wait(lambda: tel.health().is_armable, 20, "armable"))
        check(
            "telemetry.set_rate_attitude_euler (SET_MESSAGE_INTERVAL)",
            lambda: tel.set_rate_attitude_euler(20.0),
        )
        check("telemetry.set_rate_position", lambda: tel.set_rate_position(10.0))
        check(
            "REQUEST_MESSAGE AUTOPILOT_VERSION",
            lambda: self.command(px4.MAV_CMD_REQUEST_MESSAGE, 148) == px4.MAV_RESULT_ACCEPTED,
        )
        check(
            "REQUEST_MESSAGE HOME_POSITION",
            lambda: self.command(px4.MAV_CMD_REQUEST_MESSAGE, 242) == px4.MAV_RESULT_ACCEPTED,
        )

        def params_int() -> bool:
            before = param.get_param_int("COM_OBL_RC_ACT")
            param.set_param_int("COM_OBL_RC_ACT", 5)
            after = param.get_param_int("COM_OBL_RC_ACT")
            param.set_param_int("COM_OBL_RC_ACT", before)
            return after == 5 and param.get_param_int("COM_OBL_RC_ACT") == before

        def params_float() -> bool:
            param.set_param_float("MPC_XY_CRUISE", 3.5)
            return abs(param.get_param_float("MPC_XY_CRUISE") - 3.5) < 1e-4

        check("param get/set int", params_int)
        check("param get/set float", params_float)
        check("action.set_takeoff_altitude", lambda: action.set_takeoff_altitude(1.5))
        check("action.get_takeoff_altitude", lambda: abs(action.get_takeoff_altitude() - 1.5) < 1e-3)

        # --- arm, disarm, arm, take off
        check("action.arm", action.arm)
        check("telemetry.armed", lambda: wait(lambda: tel.armed(), 5, "armed"))
        check("action.disarm", action.disarm)
        check("telemetry.disarmed", lambda: wait(lambda: not tel.armed(), 5, "disarmed"))
        check("action.arm (again)", action.arm)
        if not check("action.takeoff", action.takeoff):
            return
        check(
            "takeoff reaches 1.5 m",
            lambda: wait(lambda: self.near(*self.truth()[:2], 1.5, 0.25), 20, "1.5 m"),
        )
        check("telemetry.in_air", lambda: wait(self.in_air, 5, "in air"))
        check("hold after takeoff", lambda: wait(lambda: self.mode().name == "HOLD", 10, "HOLD"))

        # --- auto: speed, goto
        check("action.set_current_speed (DO_CHANGE_SPEED)", lambda: action.set_current_speed(1.0))
        lat, lon, alt = ned_to_global(1.0, 0.0, -1.5)
        check("action.goto_location (DO_REPOSITION)", lambda: action.goto_location(lat, lon, alt, 0.0))
        check("goto arrives", lambda: wait(lambda: self.near(1.0, 0.0, 1.5), 20, "goto target"))

        # --- offboard
        check(
            "offboard.set_position_ned (one setpoint)",
            lambda: offboard.set_position_ned(PositionNedYaw(1.0, 0.0, -1.5, 0.0)),
        )
        if check("offboard.start after one setpoint", offboard.start):
            check("mode OFFBOARD", lambda: wait(lambda: self.mode().name == "OFFBOARD", 5, "OFFBOARD"))
            offboard.set_position_ned(PositionNedYaw(0.0, 0.0, -1.5, 0.0))
            check(
                "offboard position NED flies",
                lambda: wait(lambda: self.near(0.0, 0.0, 1.5), 20, "NED target"),
            )
            offboard.set_velocity_ned(VelocityNedYaw(0.5, 0.0, 0.0, 0.0))
            check(
                "offboard velocity NED flies", lambda: wait(lambda: self.truth()[0] > 0.5, 10, "north 0.5 m")
            )
            offboard.set_velocity_body(VelocityBodyYawspeed(-0.5, 0.0, 0.0, 0.0))
            check(
                "offboard velocity body flies", lambda: wait(lambda: self.truth()[0] < 0.0, 10, "back south")
            )
            g = ned_to_global(0.5, 0.5, -1.5)
            offboard.set_position_global(
                PositionGlobalYaw(g[0], g[1], 1.5, 0.0, PositionGlobalYaw.AltitudeType.REL_HOME)
            )
            check(
                "offboard position global flies",
                lambda: wait(lambda: self.near(0.5, 0.5, 1.5), 20, "global target"),
            )
            check("offboard.stop", offboard.stop)
            check("hold after offboard.stop", lambda: wait(lambda: self.mode().name == "HOLD", 5, "HOLD"))
            # Hold first brakes to its braking point (PX4: v·(v/2a + 0.6 s), ≈ 0.3 m from 0.45 m/s; the
            # simulated autopilot does the same): "stays put" is judged once that stop is over.
            check("hold brakes to a stop", lambda: wait(self.settled, 10, "at rest in HOLD"))
            p0 = self.truth()
            time.sleep(2.0)
            check("hold stays put", lambda: math.dist(p0, self.truth()) < 0.3)

        # --- mission
        items = []
        for north, east in ((0.0, 1.0), (1.0, 1.0), (0.0, 0.0)):
            la, lo, _ = ned_to_global(north, east, 0.0)
            items.append(
                MissionItem(
                    latitude_deg=la,
                    longitude_deg=lo,
                    relative_altitude_m=1.5,
                    speed_m_s=1.0,
                    is_fly_through=False,
                    acceptance_radius_m=0.3,
                    yaw_deg=0.0,
                )
            )
        mission = self.plugins["mission"]
        if check("mission.upload_mission", lambda: mission.upload_mission(MissionPlan(items))):
            check("mission.start_mission", mission.start_mission)
            check("mode MISSION", lambda: wait(lambda: self.mode().name == "MISSION", 10, "MISSION"))
            check("mission finishes", lambda: wait(mission.is_mission_finished, 40, "mission finished"))
            check(
                "mission ends at last item",
                lambda: wait(lambda: self.near(0.0, 0.0, 1.5, 0.4), 10, "last item"),
            )

        # --- land
        check("action.land", action.land)
        check("lands", lambda: wait(lambda: not self.in_air(), 20, "on the ground"))
        check("auto-disarm after landing", lambda: wait(lambda: not tel.armed(), 20, "disarmed"))


def info_version_ok(info: Any) -> bool:
    version = info.get_version()
    return bool(version.flight_sw_major >= 1)


# --- tests ------------------------------------------------------------------------------------------

_RESULTS: dict[str, dict[str, str]] = {}


def _report(name: str, results: dict[str, str]) -> str:
    return "\n".join(f"  {k}: {v}" for k, v in results.items() if v != "ok") or "  (all ok)"


def _sim_results() -> dict[str, str]:
    """The script's results on the simulated autopilot (run once per session, whichever test asks first)."""
    if "sim" not in _RESULTS:
        with sim_target() as target:
            _RESULTS["sim"] = Script(target, print).run()
    return _RESULTS["sim"]


def _px4_results(px4_sitl: Callable[..., Px4Sitl]) -> dict[str, str]:
    """The script's results on PX4 v1.16 SITL (run once per session, whichever test asks first)."""
    if "px4" not in _RESULTS:
        with px4_target(px4_sitl(params=SETUP)) as target:
            _RESULTS["px4"] = Script(target, print).run()
    return _RESULTS["px4"]


def test_mavsdk_capabilities_sim() -> None:
    results = _sim_results()
    failed = {k: v for k, v in results.items() if v != "ok"}
    assert not failed, f"MAVSDK capabilities failing on the simulated autopilot:\n{_report('sim', results)}"


def test_mavsdk_capabilities_px4(px4_sitl: Callable[..., Px4Sitl]) -> None:
    """The same script against PX4 v1.16 SITL (the tier's fixture starts it; skipped without a build)."""
    results = _px4_results(px4_sitl)
    assert results.get("discover autopilot") == "ok", _report("px4", results)


def test_sim_does_what_px4_does(px4_sitl: Callable[..., Px4Sitl]) -> None:
    """Whatever MAVSDK can do with PX4 it can do with the simulated autopilot (runs both scripts if no
    other test of this module has: no test depends on another having run)."""
    px4_ok = {k for k, v in _px4_results(px4_sitl).items() if v == "ok"}
    sim_ok = {k for k, v in _sim_results().items() if v == "ok"}
    assert px4_ok <= sim_ok, f"work on PX4 but not on the sim: {sorted(px4_ok - sim_ok)}"


def main(argv: list[str]) -> int:
    """``python tests/px4/test_mavsdk.py sim|px4 [instance 0..9]``: run the script, print each capability."""
    which = argv[1] if len(argv) > 1 else "sim"
    with contextlib.ExitStack() as stack:
        if which == "px4":
            px4_sim = stack.enter_context(Px4Sitl(int(argv[2]) if len(argv) > 2 else 9, params=SETUP))
            target = stack.enter_context(px4_target(px4_sim))
        else:
            target = stack.enter_context(sim_target())
        results = Script(target, print).run()
    print(_report(which, results))
    return 0 if all(v == "ok" for v in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
