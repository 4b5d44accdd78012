"""End-to-end runs of ``make bench``: the real vision pipeline, and its floors, as processes on loopback.

**Arena.** A private Zenoh router, the Motive emulator (``services.sim_mocap``), the ingest, the frame
transform, one downsampler and one gateway per vehicle, each a process with the config this module writes
(multicast NatNet on 127.0.0.1, no noise, vision rate 400 Hz so that the downsampler drops nothing by
design at 180 or 360 Hz, every gateway sending MAVLink to a UDP port of the harness).  The harness
publishes each vehicle's true pose (a circle, 60 Hz), joins the NatNet multicast group itself and reads
every vehicle's MAVLink socket, all with kernel receive stamps (:mod:`bench.harness`).

How each ODOMETRY is matched to its frame, and what is lost: :mod:`bench.matching`.

**Floors.** The same topology with :mod:`bench.floor` processes that only move bytes (of the
arena payloads' sizes), over Zenoh with the arena's settings, or over UDP; messages carry their frame
number, so matching is exact.  They run from :mod:`bench.floor_run` with this module's helpers.

Every point also says how many poses per second each vehicle received over its window (the least, the
median and the most: :func:`vision_rates`).
"""

from __future__ import annotations

import math
import os
import random
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena_common.bus.session import Bus, open_bus
from arena_common.core.config import ArenaConfig
from arena_common.mocap import natnet
from arena_common.runtime.options import read_config as load_config
from bench.feeds import StatsWatcher, TruthFeeder
from bench.harness import (
    Child,
    Collector,
    ProcessSet,
    free_port,
    latency_stats,
    python_module,
    stamped_socket,
    wait_port,
    wait_until,
)
from bench.matching import (
    NATNET_VERSION,
    VISION_RATE,
    HopWatcher,
    analyze_arena,
    decode_frames,
    hop_breakdown,
    odometry_of,
)

__all__ = [
    "CHAINS",
    "PointResult",
    "RunSettings",
    "run_arena",
    "vision_rates",
    "write_config",
]

# The arena's chains, by where the vision is decimated ([pipeline] decimate).
CHAINS = {"downsampler": "arena", "transform": "arena-td"}
HOST = "bench"
FLOOR_PREFIX = "bench/floor"


@dataclass(frozen=True)
class RunSettings:
    """How long each load point runs, and where logs go."""

    duration: float = 3.0  # s measured
    warmup: float = 1.0  # s of flow before the measurement starts
    drain: float = 0.3  # s after the window for late messages to arrive
    start_timeout: float = 90.0  # s for the processes to come up and data to flow
    idle: float = 1.0  # s of idle CPU measured before the stream starts (0: skip)
    settle: float = 0.5  # s after every service came up before the idle window opens
    logs: Path = Path("bench-results/logs")
    repo: Path = Path(".")
    profile: Callable[[ProcessSet, float], dict[str, Any]] | None = None  # run during the window
    hops: bool = False  # also subscribe to the first vehicle's mocap/pose/vision for a per-stage breakdown
    vehicle_mode: str = ""  # the config's zenoh.vehicle_mode ("": its default)
    # Processes the gateways run in: 0, one per vehicle (as deployed); K, the vehicles split over K
    # processes of bench.gateway_host (the per-host design of issue #35, measured)
    gateway_hosts: int = 0
    gateway_vision: str = "frame"  # their vision: one message per mocap frame, or each vehicle's own key


@dataclass
class PointResult:
    """One load point of one chain (arena, floor-zenoh, floor-udp)."""

    chain: str
    vehicles: int
    rate: float
    latency: dict[str, float]
    expected: int
    delivered: int
    lost: int
    designed_drops: int = 0
    mismatched: int = 0
    duplicates: int = 0
    per_service: dict[str, dict[str, Any]] = field(default_factory=dict)
    idle: dict[str, dict[str, Any]] = field(default_factory=dict)
    counters: dict[str, dict[str, int]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    profile: dict[str, Any] = field(default_factory=dict)
    hops: dict[str, dict[str, float]] = field(default_factory=dict)
    load: float = math.nan  # the machine's 1-minute load average at the end of the measurement
    # Poses per second each vehicle's socket received over the window (frames of the window that arrived):
    # the least, the median and the most over the vehicles.
    vision_rate: dict[str, float] = field(default_factory=dict)
    hogs: int = 0  # CPU hogs run beside the chain during the window (the overload point)
    vehicle_mode: str = ""  # the config's zenoh.vehicle_mode the point ran with ("": its default)
    # s from the first process started to every service alive ("services"), and from the emulator's start
    # to ODOMETRY from every gateway ("vision"); the first point of a process set only
    startup: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# -- configuration -------------------------------------------------------------------------------------------


def _group() -> str:
    return f"239.255.{random.randint(1, 254)}.{random.randint(1, 254)}"


def write_config(
    directory: Path,
    n_vehicles: int,
    rate: float,
    harness_ports: Sequence[int],
    *,
    decimate: str = "downsampler",
    vehicle_mode: str = "",
) -> Path:
    """An arena config with private ports: multicast NatNet, no noise, gateways sending to the harness.

    ``decimate`` is the config's ``[pipeline] decimate``, ``vehicle_mode`` its ``zenoh.vehicle_mode``.
    """
    directory.mkdir(parents=True, exist_ok=True)
    router = free_port(socket_kind_tcp())
    lines = [
        "[arena]",
        'name = "bench"',
        "[mocap]",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        "multicast = true",
        f'group = "{_group()}"',
        f"command_port = {free_port()}",
        f"data_port = {free_port()}",
        'up_axis = "y"',
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["tcp/127.0.0.1:{router}"]',
        f'router_listen = ["tcp/127.0.0.1:{router}"]',
        *([f'vehicle_mode = "{vehicle_mode}"'] if vehicle_mode else []),
        f"[hosts.{HOST}]",
        'services = ["router", "sim", "mocap", "transform"]',
        "vehicles = [" + ", ".join(f'"d{i + 1}"' for i in range(n_vehicles)) + "]",
        "[sim]",
        f"mocap_rate = {float(rate)}",
        f'natnet_version = "{NATNET_VERSION}"',
        "noise_m = 0.0",
        "dropout = 0.0",
        "[pipeline]",
        f'decimate = "{decimate}"',
    ]
    for i in range(n_vehicles):
        lines += [
            f"[vehicles.d{i + 1}]",
            f'rigid_body = "d{i + 1}"',
            f'mavlink = "udpout:127.0.0.1:{harness_ports[i]}"',
            f"system_id = {i + 1}",
            f"vision_rate = {VISION_RATE}",
        ]
    path = directory / f"bench-{n_vehicles}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def socket_kind_tcp() -> int:
    import socket

    return socket.SOCK_STREAM


def router_port(cfg: ArenaConfig) -> int:
    return int(cfg.zenoh.router_listen[0].rsplit(":", 1)[1])


def vision_rates(per_vehicle: Mapping[Any, Mapping[str, int]], n: int, window_s: float) -> dict[str, float]:
    """The least, median and most poses per second a vehicle received over a ``window_s`` s window
    (``per_vehicle[v]["delivered"]``; a vehicle missing from it received none)."""
    if window_s <= 0 or n <= 0:
        return {}
    rates = sorted(per_vehicle.get(v, {}).get("delivered", 0) / window_s for v in range(n))
    return {"min": rates[0], "median": statistics.median(rates), "max": rates[-1]}


def _result(
    chain: str,
    n: int,
    rate: float,
    found: Mapping[str, Any],
    usage: dict[str, Any],
    *,
    window_s: float = 0.0,
    **extra: Any,
) -> PointResult:
    """A load point from an analysis (``analyze_arena`` or ``analyze_floor``) and the processes' usage."""
    return PointResult(
        chain=chain,
        vehicles=n,
        rate=rate,
        latency=latency_stats(found["latencies"]).as_dict(),
        expected=found["expected"],
        delivered=found["delivered"],
        lost=found["lost"],
        duplicates=found["duplicates"],
        per_service=usage,
        load=os.getloadavg()[0],
        vision_rate=vision_rates(found.get("per_vehicle", {}), n, window_s),
        **extra,
    )


def _delta(
    before: Mapping[str, Mapping[str, int]], after: Mapping[str, Mapping[str, int]]
) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for name, counts in after.items():
        prev = before.get(name, {})
        if prev.get("pid") != counts.get("pid"):
            prev = {}  # a new process of the same name: its counters start from zero
        d = {k: v - prev.get(k, 0) for k, v in counts.items() if k != "pid" and v != prev.get(k, 0)}
        if d:
            out[name] = d
    return out


# -- the arena run -------------------------------------------------------------------------------------------


def _vehicle_sockets(n: int) -> tuple[dict[Any, Any], list[int]]:
    socks: dict[Any, Any] = {}
    ports: list[int] = []
    for i in range(n):
        s = stamped_socket(0)
        socks[i] = s
        ports.append(int(s.getsockname()[1]))
    return socks, ports


def _wait_outputs(
    collector: Collector,
    n: int,
    timeout: float,
    what: str,
    procs: ProcessSet,
    accept: Callable[[bytes], bool] = lambda data: True,
) -> None:
    """Wait until every vehicle's socket received a datagram ``accept`` takes (ODOMETRY, not HEARTBEAT)."""
    checked = dict.fromkeys(range(n), 0)
    done: set[int] = set()

    def flowing() -> bool:
        for i in range(n):
            if i in done:
                continue
            records = collector.records[i]
            end = len(records)
            if any(accept(data) for _, data in records[checked[i] : end]):
                done.add(i)
            checked[i] = end
        return len(done) == n

    wait_until(flowing, timeout, what, procs)


def _wait_quiet(collector: Collector, tags: Sequence[Any], quiet: float = 0.3, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    last = sum(collector.count(t) for t in tags)
    calm_since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.05)
        now_count = sum(collector.count(t) for t in tags)
        if now_count != last:
            last, calm_since = now_count, time.monotonic()
        elif time.monotonic() - calm_since >= quiet:
            return


def run_arena(
    n: int,
    rates: Sequence[float],
    settings: RunSettings,
    *,
    realistic_vision: float | None = None,
    overload: int = 0,
    on_point: Callable[[PointResult], None] | None = None,
    decimate: str = "downsampler",
    deployed_only: bool = False,
) -> list[PointResult]:
    """The real pipeline for ``n`` vehicles at each rate (processes started once, the emulator per rate).

    Every pose goes to the autopilot (vision rate :data:`VISION_RATE`).  With ``realistic_vision``, the
    decimators are then restarted at that vision rate and one more point runs at the first rate (chain
    ``arena-v<rate>``): the pipeline's CPU as deployed, its latencies and losses against what the
    decimator passes by design.  With ``overload`` as well, that point runs once more with ``overload``
    CPU hogs (``while True: pass``, nice 0) beside it for the warm-up and the window (chain
    ``arena-v<rate>-loaded``): whether every vehicle's vision survives a computer that cannot keep up.
    ``decimate`` is the config's ``[pipeline] decimate``: ``downsampler`` (one process per vehicle; chain
    ``arena``) or ``transform`` (chain ``arena-td``).  ``deployed_only`` skips the every-pose points: the
    decimators start at ``realistic_vision`` and only the deployed (and overloaded) points run, the idle
    figures and the start-up with the first of them (the fleet point).
    """
    run = _ArenaRun(n, rates[0], settings, decimate, on_point)
    try:
        deployed_rate = realistic_vision if deployed_only else None  # the decimators start as deployed
        run.start(deployed_rate or VISION_RATE)
        idle = run.idle()
        for rate in rates if deployed_rate is None else ():
            run.measure(rate, run.chain_name, VISION_RATE, idle)
            idle = {}
        if realistic_vision is not None:
            if deployed_rate is None:
                run.restart_decimators(realistic_vision)
            deployed = f"{run.chain_name}-v{realistic_vision:g}"
            run.measure(rates[0], deployed, realistic_vision, idle)
            if overload > 0:
                run.measure(rates[0], f"{deployed}-loaded", realistic_vision, {}, hogs=overload)
    finally:
        run.close()
    return run.results


class _ArenaRun:
    """One process set of :func:`run_arena`: its config, its processes, the harness's sockets and session,
    and the points measured on it, in order."""

    def __init__(
        self,
        n: int,
        rate: float,
        settings: RunSettings,
        decimate: str,
        on_point: Callable[[PointResult], None] | None,
    ) -> None:
        from arena_common.pipeline.transform import frame_transform
        from arena_common.sim.natnet_scene import rigid_bodies
        from arena_common.sim.natnet_server import TICK_FREQUENCY

        self.tick_frequency = TICK_FREQUENCY
        self.n, self.settings, self.decimate, self.on_point = n, settings, decimate, on_point
        self.chain_name = CHAINS[decimate]
        workdir = settings.logs / f"{self.chain_name}-{n}"
        socks, ports = _vehicle_sockets(n)
        self.path = write_config(
            workdir, n, rate, ports, decimate=decimate, vehicle_mode=settings.vehicle_mode
        )
        self.cfg = load_config(self.path)
        socks["frames"] = stamped_socket(self.cfg.mocap.data_port, group=self.cfg.mocap.group)
        self.names = list(self.cfg.vehicles)
        self.body_to_vehicle = {body_id: self.names.index(v) for v, _, body_id in rigid_bodies(self.cfg)}
        self.transform = frame_transform(self.cfg)
        self.version = natnet.Version.parse(NATNET_VERSION)
        self.common = ["-c", str(self.path), "--host", HOST, "--log-level", "WARNING"]
        self.results: list[PointResult] = []
        self.procs = ProcessSet(workdir, env=_env(settings.repo))
        self.collector = Collector(socks)
        self.bus: Bus | None = None
        self.feeder: TruthFeeder | None = None
        self.watcher: StatsWatcher | None = None
        self.hop_watcher: HopWatcher | None = None
        # s to every service alive ("services") and to vision from every gateway ("vision"): PointResult's
        self.startup: dict[str, float] = {}

    def _spawn(self, name: str, role: str, module: str, *args: str) -> Child:
        return self.procs.spawn(name, role, python_module(module, *args), self.settings.repo)

    def start(self, vision_rate: float) -> None:
        """The router, the harness's session and feeds, the decimators at ``vision_rate``, the transform and
        the gateways; returns once every service is alive."""
        self.collector.start()
        t_start = time.monotonic()
        self._spawn("router", "router", "arena_common.cli", "router", "-c", str(self.path), "--host", HOST)
        wait_port(router_port(self.cfg), 30, "the Zenoh router", self.procs)
        self.bus = open_bus(self.cfg.zenoh)
        self.feeder = TruthFeeder(self.bus, self.names).start()
        self.watcher = StatsWatcher(self.bus)
        if self.settings.hops:
            self.hop_watcher = HopWatcher(self.bus, self.names[0])
        self._decimators(vision_rate)
        if self.decimate == "downsampler":
            self._spawn("transform", "transform", "services.frame_transform", *self.common)
        self._gateways()
        self._all_up()
        self.startup["services"] = time.monotonic() - t_start

    @property
    def gateway_hosts(self) -> int:
        """Processes of bench.gateway_host the gateways run in (0: one gateway process per vehicle)."""
        return min(self.settings.gateway_hosts, self.n)

    def _gateways(self) -> None:
        k = self.gateway_hosts
        if k <= 0:
            for v in self.names:
                args = (*self.common, "--vehicle", v)
                self._spawn(f"gateway.{v}", "gateway", "services.mavlink_gateway", *args)
            return
        for i in range(k):
            vehicles = [a for v in self.names[i::k] for a in ("--vehicle", v)]
            vision = ("--vision", self.settings.gateway_vision)
            self._spawn(
                f"gateway-host.{i}", "gateway", "bench.gateway_host", *self.common, *vehicles, *vision
            )

    def _decimators(self, vision_rate: float) -> None:
        if self.decimate == "transform":
            conf = self.path
            if vision_rate != VISION_RATE:  # the same arena (ports and all), another vision rate
                conf = self.path.with_name(f"{self.path.stem}-v{vision_rate:g}.toml")
                conf.write_text(
                    self.path.read_text().replace(
                        f"vision_rate = {VISION_RATE}", f"vision_rate = {vision_rate}"
                    )
                )
            self._spawn(
                "transform", "transform", "services.frame_transform", "-c", str(conf), *self.common[2:]
            )
            return
        for v in self.names:
            args = (*self.common, "--vehicle", v, "--rate", str(vision_rate))
            self._spawn(f"downsampler.{v}", "downsampler", "services.downsampler", *args)

    def restart_decimators(self, vision_rate: float) -> None:
        """The decimators stopped and started again at ``vision_rate``; returns once all are alive."""
        role = "downsampler" if self.decimate == "downsampler" else "transform"
        for c in [c for c in self.procs.children if c.role == role]:
            self.procs.stop(c)
        self._decimators(vision_rate)
        self._all_up()

    def _all_up(self) -> None:
        # router, transform, gateways, downsamplers
        expected_alive = 2 + (2 * self.n if self.decimate == "downsampler" else self.n)
        assert self.bus is not None
        the_bus = self.bus
        wait_until(
            lambda: len(the_bus.alive(f"arena/sys/alive/{HOST}/**", timeout=0.5)) >= expected_alive,
            self.settings.start_timeout,
            f"{expected_alive} services to come up",
            self.procs,
        )

    def idle(self) -> dict[str, dict[str, Any]]:
        """Every process's usage over ``settings.idle`` s with nothing flowing (after ``settings.settle``)."""
        if self.settings.idle <= 0:
            return {}
        time.sleep(self.settings.settle)
        self.procs.mark()
        time.sleep(self.settings.idle)
        return self.procs.usage()

    def measure(
        self, rate: float, chain: str, vision_rate: float, idle: dict[str, dict[str, Any]], hogs: int = 0
    ) -> PointResult:
        """One load point: the emulator at ``rate`` and the ingest started, the window measured (with
        ``hogs`` CPU hogs), both stopped, and every ODOMETRY matched to its frame."""
        assert self.watcher is not None
        before = self.watcher.counters()
        self.collector.clear()
        if self.hop_watcher is not None:
            self.hop_watcher.clear()
        emulator, ingest = self._flow(rate)
        t0, t1, usage, profile = self._window(hogs)
        time.sleep(self.settings.drain)
        self.procs.check_alive()
        self.procs.stop(emulator)
        _wait_quiet(self.collector, list(range(self.n)))
        time.sleep(1.2)  # one more stats period, so the counters cover the whole run
        after = self.watcher.counters()
        self.procs.stop(ingest)
        found = self._analyse(self.collector.take(), t0, t1, rate, vision_rate)
        point = _result(
            chain,
            self.n,
            rate,
            found,
            usage,
            designed_drops=found["designed_drops"],
            mismatched=found["mismatched"],
            idle=idle,
            counters=_delta(before, after),
            profile=profile,
            hops=hop_breakdown(found["first_vehicle"], self.hop_watcher.stamps) if self.hop_watcher else {},
            window_s=(t1 - t0) / 1e9,
            hogs=hogs,
            vehicle_mode=self.settings.vehicle_mode,
            startup=dict(self.startup) if not self.results else {},
        )
        keys_ = ("frames", "frame_gaps", "substituted", "unmatched_time", "clock_residual_us_p99")
        if (k := self.gateway_hosts) > 0:
            point.notes.append(
                f"gateways in {k} process{'es' if k > 1 else ''} (bench.gateway_host), "
                f"vision per {self.settings.gateway_vision}"
            )
        point.notes.append(
            f"vision {vision_rate:g} Hz, "
            + ", ".join(
                f"{k}={found[k]:.3g}" if isinstance(found[k], float) else f"{k}={found[k]}" for k in keys_
            )
        )
        self.results.append(point)
        if self.on_point is not None:
            self.on_point(point)
        return point

    def _flow(self, rate: float) -> tuple[Child, Child]:
        """The emulator at ``rate``, then the ingest (its handshake then succeeds at once), until every
        gateway sends ODOMETRY; both are started per rate."""
        t_emulator = time.monotonic()
        emulator = self._spawn(
            f"emulator.{int(rate)}", "emulator", "services.sim_mocap", *self.common, "--rate", str(rate)
        )
        wait_until(
            lambda: self.collector.count("frames") > 0,
            self.settings.start_timeout,
            "NatNet frames",
            self.procs,
        )
        ingest = self._spawn("ingest", "ingest", "services.mocap_ingest", *self.common)
        what = f"ODOMETRY from all {self.n} gateways at {rate:g} Hz"
        _wait_outputs(
            self.collector,
            self.n,
            self.settings.start_timeout,
            what,
            self.procs,
            lambda d: odometry_of(d) is not None,
        )
        if "services" in self.startup and "vision" not in self.startup:
            self.startup["vision"] = time.monotonic() - t_emulator
        return emulator, ingest

    def _window(self, hogs: int) -> tuple[int, int, dict[str, dict[str, Any]], dict[str, Any]]:
        """The warm-up, then the measured window (``hogs`` CPU hogs beside it): its start and end (ns), every
        process's usage over it and the profile taken during it."""
        settings = self.settings
        loads = [
            self.procs.spawn(f"hog.{k}", "load", [sys.executable, "-c", "while True: pass"])
            for k in range(hogs)
        ]
        time.sleep(settings.warmup)
        self.procs.check_alive()
        t0 = time.time_ns()
        self.procs.mark()
        profile = settings.profile(self.procs, settings.duration) if settings.profile else {}
        remaining = settings.duration - (time.time_ns() - t0) / 1e9
        if remaining > 0:
            time.sleep(remaining)
        usage = self.procs.usage()
        t1 = time.time_ns()
        for hog in loads:
            self.procs.stop(hog)
        return t0, t1, usage, profile

    def _analyse(
        self, records: dict[Any, list[tuple[int, bytes]]], t0: int, t1: int, rate: float, vision_rate: float
    ) -> dict[str, Any]:
        frames = decode_frames(
            records["frames"], self.body_to_vehicle, self.transform, self.version, self.tick_frequency
        )
        outputs = {i: records[i] for i in range(self.n)}
        return analyze_arena(frames, outputs, t0, t1, rate, vision_rate)

    def close(self) -> None:
        """Everything stopped and closed: feeds, processes, the session, the sockets."""
        if self.hop_watcher is not None:
            self.hop_watcher.close()
        if self.feeder is not None:
            self.feeder.close()
        if self.watcher is not None:
            self.watcher.close()
        self.procs.stop()
        if self.bus is not None:
            self.bus.close()
        self.collector.close()


def _env(repo: Path) -> dict[str, str]:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo.resolve()) + (
        os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
    )
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env
