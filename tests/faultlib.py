"""Run the simulated arena with private ports, break it, and measure what the vehicles live through.

The pieces (every port private to the caller, every address 127.0.0.1):

- :func:`write_arena_config` — a config whose router, NatNet and MAVLink ports are all free ones;
- :class:`World` — the simulated vehicles *in this process* (:class:`TapAutopilot`, the real simulated
  PX4 with a tap on its input) publishing their true poses like ``services.sim_vehicle``, so a test sees
  what reaches each autopilot (every ODOMETRY, SET_POSITION_TARGET_LOCAL_NED and COMMAND_LONG, checked)
  and how it flies, whatever happens to the arena's processes; :meth:`World.occlude` hides a body from
  the Motive emulator the way Motive streams an occluded body (tracking bit clear);
- :class:`ArenaUp` — ``arena up`` (the supervisor) as a :class:`~tests.conftest.Proc` (a child
  process started the library's way, output in a log file) whose children's pids are read from its output;
- :class:`Watch` — what the bus says: states, events, stats of every service;
- :class:`LossyLink` — a UDP relay that drops and delays datagrams, a bad radio link in user space;
- :func:`record` — collected figures, written to ``bench-results/faults.json`` and printed.
"""

from __future__ import annotations

import heapq
import itertools
import json
import math
import os
import random
import re
import select
import signal
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, ArenaSpec, ZenohSpec
from arena_common.mavlink import px4
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot, SimClock, TruePose
from tests.helpers import PYTHON, REPO, Proc, free_port, wait_for

RESULTS_DIR = REPO / "bench-results"
ARENA_PARAMS: dict[str, Any] = {name: value for name, (value, _) in px4.ARENA_REQUIRED_PARAMS.items()}
WATCHED = ("ODOMETRY", "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG")


# -- configuration -------------------------------------------------------------------------------------------


def grid_start(index: int, n: int) -> tuple[float, float]:
    """A start position on a grid inside the default 7 × 4 m arena, 0.5 m apart, for vehicle ``index``."""
    cols = max(1, min(n, 11))
    row, col = divmod(index, cols)
    return (-2.5 + 0.5 * col, -1.5 + 0.5 * row)


def write_arena_config(
    directory: Path,
    *,
    vehicles: int = 1,
    services: Sequence[str] = ("router", "mocap", "transform"),
    vehicle_services: Sequence[str] = ("downsampler", "gateway"),
    speed: float = 1.0,
    mocap_rate: float = 180.0,
    noise_m: float = 0.0002,
    lease_ms: int | None = None,
    recorder: str = "",
    sim_links: dict[str, str] | None = None,
    gateway_ports: dict[str, int] | None = None,
    endpoint: str | None = None,
    multicast: bool = True,
    name: str = "arena.toml",
    decimate: str = "downsampler",
    vehicle_mode: str = "",
    fidelity: str = "ideal",
) -> Path:
    """Write a one-host (``test``) config with free ports; return its path.

    ``sim_links`` maps a vehicle to the MAVLink connection its simulated autopilot uses (e.g. through a
    :class:`LossyLink`) instead of the mirror of its gateway's, ``gateway_ports`` to the UDP port its
    gateway listens on (else a free one); ``recorder`` is the body of a ``[recorder]`` table;
    ``endpoint`` is the router's (else a free port); ``multicast`` false streams NatNet by unicast (a
    fresh network namespace has no multicast route); ``decimate`` is ``[pipeline] decimate`` (with
    ``transform``, no host runs downsamplers); ``vehicle_mode`` is ``[zenoh] vehicle_mode`` (else the
    default); ``fidelity`` is ``[sim] fidelity``: "ideal" by default, since these tests judge the arena's
    safety logic with bounds an exact vehicle meets (PX4's wander: tests/unit/sim/test_sim_px4_parity.py).
    Without the ``mocap`` service nothing answers the clock check, so ``clock.require`` is then
    false.
    """
    if decimate == "transform":
        vehicle_services = [s for s in vehicle_services if s != "downsampler"]
    endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
    lines = [
        "[arena]",
        'name = "faults"',
        "[mocap]",
        f"command_port = {free_port(socket.SOCK_DGRAM)}",
        f"data_port = {free_port(socket.SOCK_DGRAM)}",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        f"multicast = {'true' if multicast else 'false'}",
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["{endpoint}"]',
        f'router_listen = ["{endpoint}"]',
    ]
    if lease_ms is not None:
        lines.append(f"lease_ms = {lease_ms}")
    if vehicle_mode:
        lines.append(f'vehicle_mode = "{vehicle_mode}"')
    if "mocap" not in services:  # the test feeds vision itself: no ingest, no time reference on the bus
        lines += ["[clock]", "require = false"]
    names = [f"d{i + 1}" for i in range(vehicles)]
    lines += [
        "[hosts.test]",
        "services = [" + ", ".join(f'"{s}"' for s in services) + "]",
        "vehicles = [" + ", ".join(f'"{n}"' for n in names) + "]",
        "vehicle_services = [" + ", ".join(f'"{s}"' for s in vehicle_services) + "]",
    ]
    for i, n in enumerate(names):
        north, east = grid_start(i, vehicles)
        sim = f"start = [{north}, {east}]"
        if sim_links and n in sim_links:
            sim += f', mavlink = "{sim_links[n]}"'
        lines += [
            f"[vehicles.{n}]",
            f'rigid_body = "{n}"',
            f'mavlink = "udpin:127.0.0.1:{(gateway_ports or {}).get(n) or free_port(socket.SOCK_DGRAM)}"',
            f"system_id = {i + 1}",
            f"sim = {{ {sim} }}",
        ]
    lines += ["[sim]", f"speed = {speed}", f"mocap_rate = {mocap_rate}", f"noise_m = {noise_m}"]
    lines.append(f'fidelity = "{fidelity}"')
    lines += ["[pipeline]", f'decimate = "{decimate}"']
    if recorder:
        lines += ["[recorder]", recorder]
    path = directory / name
    path.write_text("\n".join(lines) + "\n")
    return path


def peer_bus(cfg: ArenaConfig) -> Bus:
    """A peer session on the config's router (what a user program on this host opens)."""
    return open_bus(cfg.zenoh)


def router(endpoint: str) -> Bus:
    """A Zenoh router in this process listening on ``endpoint`` (close it to stop)."""
    return open_bus(
        ZenohSpec(mode="router", connect=(), router_listen=(endpoint,)),
        BusOptions(settings={"connect/endpoints": []}),
    )


def client_bus(cfg: ArenaConfig) -> Bus:
    """A client session: reaches the arena through the router only (a laptop's user program)."""
    return open_bus(ZenohSpec(mode="client", connect=cfg.zenoh.connect))


# -- the simulated vehicles, tapped --------------------------------------------------------------------------


@dataclass
class Arrival:
    """One watched message as it reached the simulated autopilot."""

    mono: float  # time.monotonic() at arrival
    name: str
    problem: str  # empty when the message is one a vehicle may be sent
    age: float = math.nan  # ODOMETRY: arrival minus its time_usec on the clock it is on, s
    p: tuple[float, float, float] | None = None  # ODOMETRY position, SET_POSITION_TARGET position


@dataclass
class Tap:
    """What reached one simulated autopilot."""

    counts: Counter[str] = field(default_factory=Counter)
    arrivals: deque[Arrival] = field(default_factory=lambda: deque(maxlen=200_000))
    invalid: list[tuple[str, str]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def times(self, name: str, after: float = -math.inf, before: float = math.inf) -> list[float]:
        """Arrival times of ``name`` messages within ``(after, before]``."""
        with self.lock:
            return [a.mono for a in self.arrivals if a.name == name and after < a.mono <= before]

    def count(self, name: str) -> int:
        with self.lock:
            return self.counts[name]

    def positions(self, name: str, after: float = -math.inf) -> list[tuple[float, float, float]]:
        """Positions carried by the ``name`` messages that arrived after ``after``."""
        with self.lock:
            return [a.p for a in self.arrivals if a.name == name and a.mono > after and a.p is not None]

    def ages(self, after: float = -math.inf, before: float = math.inf) -> list[float]:
        """Age (s) of each ODOMETRY at arrival within ``(after, before]``: measurement to autopilot."""
        with self.lock:
            return [a.age for a in self.arrivals if a.name == "ODOMETRY" and after < a.mono <= before]


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


WALL_EPOCH_US = 10**15  # 2001 in µs since 1970: a stamp below is on a boot clock (31 years of uptime)

#: Commands that only ask the autopilot for messages (the gateway's own: origin, estimator status).
DATA_REQUESTS = frozenset({px4.MAV_CMD_SET_MESSAGE_INTERVAL, px4.MAV_CMD_REQUEST_MESSAGE})


class TapAutopilot(SimAutopilot):
    """The simulated PX4, recording and checking every ODOMETRY, setpoint and COMMAND_LONG it receives.

    A received message is *invalid* when a vehicle must never be sent it: non-finite or absurd vision
    (beyond 1 km, a quaternion not of unit norm, a time stamp in the future), a setpoint outside the
    arena's safe volume or above its speed limits, a command for another system.
    """

    def __init__(self, *args: Any, arena: ArenaSpec | None = None, **kwargs: Any) -> None:
        self.tap = Tap()
        self.arena_spec = arena or ArenaSpec()
        super().__init__(*args, **kwargs)

    def _recv(self) -> Any:
        msg = super()._recv()
        if msg is not None:
            name = msg.get_type()
            if name in WATCHED:
                problem = self._judge(name, msg)
                if name == "COMMAND_LONG" and msg.command in DATA_REQUESTS:
                    name = "COMMAND_LONG (data request)"  # the gateway asking for messages, not acting
                age = self.stamp_age(msg.time_usec) if name == "ODOMETRY" else math.nan
                p = (msg.x, msg.y, msg.z) if hasattr(msg, "x") else None
                with self.tap.lock:
                    self.tap.counts[name] += 1
                    self.tap.arrivals.append(Arrival(time.monotonic(), name, problem, age, p))
                    if problem:
                        self.tap.invalid.append((name, problem))
        return msg

    def stamp_age(self, time_usec: int) -> float:
        """How old a vision stamp is now (s), on the clock it is on: the autopilot's boot clock once the
        gateway knows it (its TIMESYNC answers and its stamps follow it), this host's wall clock before
        (µs since 1970: a stamp that large is no boot clock's)."""
        if time_usec >= WALL_EPOCH_US:
            return time.time() - time_usec * 1e-6
        return self.sim.time - time_usec * 1e-6

    def _judge(self, name: str, msg: Any) -> str:
        if name == "ODOMETRY":
            if not _finite(msg.x, msg.y, msg.z) or max(abs(msg.x), abs(msg.y), abs(msg.z)) > 1000.0:
                return f"position {(msg.x, msg.y, msg.z)}"
            q = [float(c) for c in msg.q]
            if not _finite(*q) or abs(math.sqrt(sum(c * c for c in q)) - 1.0) > 1e-3:
                return f"quaternion {q}"
            if self.stamp_age(msg.time_usec) < -0.2:
                return f"time stamp {msg.time_usec} µs is in the future"
            return ""
        if name == "SET_POSITION_TARGET_LOCAL_NED":
            m = msg.type_mask
            if msg.target_system != self.system_id:
                return f"setpoint for system {msg.target_system}"
            if not m & px4.TYPEMASK_POSITION:
                p = (msg.x, msg.y, msg.z)
                box = self.arena_spec.safe_box()
                if not _finite(*p) or not all(box[i][0] - 1e-6 <= p[i] <= box[i][1] + 1e-6 for i in range(3)):
                    return f"position setpoint {p} outside the safe volume"
            if not m & px4.TYPEMASK_VELOCITY:
                v = (msg.vx, msg.vy, msg.vz)
                if not _finite(*v) or math.hypot(v[0], v[1]) > self.arena_spec.max_speed + 1e-6:
                    return f"velocity setpoint {v}"
                if abs(v[2]) > self.arena_spec.max_climb + 1e-6:
                    return f"velocity setpoint {v}"
            if not _finite(msg.yaw, msg.yaw_rate):
                return "yaw not finite"
            return ""
        if msg.target_system != self.system_id:
            return f"command {msg.command} for system {msg.target_system}"
        return ""


def truth_pose(pose: TruePose, ok: bool = True) -> wire.Pose:
    """A true pose as ``services.sim_vehicle`` publishes it."""
    return wire.Pose(
        t=pose.time_ns,
        p=pose.position,
        q=pose.q,
        ok=ok,
        v=pose.velocity,
        w=pose.rates,
        vok=ok,
        tp=wire.now_ns(),
    )


@dataclass(frozen=True, slots=True)
class Sample:
    """How one vehicle flew at one instant (sampled every 5 ms by :class:`World`)."""

    mono: float
    mode: str
    armed: bool
    z: float  # true down position, m (0 on the floor)
    fusing: bool  # the autopilot's estimator uses vision


class World:
    """The configured vehicles as tapped simulated PX4s in this process, their true poses on the bus.

    ``truth_rate`` (Hz of simulated time) is how often each true pose is published, as
    ``services.sim_vehicle --truth-rate`` does (0: never).  The autopilots start with the arena's
    parameters set.  A monitor thread keeps a :class:`Sample` of each vehicle every 5 ms, so
    :meth:`when` tells when something first happened, whatever the test was doing meanwhile.
    """

    def __init__(
        self,
        cfg: ArenaConfig,
        bus: Bus,
        *,
        names: Iterable[str] | None = None,
        truth_rate: float = 250.0,
        params: dict[str, Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.clock = SimClock(cfg.sim.speed)
        self.aps: dict[str, TapAutopilot] = {}
        self._hidden: dict[str, float] = {}
        self._period_ns = int(1e9 / truth_rate) if truth_rate > 0 else 0
        try:
            for index, name in enumerate(names if names is not None else cfg.vehicles):
                v = cfg.vehicle(name)
                ap = TapAutopilot(
                    v.sim_mavlink(),
                    v.system_id,
                    arena=cfg.arena,
                    clock=self.clock,
                    name=name,
                    position=(v.sim.start[0], v.sim.start[1], 0.0),
                    params=ARENA_PARAMS if params is None else params,
                    seed=index,
                    ideal=cfg.sim.fidelity == "ideal",
                )
                if truth_rate > 0:
                    ap.on_tick = self._publisher(name, bus.stream_publisher(keys.truth(name), wire.Pose))
                self.aps[name] = ap
        except BaseException:
            for ap in self.aps.values():
                ap.close()
            raise
        self.history: dict[str, deque[Sample]] = {n: deque(maxlen=400_000) for n in self.aps}
        self._stop = threading.Event()
        self.loop = AutopilotLoop(self.aps.values()).start()
        self._monitor = threading.Thread(target=self._sample, name="world-monitor", daemon=True)
        self._monitor.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.005):
            now = time.monotonic()
            for name, ap in self.aps.items():
                z = ap.true_pose().position[2]
                self.history[name].append(
                    Sample(now, ap.mode_name, ap.armed, z, ap.sim.estimator.vision_fusing)
                )

    def when(
        self, name: str, predicate: Callable[[Sample], bool], after: float, timeout: float, what: str
    ) -> float:
        """The first sampled time after ``after`` at which ``predicate`` held (waiting up to ``timeout``)."""

        def found() -> float | None:
            return next((s.mono for s in list(self.history[name]) if s.mono > after and predicate(s)), None)

        result: float = wait_for(found, timeout, 0.02, what=f"{name}: {what}")
        return result

    def _publisher(self, name: str, pub: Any) -> Callable[[TruePose], None]:
        next_due = 0

        def on_tick(pose: TruePose) -> None:
            nonlocal next_due
            if pose.time_ns >= next_due:
                next_due = max(next_due + self._period_ns, pose.time_ns + self._period_ns // 2)
                hidden = time.monotonic() < self._hidden.get(name, -math.inf)
                pub.put(truth_pose(pose, ok=not hidden))

        return on_tick

    def occlude(self, name: str, seconds: float) -> float:
        """Hide ``name`` from the cameras for ``seconds`` (from now); returns the monotonic end time.

        The emulator then streams the body untracked, as Motive does for a body its cameras lose.
        """
        end = time.monotonic() + seconds
        self._hidden[name] = end
        return end

    def close(self) -> None:
        """Stop the loop and close every link."""
        self._stop.set()
        self._monitor.join(2.0)
        try:
            self.loop.stop()
        finally:
            for ap in self.aps.values():
                ap.close()


# -- processes -----------------------------------------------------------------------------------------------


def alive(pid: int) -> bool:
    """Whether ``pid`` is a running (not zombie) process."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def rss_bytes(pid: int) -> int:
    """Resident memory of ``pid`` (0 when gone)."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


_STARTED = re.compile(r"^\[arena\] (?:re)?started (\S+) \(pid (\d+)")


class ArenaUp(Proc):
    """``arena up CONFIG --host test``: the supervisor; :attr:`pids` holds each child's latest pid."""

    def __init__(self, cfg_path: Path, log_dir: Path, grace: float = 3.0) -> None:
        self.pids: dict[str, int] = {}
        self.started_at: dict[str, float] = {}  # monotonic time each child was last (re)started
        self.every_pid: set[int] = set()
        argv = [
            PYTHON,
            "-m",
            "arena_common.cli",
            "up",
            str(cfg_path),
            "--host",
            "test",
            "--grace",
            str(grace),
        ]
        super().__init__("arena-up", argv, log_dir, env={"NO_COLOR": "1"})

    def on_line(self, line: str) -> None:
        m = _STARTED.match(line)
        if m:
            self.started_at[m[1]] = time.monotonic()
            self.pids[m[1]] = int(m[2])
            self.every_pid.add(int(m[2]))

    def wait_started(self, names: Iterable[str], timeout: float = 60.0) -> dict[str, int]:
        want = set(names)
        wait_for(lambda: want <= set(self.pids), timeout, 0.05, what=f"children {sorted(want)} started")
        return {n: self.pids[n] for n in want}

    def kill_child(self, name: str, sig: int = signal.SIGKILL) -> int:
        """Signal one child by its latest pid; returns that pid."""
        pid = self.pids[name]
        os.kill(pid, sig)
        return pid

    def wait_restarted(self, name: str, old_pid: int, timeout: float = 30.0) -> tuple[int, float]:
        """Wait for the supervisor to restart ``name``: its new pid and when it was started."""
        wait_for(lambda: self.pids.get(name, old_pid) != old_pid, timeout, 0.02, what=f"{name} restarted")
        return self.pids[name], self.started_at[name]

    def stop(self, timeout: float = 25.0, sig: int = signal.SIGINT) -> int | None:
        """Stop the supervisor (``sig``, SIGKILL after ``timeout``), then any child it left behind."""
        code = super().stop(timeout, sig)
        for pid in self.every_pid:  # children die with the supervisor; make sure of it
            if alive(pid):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        return code


# -- services in threads -------------------------------------------------------------------------------------


class ServiceThread:
    """A service's real ``main`` run in a thread of this process until :meth:`stop` (its ``stop`` event)."""

    def __init__(self, name: str, main: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        self.name = name
        self.stop_event = threading.Event()
        self.error: BaseException | None = None

        def run() -> None:
            try:
                main(*args, stop=self.stop_event, **kwargs)
            except BaseException as exc:  # reported by the test: a service must not die
                self.error = exc

        self.thread = threading.Thread(target=run, name=f"service:{name}", daemon=True)
        self.thread.start()

    @property
    def alive(self) -> bool:
        return self.thread.is_alive()

    def stop(self, timeout: float = 10.0) -> None:
        self.stop_event.set()
        self.thread.join(timeout)


class ThreadDeaths:
    """Every thread of this process that dies of an uncaught exception while installed (an excepthook)."""

    def __init__(self) -> None:
        self.deaths: list[tuple[str, str]] = []
        self._previous: Any = None

    def _hook(self, args: Any) -> None:
        name = args.thread.name if args.thread is not None else "?"
        self.deaths.append((name, f"{args.exc_type.__name__}: {args.exc_value}"))

    def install(self) -> ThreadDeaths:
        self._previous = threading.excepthook
        threading.excepthook = self._hook
        return self

    def uninstall(self) -> None:
        if self._previous is not None:
            threading.excepthook = self._previous

    def since(self, n: int) -> list[tuple[str, str]]:
        """Deaths after the first ``n``."""
        return self.deaths[n:]


# -- observing the bus ---------------------------------------------------------------------------------------


class Watch:
    """States, events and stats as the bus carries them, drained by a background thread.

    With ``history``, every Stats received is kept in :attr:`stats_history` (service → [(time, Stats)]).
    """

    def __init__(self, bus: Bus, history: bool = False) -> None:
        self.bus = bus
        self.keep_history = history
        self.stats_history: dict[str, list[tuple[float, wire.Stats]]] = {}
        self.states: dict[str, wire.State] = {}
        self.state_times: dict[str, deque[float]] = {}
        self.events: list[tuple[float, str, wire.Event]] = []
        self.stats: dict[str, wire.Stats] = {}
        self.stats_times: dict[str, float] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._states = bus.subscribe("arena/*/state", capacity=1024, ring=True)
        self._events = bus.subscribe("arena/*/events", capacity=10_000, ring=False)
        self._stats = bus.subscribe(keys.STATS_ALL, capacity=4096, ring=True)
        self._thread = threading.Thread(target=self._run, name="watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            now = time.monotonic()
            with self._lock:
                for item in self._states.channel.drain():
                    if isinstance(item.payload, wire.State):
                        name = item.key.split("/")[1]
                        self.states[name] = item.payload
                        self.state_times.setdefault(name, deque(maxlen=100_000)).append(now)
                for item in self._events.channel.drain():
                    if isinstance(item.payload, wire.Event):
                        self.events.append((now, item.key.split("/")[1], item.payload))
                for item in self._stats.channel.drain():
                    if isinstance(item.payload, wire.Stats):
                        self.stats[item.payload.service] = item.payload
                        self.stats_times[item.payload.service] = now
                        if self.keep_history:
                            self.stats_history.setdefault(item.payload.service, []).append(
                                (now, item.payload)
                            )

    def state(self, name: str) -> wire.State | None:
        with self._lock:
            return self.states.get(name)

    def stat(self, service: str) -> wire.Stats | None:
        with self._lock:
            return self.stats.get(service)

    def all_stats(self) -> dict[str, wire.Stats]:
        with self._lock:
            return dict(self.stats)

    def history(self, service: str, after: float = -math.inf, before: float = math.inf) -> list[wire.Stats]:
        """The stats of ``service`` received within ``(after, before]`` (needs ``history=True``)."""
        with self._lock:
            return [s for t, s in self.stats_history.get(service, []) if after < t <= before]

    def fresh_stat(self, service: str, after: float) -> wire.Stats | None:
        """The latest stats of ``service`` received after monotonic time ``after``."""
        with self._lock:
            return self.stats.get(service) if self.stats_times.get(service, -math.inf) > after else None

    def event_texts(self, name: str, after: float = -math.inf) -> list[str]:
        with self._lock:
            return [e.text for t, n, e in self.events if n == name and t > after]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


# -- measuring -----------------------------------------------------------------------------------------------


def max_gap(times: Sequence[float], start: float, end: float) -> float:
    """The longest interval without an arrival within ``[start, end]`` (the edges count).

    ``times`` may be a deque another thread appends to: it is copied first (``tuple`` copies it in one step
    under the GIL; iterating it directly can fail with "deque mutated during iteration").
    """
    points = [start, *[t for t in tuple(times) if start < t < end], end]
    return max(b - a for a, b in itertools.pairwise(points))


def first_after(times: Sequence[float], t0: float) -> float | None:
    """The first time after ``t0``, or None (``times`` is copied first, as in :func:`max_gap`)."""
    return next((t for t in tuple(times) if t > t0), None)


def wait_time(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.01) -> float:
    """Wait for ``predicate`` (bounded); the monotonic time it first held."""
    wait_for(predicate, timeout, interval, what=what)
    return time.monotonic()


def rate_between(times: Sequence[float], start: float, end: float) -> float:
    """Arrivals per second within ``[start, end]``."""
    n = sum(1 for t in times if start <= t <= end)
    return n / max(end - start, 1e-9)


_RESULTS: dict[str, dict[str, Any]] = {}


def record(name: str, file: str = "faults.json", **figures: Any) -> dict[str, Any]:
    """Keep one fault's measured figures, print them and (re)write ``bench-results/<file>``."""
    rounded = {k: round(v, 3) if isinstance(v, float) else v for k, v in figures.items()}
    _RESULTS[name] = rounded
    print(f"\n[{name}] " + ", ".join(f"{k}={v}" for k, v in rounded.items()))
    try:
        RESULTS_DIR.mkdir(exist_ok=True)
        path = RESULTS_DIR / file
        old: dict[str, Any] = {}
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except ValueError:
                old = {}
        old[name] = rounded
        path.write_text(json.dumps(old, indent=2, sort_keys=True) + "\n")
    except OSError:
        pass  # a read-only tree: the printed figures are enough
    return rounded


# -- a bad radio link ----------------------------------------------------------------------------------------


class LossyLink:
    """A UDP relay between a simulated autopilot and its gateway that drops and delays datagrams.

    The autopilot sends to ``listen_port`` (``udpout:127.0.0.1:<listen_port>``); the relay forwards to the
    gateway's ``udpin`` port from its own socket, and the gateway's answers back to the autopilot.  Each
    datagram is dropped with probability ``loss`` or delivered after ``delay`` ± ``jitter`` seconds (in
    order per direction).  Settings can change while it runs.
    """

    def __init__(
        self, gateway_port: int, *, loss: float = 0.0, delay: float = 0.0, jitter: float = 0.0
    ) -> None:
        self.loss, self.delay, self.jitter = loss, delay, jitter
        self.gateway = ("127.0.0.1", gateway_port)
        self.vehicle: tuple[str, int] | None = None
        self.outer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.outer.bind(("127.0.0.1", 0))
        self.inner = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.inner.bind(("127.0.0.1", 0))
        self.listen_port = int(self.outer.getsockname()[1])
        self.passed = Counter[str]()
        self.dropped = Counter[str]()
        self._queue: list[tuple[float, int, socket.socket, bytes, tuple[str, int]]] = []
        self._seq = 0
        self._last_due = {"up": 0.0, "down": 0.0}
        self._rng = random.Random(7)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lossy-link", daemon=True)
        self._thread.start()

    def set(
        self, *, loss: float | None = None, delay: float | None = None, jitter: float | None = None
    ) -> None:
        if loss is not None:
            self.loss = loss
        if delay is not None:
            self.delay = delay
        if jitter is not None:
            self.jitter = jitter

    def _enqueue(self, direction: str, sock: socket.socket, data: bytes, to: tuple[str, int]) -> None:
        if self.loss > 0 and self._rng.random() < self.loss:
            self.dropped[direction] += 1
            return
        due = time.monotonic() + max(0.0, self.delay + self._rng.uniform(-self.jitter, self.jitter))
        due = max(due, self._last_due[direction])  # a radio does not reorder
        self._last_due[direction] = due
        self._seq += 1
        heapq.heappush(self._queue, (due, self._seq, sock, data, to))
        self.passed[direction] += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.monotonic()
            while self._queue and self._queue[0][0] <= now:
                _, _, sock, data, to = heapq.heappop(self._queue)
                try:
                    sock.sendto(data, to)
                except OSError:
                    pass
            timeout = 0.01 if not self._queue else max(0.0, min(0.01, self._queue[0][0] - now))
            try:
                ready, _, _ = select.select([self.outer, self.inner], [], [], timeout)
            except (OSError, ValueError):
                return
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    continue
                if sock is self.outer:
                    self.vehicle = addr
                    self._enqueue("up", self.inner, data, self.gateway)
                elif self.vehicle is not None:
                    self._enqueue("down", self.outer, data, self.vehicle)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.outer.close()
        self.inner.close()
