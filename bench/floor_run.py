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
    sizes = payload_sizes(n)
    workdir = settings.logs / f"{chain}-{n}"
    socks, ports = _vehicle_sockets(n)
    group, data_port = _group(), free_port()
    socks["frames"] = stamped_socket(data_port, group=group)
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector(socks)
    results: list[PointResult] = []
    z: list[str] = []

    def relay(name: str, role: str, source: str, target: str, size: str, *extra: str) -> None:
        argv = python_module("bench.floor", "relay", "--in", source, "--out", target, "--size", size)
        procs.spawn(name, role, [*argv, *extra, *z], settings.repo)

    try:
        collector.start()
        if kind == "zenoh":
            rport = free_port(socket_kind_tcp())
            endpoint = f"tcp/127.0.0.1:{rport}"
            procs.spawn(
                "router",
                "router",
                python_module("arena_common.cli", "router", "--listen", endpoint),
                settings.repo,
            )
            wait_port(rport, 30, "the Zenoh router", procs)
            z = ["--connect", endpoint] + (["--inline"] if inline else [])
            b, c = (f"zenoh:{FLOOR_PREFIX}/v{{i}}/{s}" for s in "bc")
            a = into_transform = f"zenoh:{FLOOR_PREFIX}/frames"
            out_transform = b
            into_ds = [f"zenoh:{FLOOR_PREFIX}/v{i}/b" for i in range(n)]
            into_gw = [f"zenoh:{FLOOR_PREFIX}/v{i}/c" for i in range(n)]
            out_ds = [c] * n
        else:
            p_all = free_port()
            p_b = [free_port() for _ in range(n)]
            p_c = [free_port() for _ in range(n)]
            a, into_transform = f"udp:{p_all}", f"udp:{p_all}"
            out_transform = "udp:" + ",".join(map(str, p_b))
            into_ds = [f"udp:{p}" for p in p_b]
            out_ds = [f"udp:{p}" for p in p_c]
            into_gw = out_ds
        relay("ingest", "ingest", f"mcast:{group}:{data_port}", a, str(sizes["frames"]))

        def transform(*extra: str) -> None:
            argv = (into_transform, out_transform, str(sizes["pose"]), "--fanout", str(n), *extra)
            relay("transform", "transform", *argv)

        transform()
        for i in range(n):
            relay(f"downsampler.d{i + 1}", "downsampler", into_ds[i], out_ds[i], str(sizes["pose"]))
        for i in range(n):
            relay(f"gateway.d{i + 1}", "gateway", into_gw[i], f"udp:{ports[i]}", str(sizes["odometry"]))
        time.sleep(0.5)
        points: list[tuple[float, str, float | None]] = [(rate, chain, None) for rate in rates]
        if vision_rate is not None:
            points.append((rates[0], f"{chain}-v{vision_rate:g}", vision_rate))
        for rate, name, vision in points:
            if vision is not None:  # the transform's relay passes the vision rate only from now on
                procs.stop(next(c for c in procs.children if c.role == "transform"))
                transform("--keep", repr(min(1.0, vision / rate)))
            collector.clear()
            source = procs.spawn(
                f"source.{int(rate)}",
                "emulator",
                python_module(
                    "bench.floor",
                    "source",
                    "--group",
                    group,
                    "--port",
                    str(data_port),
                    "--rate",
                    str(rate),
                    "--size",
                    str(sizes["natnet"]),
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
            point = _result(name, n, rate, found, usage, window_s=(t1 - t0) / 1e9)
            results.append(point)
            if on_point is not None:
                on_point(point)
    finally:
        procs.stop()
        collector.close()
    return results
