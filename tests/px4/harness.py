"""The real-PX4 tier's machinery: PX4 SITL instances and the arena's unchanged services in front of them.

:class:`Px4Stack` runs, for each vehicle of a private config (``autopilot = "px4-sitl"``), a PX4 SITL
instance (in this process: :class:`~arena_common.runtime.px4_sitl.Px4Sitl`, so a test can read PX4's own view
with ``px4-listener`` or boot it again) and, as separate processes that a test can stop and start, the
Motive emulator, mocap ingest, frame transform, and per vehicle its truth bridge, downsampler and
gateway — the pipeline ``arena up`` runs, one process each.  Every output goes to a log file under the
test's temporary directory.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from arena_common import Arena
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.geometry.frames import quat_yaw, wrap_angle
from arena_common.runtime.options import read_config
from arena_common.runtime.process import child_setup
from arena_common.runtime.px4_sitl import MAX_INSTANCE, Px4Sitl, Px4SitlError, instance_busy, is_true
from services.px4_sitl import boot_params
from tests.conftest import REPO, free_port, wait_for

HOST = "test"
SHARED = ("sim_mocap", "mocap_ingest", "frame_transform")  # the room and the ground computer
PER_VEHICLE = ("px4_truth", "downsampler", "mavlink_gateway")


class InstancePool:
    """Distinct PX4 SITL instance numbers (0..9) for the tests of one session, skipping busy ones.

    Numbers are handed out in turn, so consecutive tests use different instances (no stale socket or
    port of a previous test in the way); one held by this session or by any px4 of the machine (its lock
    file held, e.g. a colleague's) is never handed out.
    """

    def __init__(self, numbers: Sequence[int] = tuple(range(MAX_INSTANCE + 1))) -> None:
        self.numbers = tuple(numbers)
        self.held: set[int] = set()
        self._next = 0
        self._lock = threading.Lock()

    def take(self) -> int:
        """A free instance number; :class:`RuntimeError` when all ten are busy."""
        with self._lock:
            for k in range(len(self.numbers)):
                n = self.numbers[(self._next + k) % len(self.numbers)]
                if n not in self.held and not instance_busy(n):
                    self.held.add(n)
                    self._next = (self._next + k + 1) % len(self.numbers)
                    return n
        raise RuntimeError(f"every PX4 SITL instance of {self.numbers} is in use on this machine")

    def give_back(self, n: int) -> None:
        """Return ``n`` to the pool."""
        with self._lock:
            self.held.discard(n)


def write_px4_config(
    path: Path,
    router_endpoint: str,
    instances: Mapping[str, int],
    *,
    preset: str = "arena",
    px4_params: Mapping[str, Mapping[str, float]] | None = None,
    starts: Mapping[str, tuple[float, float]] | None = None,
    require_setup: bool = True,
    services: Sequence[str] = ("sim", "mocap", "transform"),
    extra: str = "",
    simulated: bool = False,
) -> ArenaConfig:
    """Write (and load) a config of PX4 SITL vehicles whose every port is private to this test.

    ``instances``: vehicle name → PX4 SITL instance; ``preset``: ``sim.px4_params`` ("arena" boots PX4
    set up for the arena, "px4" with its defaults); ``px4_params``: per-vehicle boot parameters;
    ``require_setup`` false lets the gateways arm a PX4 whose parameters differ from the arena's;
    ``simulated``: the same vehicles flown by the arena's simulated autopilot instead (its default
    ``fidelity``, "px4"), for comparing the two.
    """
    cmd_port, data_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    lines = [
        "[arena]",
        'name = "px4-test"',
        "[mocap]",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        "multicast = false",
        f"command_port = {cmd_port}",
        f"data_port = {data_port}",
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["{router_endpoint}"]',
        f'router_listen = ["{router_endpoint}"]',
        f"[hosts.{HOST}]",
        "services = [" + ", ".join(f'"{x}"' for x in services) + "]",
        "vehicles = [" + ", ".join(f'"{v}"' for v in instances) + "]",
        "[sim]",
        f'px4_params = "{preset}"',
    ]
    for index, (name, n) in enumerate(instances.items()):
        north, east = (starts or {}).get(name, (index * 1.0 - 1.0, 0.0))
        flown_by = (
            [f'mavlink = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"', f"system_id = {index + 1}"]
            if simulated
            else ['autopilot = "px4-sitl"', f"px4_instance = {n}"]
        )
        lines += [
            f"[vehicles.{name}]",
            *flown_by,
            f'rigid_body = "{name}"',
            f"sim = {{ start = [{north}, {east}] }}",
            f"require_setup = {str(require_setup).lower()}",
        ]
        params = (px4_params or {}).get(name)
        if params:
            lines.append("px4_params = { " + ", ".join(f"{k} = {v!r}" for k, v in params.items()) + " }")
    lines.append(extra)
    path.write_text("\n".join(lines) + "\n")
    return read_config(path)


def _spawn(argv: list[str], log: Path) -> subprocess.Popen[bytes]:
    """Start ``argv`` from the checkout, its output appended to ``log``; it dies with the test run (a run
    that is killed takes its services with it: they had outlived it)."""
    with open(log, "ab") as out:
        return subprocess.Popen(
            argv,
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"},
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            preexec_fn=child_setup(os.getpid(), signal.SIGTERM),
        )


@dataclass
class _Proc:
    argv: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    stopped: bool = False  # by the test (Px4Stack.stop), not a crash


@dataclass
class Px4Stack:
    """PX4 SITL instances and the arena's services of one config; :meth:`close` stops everything."""

    cfg: ArenaConfig
    logs: Path
    px4: dict[str, Px4Sitl] = field(default_factory=dict)
    procs: dict[str, _Proc] = field(default_factory=dict)
    boot_s: dict[str, float] = field(default_factory=dict)
    keep_log: bool = False  # PX4 writes its ULog (~1 MB/s): :meth:`ulog` after :meth:`stop_px4`
    # A slow link (delay, jitter: s each way) between a vehicle's PX4 and its gateway: a relay, as a radio
    links: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    relays: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)  # tests.px4.radio
    _files: list[IO[str]] = field(default_factory=list)

    # -- PX4 ----------------------------------------------------------------------------------------------
    def start_px4(self, vehicle: str) -> float:
        """Boot ``vehicle``'s PX4 SITL instance (output in ``px4.<vehicle>.log``); its boot time [s]."""
        spec = self.cfg.vehicle(vehicle)
        assert spec.px4_instance is not None, vehicle
        out = open(self.logs / f"px4.{vehicle}.log", "a", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._files.append(out)

        def write(line: str) -> None:
            out.write(f"{time.strftime('%H:%M:%S')} {line}\n")
            out.flush()

        px4 = Px4Sitl(
            spec.px4_instance, params=boot_params(self.cfg, spec), output=write, keep_log=self.keep_log
        )
        self.px4[vehicle] = px4
        px4.start()
        self.boot_s[vehicle] = px4.wait_ready()
        if vehicle in self.links:
            self._relay(vehicle, px4)
        return self.boot_s[vehicle]

    def _relay(self, vehicle: str, px4: Px4Sitl) -> None:
        """Put the vehicle's slow link between its PX4 and its gateway, before the gateway starts, in a
        process of its own (:mod:`tests.px4.radio`; output in ``radio.<vehicle>.log``): the relay speaks to
        PX4 first, so PX4 (which answers only its first peer) sends everything through it."""
        delay, jitter = self.links[vehicle]
        log = self.logs / f"radio.{vehicle}.log"
        argv = [sys.executable, "-m", "tests.px4.radio", "--gateway-port", str(px4.ports.offboard)]
        argv += ["--px4-port", str(px4.ports.px4_offboard), "--delay", str(delay), "--jitter", str(jitter)]
        self.relays[vehicle] = _spawn([*argv, "--seed", str(px4.ports.instance)], log)
        wait_for(
            lambda: self.relay_counts(vehicle), 10.0, 0.05, f"{vehicle}: the radio relay to speak to PX4"
        )

    def relay_counts(self, vehicle: str) -> dict[str, int]:
        """The vehicle's radio relay's last counts (``forwarded``, ``dropped``, ``send_errors``); empty
        before its first report."""
        lines = (self.logs / f"radio.{vehicle}.log").read_text(errors="replace").splitlines()
        reports = [line for line in lines if line.startswith("{")]
        return dict(json.loads(reports[-1])) if reports else {}

    def stop_px4(self, vehicle: str) -> None:
        """Stop ``vehicle``'s PX4 and keep its working directory (its ULog) until :meth:`close`."""
        self.px4[vehicle].stop(keep=True)

    def ulog(self, vehicle: str) -> Path | None:
        """The newest ULog ``vehicle``'s PX4 wrote (``keep_log``; complete once :meth:`stop_px4` returned)."""
        logs = sorted(self.px4[vehicle].workdir.rglob("*.ulg"), key=lambda p: p.stat().st_mtime)
        return logs[-1] if logs else None

    # -- services -----------------------------------------------------------------------------------------
    def _argv(self, module: str, vehicle: str | None) -> list[str]:
        argv = [sys.executable, "-m", f"services.{module}", "-c", self.cfg.path, "--host", HOST]
        return argv + (["--vehicle", vehicle] if vehicle else [])

    def start(self, module: str, vehicle: str | None = None) -> subprocess.Popen[bytes]:
        """Start (or start again) service ``module`` (``sim_mocap``, ``mavlink_gateway``…) as a process."""
        name = f"{module}.{vehicle}" if vehicle else module
        p = self.procs.get(name) or _Proc(self._argv(module, vehicle), self.logs / f"{name}.log")
        self.procs[name] = p
        if p.proc is not None and p.proc.poll() is None:
            return p.proc
        p.stopped = False
        p.proc = _spawn(p.argv, p.log)
        return p.proc

    def stop(self, name: str, timeout: float = 15.0) -> int | None:
        """Stop process ``name`` (``sim_mocap``, ``mavlink_gateway.d1``…): SIGTERM, then SIGKILL."""
        p = self.procs.get(name)
        if p is None or p.proc is None:
            return None
        p.stopped = True
        if p.proc.poll() is None:
            p.proc.terminate()
            try:
                p.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                p.proc.kill()
                p.proc.wait(5)
        return p.proc.returncode

    def start_all(self) -> None:
        """Every PX4 instance first (they boot in about a second), then the pipeline.  Vehicles the
        arena simulates (``autopilot = "sim"``) fly in one ``sim_vehicle`` process, with no truth bridge."""
        specs = self.cfg.vehicles
        for vehicle, spec in specs.items():
            if spec.px4_sitl:
                self.start_px4(vehicle)
        if any(spec.simulated for spec in specs.values()):
            self.start("sim_vehicle")
        for module in SHARED:
            self.start(module)
        for vehicle, spec in specs.items():
            for module in PER_VEHICLE:
                if module != "px4_truth" or spec.px4_sitl:
                    self.start(module, vehicle)

    def dead(self) -> list[str]:
        """Processes that exited by themselves (a crash, not :meth:`stop`), with their status."""
        return [
            f"{name} (status {p.proc.returncode})"
            for name, p in self.procs.items()
            if p.proc is not None and p.proc.poll() is not None and not p.stopped
        ]

    def tail(self, name: str, n: int = 30) -> str:
        """The last ``n`` lines of a log (``px4.d1``, ``mavlink_gateway.d1``…)."""
        try:
            lines = (self.logs / f"{name}.log").read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def close(self) -> None:
        """Stop the services (gateways first), then PX4; close the logs."""
        for name in reversed(list(self.procs)):
            if self.procs[name].proc is not None and self.procs[name].proc.poll() is None:  # type: ignore[union-attr]
                self.procs[name].proc.terminate()  # type: ignore[union-attr]
        for name in reversed(list(self.procs)):
            self.stop(name)
        for px4 in self.px4.values():
            px4.stop()
        for relay in self.relays.values():
            relay.terminate()
            relay.wait(5)
        for f in self._files:
            f.close()


@contextmanager
def px4_stack(
    cfg: ArenaConfig,
    logs: Path,
    keep_log: bool = False,
    links: Mapping[str, tuple[float, float]] | None = None,
) -> Iterator[Px4Stack]:
    """A started :class:`Px4Stack`; everything stopped at the end, whatever happened."""
    stack = Px4Stack(cfg, logs, keep_log=keep_log, links=links or {})
    try:
        stack.start_all()
        yield stack
    finally:
        stack.close()


# -- PX4's own view, over time ------------------------------------------------------------------------

#: vehicle_status.nav_state of PX4 v1.16 (msg/VehicleStatus.msg).
NAV_STATES = {
    0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
    6: "POSITION_SLOW", 10: "ACRO", 12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD", 15: "STAB",
    17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET", 20: "AUTO_PRECLAND", 21: "ORBIT",
}  # fmt: skip
ARMING_STATES = {1: "disarmed", 2: "armed"}
#: failsafe_flags a test of the tier looks at.
FAILSAFE_FLAGS = ("offboard_control_signal_lost", "local_position_invalid", "local_altitude_invalid")


def timesync_converged(px4: Px4Sitl) -> bool:
    """PX4 stamps vision with the gateway's measurement time, not its arrival: its TIMESYNC filter has
    converged (500 answered requests at 10 Hz, ~50 s: src/lib/timesync/Timesync.hpp)."""
    try:
        odometry = px4.listener("vehicle_visual_odometry")
    except Px4SitlError:
        return False
    arrival, sample = odometry.get("timestamp"), odometry.get("timestamp_sample")
    if not isinstance(arrival, int | float) or not isinstance(sample, int | float):
        return False
    return arrival - sample > 1000


#: PX4's TIMESYNC stream on the gateway's link while the tests wait for its filter, and after (its default).
TIMESYNC_FAST_HZ, TIMESYNC_HZ = 50, 10


def timesync_rate(px4: Px4Sitl, hz: int) -> None:
    """Set PX4's TIMESYNC requests on the gateway's link to ``hz`` (``mavlink stream``, PX4's shell)."""
    port = px4.ports.px4_offboard
    done = px4.tool("mavlink", "stream", "-u", str(port), "-s", "TIMESYNC", "-r", str(hz))
    if done.returncode != 0:
        raise Px4SitlError(f"px4-mavlink stream TIMESYNC -r {hz} on udp {port}: {done.stdout}{done.stderr}")


def wait_timesync_settled(
    px4: Px4Sitl, timeout: float = 150.0, hold: float = 2.0, *, fast: bool = False
) -> None:
    """Wait until PX4's TIMESYNC has converged and its pre-flight checks have passed for ``hold`` s since.

    PX4's filter converges after 500 answered requests, ~50 s at its 10 Hz.  ``fast`` asks for
    :data:`TIMESYNC_FAST_HZ` while waiting (~10 s), then sets 10 Hz back, so that PX4 flies with its default
    rate and, its filter's gains being per sample, the converged filter follows as it does in a lab.  PX4
    then flies ~20 s after its boot instead of ~60 s, and hovers differently (measured in 3 flights: 10.1–12.3 cm
    p50, against 5.1–6.6 cm later): the parity flight, compared with figures flown later, waits at 10 Hz.
    When the filter converges PX4's vision stamps switch from arrival to the gateway's measurement time,
    and its estimate may drop out for a moment then: an arm in that moment is denied ("Resolve system
    health failures first", seen once in a CI run), so a flight starts once PX4 is steady again.
    """
    if fast:
        timesync_rate(px4, TIMESYNC_FAST_HZ)
    try:
        _wait_timesync_settled(px4, timeout, hold)
    finally:
        if fast:
            timesync_rate(px4, TIMESYNC_HZ)


def _wait_timesync_settled(px4: Px4Sitl, timeout: float, hold: float) -> None:
    # Three readings in a row: before convergence PX4 stamps on arrival, yet one sample published more than
    # 1 ms after its arrival (a busy machine) reads as converged — seen once: a flight flown before it.
    in_a_row = 0

    def converged() -> bool:
        nonlocal in_a_row
        in_a_row = in_a_row + 1 if timesync_converged(px4) else 0
        return in_a_row >= 3

    wait_for(converged, timeout, 1.0, "PX4's TIMESYNC to converge")
    since: list[float] = []

    def steady() -> bool:
        if not is_true(px4.listener("vehicle_status"), "pre_flight_checks_pass"):
            since.clear()
            return False
        if not since:
            since.append(time.monotonic())
        return time.monotonic() - since[0] >= hold

    wait_for(steady, 30.0, 0.25, f"PX4's pre-flight checks to pass for {hold:g} s after TIMESYNC converged")


def nav_state(status: Mapping[str, object]) -> str:
    """vehicle_status.nav_state by name (``"AUTO_LAND"``…)."""
    n = status.get("nav_state")
    return NAV_STATES.get(n, str(n)) if isinstance(n, int) else str(n)


@dataclass(frozen=True)
class Px4View:
    """One reading of PX4's vehicle_status, failsafe_flags and vehicle_land_detected (monotonic ``t``)."""

    t: float
    nav: str
    armed: bool
    failsafe: bool
    landed: bool
    flags: frozenset[str]

    def brief(self) -> str:
        return (
            f"{self.nav} {'armed' if self.armed else 'disarmed'}"
            + (" failsafe" if self.failsafe else "")
            + (" landed" if self.landed else "")
            + (f" [{', '.join(sorted(self.flags))}]" if self.flags else "")
        )


class Px4Watch:
    """Reads PX4's own view (three ``px4-listener`` runs, a few ms each) every ``period`` s in a thread
    and keeps each change, so a test sees states that last less than its own polling (``with
    Px4Watch(px4) as w``).  Not much faster: on two cores, spawning listeners starves the pipeline.
    """

    def __init__(self, px4: Px4Sitl, period: float = 0.2) -> None:
        self.px4 = px4
        self.period = period
        self.changes: list[Px4View] = []
        self.latest: Px4View | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"px4-watch-{px4.instance}", daemon=True)

    def read(self) -> Px4View | None:
        """Read PX4's view now (None while px4 does not answer, e.g. rebooting)."""
        try:
            status = self.px4.listener("vehicle_status")
            flags = self.px4.listener("failsafe_flags")
            land = self.px4.listener("vehicle_land_detected")
        except Px4SitlError:
            return None
        return Px4View(
            time.monotonic(),
            nav_state(status),
            status.get("arming_state") == 2,
            status.get("failsafe") is True,
            land.get("landed") is True,
            frozenset(k for k in FAILSAFE_FLAGS if flags.get(k) is True),
        )

    def _run(self) -> None:
        while not self._stop.is_set():
            view = self.read()
            if view is not None:
                last = self.latest
                self.latest = view
                if last is None or (view.nav, view.armed, view.failsafe, view.landed, view.flags) != (
                    last.nav, last.armed, last.failsafe, last.landed, last.flags
                ):  # fmt: skip
                    self.changes.append(view)
            self._stop.wait(self.period)

    def first(self, predicate: Callable[[Px4View], bool], since: float = -math.inf) -> Px4View | None:
        """The first recorded view since ``since`` (monotonic) for which ``predicate`` holds."""
        return next((v for v in list(self.changes) if v.t >= since and predicate(v)), None)

    def timeline(self, since: float) -> str:
        """The changes since ``since``, as ``+0.00 s AUTO_LOITER armed → …``."""
        return " → ".join(f"+{v.t - since:.2f} s {v.brief()}" for v in list(self.changes) if v.t >= since)

    def __enter__(self) -> Px4Watch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)


# -- estimate versus truth ------------------------------------------------------------------------------


@dataclass
class ErrorFigure:
    """Estimate-versus-truth error over one phase of a flight [m, °]."""

    phase: str
    n: int
    horizontal_p50: float
    horizontal_max: float
    vertical_p50: float
    vertical_max: float
    yaw_max_deg: float
    velocity_p50: float = math.nan  # horizontal velocity error [m/s]
    velocity_max: float = math.nan

    def __str__(self) -> str:
        return (
            f"{self.phase:<8} n={self.n:<5} horizontal p50 {self.horizontal_p50 * 100:5.1f} cm max "
            f"{self.horizontal_max * 100:5.1f} cm · vertical p50 {self.vertical_p50 * 100:5.1f} cm max "
            f"{self.vertical_max * 100:5.1f} cm · yaw max {self.yaw_max_deg:4.1f}° · horizontal velocity "
            f"p50 {self.velocity_p50:4.2f} max {self.velocity_max:4.2f} m/s"
        )


class FlightRecord:
    """Every true pose (``arena/<d>/truth``) and autopilot state (``arena/<d>/state``) of a flight, with
    named phases; compares PX4's estimate with the truth at each state (truth interpolated in time)."""

    def __init__(self, arena: Arena, vehicle: str) -> None:
        self.vehicle = vehicle
        self._truth = arena.bus.subscribe(keys.truth(vehicle), capacity=500_000, ring=False)
        self._state = arena.bus.subscribe(keys.state(vehicle), capacity=500_000, ring=False)
        self.truth: list[wire.Pose] = []
        self.states: list[wire.State] = []
        self.phases: list[tuple[str, int]] = []
        self._closed = False

    def close(self) -> None:
        """Stop listening (what was collected stays): a record of a finished flight costs nothing more."""
        self.collect()
        self._closed = True
        self._truth.close()
        self._state.close()

    def phase(self, name: str) -> None:
        """A phase starts now (it lasts until the next one)."""
        self.phases.append((name, wire.now_ns()))

    def collect(self) -> None:
        """Take what arrived so far (nothing more once closed)."""
        if self._closed:
            return
        self.truth += [i.payload for i in self._truth.channel.drain() if isinstance(i.payload, wire.Pose)]
        self.states += [i.payload for i in self._state.channel.drain() if isinstance(i.payload, wire.State)]

    def latest_truth(self) -> wire.Pose | None:
        """The last true pose received."""
        self.collect()
        return self.truth[-1] if self.truth else None

    def track(self, t0: int, t1: int | None = None) -> list[wire.Pose]:
        """The true poses stamped in [t0, t1) (``wire.now_ns`` times; t1 None: until now)."""
        self.collect()
        return [p for p in self.truth if p.t >= t0 and (t1 is None or p.t < t1)]

    def _pairs(self, t0: int, t1: int, lag_ns: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(estimate positions, true positions, yaw errors [rad]) of the states stamped in [t0, t1)."""
        tt = np.array([p.t for p in self.truth], dtype=np.int64)
        tp = np.array([p.p for p in self.truth])
        ty = np.unwrap([quat_yaw(p.q) for p in self.truth])
        states = [
            s for s in self.states if t0 <= s.t < t1 and s.p is not None and tt[0] <= s.t - lag_ns <= tt[-1]
        ]
        if not states:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        ts = np.array([s.t - lag_ns for s in states], dtype=np.int64)
        truth = np.stack([np.interp(ts, tt, tp[:, k]) for k in range(3)], axis=1)
        est = np.array([s.p for s in states])
        yaw_err = np.array(
            [
                wrap_angle(quat_yaw(s.q) - y) if s.q is not None else 0.0
                for s, y in zip(states, np.interp(ts, tt, ty), strict=True)
            ]
        )
        return est, truth, yaw_err

    def figure(self, phase: str) -> ErrorFigure:
        """The error figure of one phase (by name)."""
        self.collect()
        names = [n for n, _ in self.phases]
        i = names.index(phase)
        t0 = self.phases[i][1]
        t1 = self.phases[i + 1][1] if i + 1 < len(self.phases) else wire.now_ns()
        est, truth, yaw = self._pairs(t0, t1)
        if len(est) == 0:
            return ErrorFigure(phase, 0, math.nan, math.nan, math.nan, math.nan, math.nan)
        h = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
        v = np.abs(est[:, 2] - truth[:, 2])
        dv = self._velocity_errors(t0, t1)
        return ErrorFigure(
            phase, len(h), float(np.median(h)), float(h.max()), float(np.median(v)), float(v.max()),
            float(np.degrees(np.abs(yaw).max())),
            float(np.median(dv)) if len(dv) else math.nan, float(dv.max()) if len(dv) else math.nan,
        )  # fmt: skip

    def _velocity_errors(self, t0: int, t1: int) -> np.ndarray:
        """|horizontal velocity estimate - true velocity| [m/s] of the states stamped in [t0, t1)."""
        tt = np.array([p.t for p in self.truth], dtype=np.int64)
        states = [s for s in self.states if t0 <= s.t < t1 and s.v is not None and tt[0] <= s.t <= tt[-1]]
        if not states:
            return np.zeros(0)
        ts = np.array([s.t for s in states], dtype=np.int64)
        tv = np.array([p.v for p in self.truth])
        true_v = np.stack([np.interp(ts, tt, tv[:, k]) for k in range(2)], axis=1)
        est_v = np.array([s.v[:2] for s in states if s.v is not None])
        return np.asarray(np.hypot(*(est_v - true_v).T))

    def lag(self, max_ms: int = 600, step_ms: int = 10) -> tuple[float, float]:
        """(lag [s], mean 3-D error at that lag [m]): how far PX4's estimate trails the truth, the shift
        that best explains it, over the whole record."""
        self.collect()
        t0, t1 = self.phases[0][1], wire.now_ns()
        best = (0.0, math.inf)
        for ms in range(0, max_ms + 1, step_ms):
            est, truth, _ = self._pairs(t0, t1, ms * 1_000_000)
            if len(est):
                err = float(np.mean(np.linalg.norm(est - truth, axis=1)))
                if err < best[1]:
                    best = (ms / 1000.0, err)
        return best

    def excursion(self, phase: str, target: Sequence[float]) -> tuple[float, float]:
        """(median, max) distance [m] of the true position from ``target`` during ``phase``."""
        self.collect()
        names = [n for n, _ in self.phases]
        i = names.index(phase)
        t0 = self.phases[i][1]
        t1 = self.phases[i + 1][1] if i + 1 < len(self.phases) else wire.now_ns()
        d = [math.dist(p.p, target) for p in self.truth if t0 <= p.t < t1]
        return (float(np.median(d)), max(d)) if d else (math.nan, math.nan)
