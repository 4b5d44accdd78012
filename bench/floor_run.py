"""The floor chains of ``make bench``: the arena's process topology with :mod:`bench.floor` relays that only
move bytes, over Zenoh (the arena's session settings and stream QoS) or over UDP, at the same loads.

Source → ingest's place (fanned out per vehicle) → transform's → one relay per vehicle in the
downsampler's place → one in the gateway's → the harness.  Messages carry their frame number, so the
harness matches them exactly (:func:`bench.matching.analyze_floor`).  With a vision rate, the transform's
relay then passes each vehicle's messages at that rate only (as the arena's decimating transform does;
chain ``floor-<kind>-v<rate>``): the floor of the deployed point.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from bench.harness import (
    BenchError,
    Collector,
    ProcessSet,
    free_port,
    python_module,
    stamped_socket,
    wait_port,
)
from bench.matching import analyze_floor, payload_sizes
from bench.pipeline import (
    FLOOR_PREFIX,
    PointResult,
    RunSettings,
    _env,
    _group,
    _result,
    _vehicle_sockets,
    _wait_outputs,
    _wait_quiet,
    socket_kind_tcp,
)

__all__ = ["run_floor"]


@dataclass(frozen=True)
class _Routes:
    """Where each relay of a floor chain reads and sends: one input, per-vehicle lists after the fan-out."""

    into_ingest: str  # what the ingest's relay sends to
    into_transform: str
    out_transform: str
    into_ds: list[str]
    out_ds: list[str]
    into_gw: list[str]
    zenoh_args: list[str] = field(default_factory=list)  # every relay's Zenoh options


def run_floor(
    kind: str,
    n: int,
    rates: Sequence[float],
    settings: RunSettings,
    *,
    inline: bool = False,
    vision_rate: float | None = None,
    on_point: Callable[[PointResult], None] | None = None,
) -> list[PointResult]:
    """The floor chain over ``kind`` (``zenoh`` or ``udp``) for ``n`` vehicles at each rate; with
    ``vision_rate``, one more point at the first rate with the transform's relay passing that rate."""
    if kind not in ("zenoh", "udp"):
        raise BenchError(f"floor transport must be zenoh or udp, not {kind!r}")
    chain = f"floor-{kind}" + ("-inline" if inline else "")
    run = _FloorRun(chain, n, settings)
    results: list[PointResult] = []
    try:
        run.collector.start()
        routes = _zenoh_routes(n, run.procs, settings, inline) if kind == "zenoh" else _udp_routes(n)
        run.start_relays(routes)
        time.sleep(0.5)
        points: list[tuple[float, str, float | None]] = [(rate, chain, None) for rate in rates]
        if vision_rate is not None:
            points.append((rates[0], f"{chain}-v{vision_rate:g}", vision_rate))
        for rate, name, vision in points:
            if vision is not None:  # the transform's relay passes the vision rate only from now on
                run.procs.stop(next(c for c in run.procs.children if c.role == "transform"))
                run.transform(routes, "--keep", repr(min(1.0, vision / rate)))
            point = run.measure(rate, name, vision)
            results.append(point)
            if on_point is not None:
                on_point(point)
    finally:
        run.procs.stop()
        run.collector.close()
    return results


class _FloorRun:
    """One floor chain's processes and the harness's sockets: the vehicles' and the source's group."""

    def __init__(self, chain: str, n: int, settings: RunSettings) -> None:
        self.n, self.settings = n, settings
        self.sizes = payload_sizes(n)
        workdir = settings.logs / f"{chain}-{n}"
        socks, self.ports = _vehicle_sockets(n)
        self.group, self.data_port = _group(), free_port()
        socks["frames"] = stamped_socket(self.data_port, group=self.group)
        self.procs = ProcessSet(workdir, env=_env(settings.repo))
        self.collector = Collector(socks)

    def relay(
        self, routes: _Routes, name: str, role: str, source: str, target: str, size: str, *extra: str
    ) -> None:
        argv = python_module("bench.floor", "relay", "--in", source, "--out", target, "--size", size)
        self.procs.spawn(name, role, [*argv, *extra, *routes.zenoh_args], self.settings.repo)

    def transform(self, routes: _Routes, *extra: str) -> None:
        """The transform's relay: fans each frame out to every vehicle (``extra``: its other options)."""
        size, fanout = str(self.sizes["pose"]), str(self.n)
        argv = (routes.into_transform, routes.out_transform, size, "--fanout", fanout, *extra)
        self.relay(routes, "transform", "transform", *argv)

    def start_relays(self, routes: _Routes) -> None:
        """A relay in the place of each of the arena's processes, the source's aside."""
        frames_in = f"mcast:{self.group}:{self.data_port}"
        self.relay(routes, "ingest", "ingest", frames_in, routes.into_ingest, str(self.sizes["frames"]))
        self.transform(routes)
        pose, odometry = str(self.sizes["pose"]), str(self.sizes["odometry"])
        for i in range(self.n):
            self.relay(
                routes, f"downsampler.d{i + 1}", "downsampler", routes.into_ds[i], routes.out_ds[i], pose
            )
        for i in range(self.n):
            self.relay(
                routes, f"gateway.d{i + 1}", "gateway", routes.into_gw[i], f"udp:{self.ports[i]}", odometry
            )

    def measure(self, rate: float, name: str, vision: float | None) -> PointResult:
        """One load point: the source at ``rate`` until every vehicle's relay delivers, the window measured,
        the source stopped, every message matched to its frame."""
        procs, collector, settings, n = self.procs, self.collector, self.settings, self.n
        collector.clear()
        source = procs.spawn(
            f"source.{int(rate)}",
            "emulator",
            python_module(
                "bench.floor",
                "source",
                "--group",
                self.group,
                "--port",
                str(self.data_port),
                "--rate",
                str(rate),
                "--size",
                str(self.sizes["natnet"]),
            ),
            settings.repo,
        )
        _wait_outputs(
            collector,
            n,
            settings.start_timeout,
            f"the {name} chain to carry data for {n} vehicles",
            procs,
        )
        time.sleep(settings.warmup)
        t0 = time.time_ns()
        procs.mark()
        time.sleep(settings.duration)
        usage = procs.usage()
        t1 = time.time_ns()
        time.sleep(settings.drain)
        procs.check_alive()
        procs.stop(source)
        _wait_quiet(collector, list(range(n)))
        records = collector.take()
        keep = None if vision is None else min(1.0, vision / rate)
        found = analyze_floor(records["frames"], {i: records[i] for i in range(n)}, t0, t1, keep=keep)
        return _result(name, n, rate, found, usage, window_s=(t1 - t0) / 1e9)


def _zenoh_routes(n: int, procs: ProcessSet, settings: RunSettings, inline: bool) -> _Routes:
    """A private Zenoh router started, and the floor's keys on it."""
    rport = free_port(socket_kind_tcp())
    endpoint = f"tcp/127.0.0.1:{rport}"
    procs.spawn(
        "router",
        "router",
        python_module("arena_common.cli", "router", "--listen", endpoint),
        settings.repo,
    )
    wait_port(rport, 30, "the Zenoh router", procs)
    b, c = (f"zenoh:{FLOOR_PREFIX}/v{{i}}/{s}" for s in "bc")
    a = f"zenoh:{FLOOR_PREFIX}/frames"
    return _Routes(
        into_ingest=a,
        into_transform=a,
        out_transform=b,
        into_ds=[f"zenoh:{FLOOR_PREFIX}/v{i}/b" for i in range(n)],
        out_ds=[c] * n,
        into_gw=[f"zenoh:{FLOOR_PREFIX}/v{i}/c" for i in range(n)],
        zenoh_args=["--connect", endpoint] + (["--inline"] if inline else []),
    )


def _udp_routes(n: int) -> _Routes:
    """Free loopback UDP ports: one into the transform's place, one per vehicle into each relay after it."""
    p_all = free_port()
    p_b = [free_port() for _ in range(n)]
    p_c = [free_port() for _ in range(n)]
    out_ds = [f"udp:{p}" for p in p_c]
    return _Routes(
        into_ingest=f"udp:{p_all}",
        into_transform=f"udp:{p_all}",
        out_transform="udp:" + ",".join(map(str, p_b)),
        into_ds=[f"udp:{p}" for p in p_b],
        out_ds=out_ds,
        into_gw=out_ds,
    )
