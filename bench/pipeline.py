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
from arena_common.core.config import load as load_config
from arena_common.mocap import natnet
from bench.feeds import StatsWatcher, TruthFeeder
from bench.harness import (
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
    from arena_common.pipeline.transform import frame_transform
    from arena_common.sim.natnet_scene import rigid_bodies
    from arena_common.sim.natnet_server import TICK_FREQUENCY

    chain_name = CHAINS[decimate]
    workdir = settings.logs / f"{chain_name}-{n}"
    socks, ports = _vehicle_sockets(n)
    path = write_config(workdir, n, rates[0], ports, decimate=decimate, vehicle_mode=settings.vehicle_mode)
    cfg = load_config(path)
    socks["frames"] = stamped_socket(cfg.mocap.data_port, group=cfg.mocap.group)
    names = list(cfg.vehicles)
    body_to_vehicle = {body_id: names.index(vehicle) for vehicle, _, body_id in rigid_bodies(cfg)}
    transform = frame_transform(cfg)
    version = natnet.Version.parse(NATNET_VERSION)
    common = ["-c", str(path), "--host", HOST, "--log-level", "WARNING"]
    results: list[PointResult] = []
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector(socks)
    bus: Bus | None = None
    feeder: TruthFeeder | None = None
    watcher: StatsWatcher | None = None
    hop_watcher: HopWatcher | None = None

    def decimators(vision_rate: float) -> None:
        if decimate == "transform":
            conf = path
            if vision_rate != VISION_RATE:  # the same arena (ports and all), another vision rate
                conf = path.with_name(f"{path.stem}-v{vision_rate:g}.toml")
                conf.write_text(
                    path.read_text().replace(f"vision_rate = {VISION_RATE}", f"vision_rate = {vision_rate}")
                )
            args = ["-c", str(conf), *common[2:]]
            procs.spawn(
                "transform", "transform", python_module("services.frame_transform", *args), settings.repo
            )
            return
        for v in names:
            procs.spawn(
                f"downsampler.{v}",
                "downsampler",
                python_module("services.downsampler", *common, "--vehicle", v, "--rate", str(vision_rate)),
                settings.repo,
            )

    def all_up() -> None:
        # router, transform, gateways, downsamplers
        expected_alive = 2 + (2 * n if decimate == "downsampler" else n)
        assert bus is not None
        the_bus = bus
        wait_until(
            lambda: len(the_bus.alive(f"arena/sys/alive/{HOST}/**", timeout=0.5)) >= expected_alive,
            settings.start_timeout,
            f"{expected_alive} services to come up",
            procs,
        )

    def measure(
        rate: float, chain: str, vision_rate: float, idle: dict[str, dict[str, Any]], hogs: int = 0
    ) -> PointResult:
        assert watcher is not None
        before = watcher.counters()
        collector.clear()
        if hop_watcher is not None:
            hop_watcher.clear()
        # The emulator first, then the ingest (its handshake then succeeds at once): both per rate.
        t_emulator = time.monotonic()
        emulator = procs.spawn(
            f"emulator.{int(rate)}",
            "emulator",
            python_module("services.sim_mocap", *common, "--rate", str(rate)),
            settings.repo,
        )
        wait_until(lambda: collector.count("frames") > 0, settings.start_timeout, "NatNet frames", procs)
        ingest = procs.spawn(
            "ingest", "ingest", python_module("services.mocap_ingest", *common), settings.repo
        )
        what = f"ODOMETRY from all {n} gateways at {rate:g} Hz"
        _wait_outputs(collector, n, settings.start_timeout, what, procs, lambda d: odometry_of(d) is not None)
        if "services" in startup and "vision" not in startup:
            startup["vision"] = time.monotonic() - t_emulator
        loads = [
            procs.spawn(f"hog.{k}", "load", [sys.executable, "-c", "while True: pass"]) for k in range(hogs)
        ]
        time.sleep(settings.warmup)
        procs.check_alive()
        t0 = time.time_ns()
        procs.mark()
        profile = settings.profile(procs, settings.duration) if settings.profile else {}
        remaining = settings.duration - (time.time_ns() - t0) / 1e9
        if remaining > 0:
            time.sleep(remaining)
        usage = procs.usage()
        t1 = time.time_ns()
        for hog in loads:
            procs.stop(hog)
        time.sleep(settings.drain)
        procs.check_alive()
        procs.stop(emulator)
        _wait_quiet(collector, list(range(n)))
        time.sleep(1.2)  # one more stats period, so the counters cover the whole run
        after = watcher.counters()
        procs.stop(ingest)
        records = collector.take()
        frames = decode_frames(records["frames"], body_to_vehicle, transform, version, TICK_FREQUENCY)
        found = analyze_arena(frames, {i: records[i] for i in range(n)}, t0, t1, rate, vision_rate)
        point = _result(
            chain,
            n,
            rate,
            found,
            usage,
            designed_drops=found["designed_drops"],
            mismatched=found["mismatched"],
            idle=idle,
            counters=_delta(before, after),
            profile=profile,
            hops=hop_breakdown(found["first_vehicle"], hop_watcher.stamps) if hop_watcher else {},
            window_s=(t1 - t0) / 1e9,
            hogs=hogs,
            startup=dict(startup) if not results else {},
        )
        keys_ = ("frames", "frame_gaps", "substituted", "unmatched_time", "clock_residual_us_p99")
        point.notes.append(
            f"vision {vision_rate:g} Hz, "
            + ", ".join(
                f"{k}={found[k]:.3g}" if isinstance(found[k], float) else f"{k}={found[k]}" for k in keys_
            )
        )
        results.append(point)
        if on_point is not None:
            on_point(point)
        return point

    startup: dict[str, float] = {}
    try:
        collector.start()
        t_start = time.monotonic()
        procs.spawn(
            "router",
            "router",
            python_module("arena_common.cli", "router", "-c", str(path), "--host", HOST),
            settings.repo,
        )
        wait_port(router_port(cfg), 30, "the Zenoh router", procs)
        bus = open_bus(cfg.zenoh)
        feeder = TruthFeeder(bus, names).start()
        watcher = StatsWatcher(bus)
        if settings.hops:
            hop_watcher = HopWatcher(bus, names[0])
        deployed_rate = realistic_vision if deployed_only else None  # the decimators start as deployed
        decimators(deployed_rate or VISION_RATE)
        if decimate == "downsampler":
            procs.spawn(
                "transform", "transform", python_module("services.frame_transform", *common), settings.repo
            )
        for v in names:
            procs.spawn(
                f"gateway.{v}",
                "gateway",
                python_module("services.mavlink_gateway", *common, "--vehicle", v),
                settings.repo,
            )
        all_up()
        startup["services"] = time.monotonic() - t_start
        idle: dict[str, dict[str, Any]] = {}
        if settings.idle > 0:
            time.sleep(settings.settle)
            procs.mark()
            time.sleep(settings.idle)
            idle = procs.usage()
        for rate in rates if deployed_rate is None else ():
            measure(rate, chain_name, VISION_RATE, idle)
            idle = {}
        if realistic_vision is not None:
            if deployed_rate is None:
                role = "downsampler" if decimate == "downsampler" else "transform"
                for c in [c for c in procs.children if c.role == role]:
                    procs.stop(c)
                decimators(realistic_vision)
                all_up()
            deployed = f"{chain_name}-v{realistic_vision:g}"
            measure(rates[0], deployed, realistic_vision, idle)
            if overload > 0:
                measure(rates[0], f"{deployed}-loaded", realistic_vision, {}, hogs=overload)
    finally:
        if hop_watcher is not None:
            hop_watcher.close()
        if feeder is not None:
            feeder.close()
        if watcher is not None:
            watcher.close()
        procs.stop()
        if bus is not None:
            bus.close()
        collector.close()
    return results


def _env(repo: Path) -> dict[str, str]:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo.resolve()) + (
        os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
    )
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env
