"""Peer comparison of ``make bench``: the gateway beside MAVProxy, forwarding the same vision stream.

Both get a stream of poses at the same rate and send ODOMETRY to a UDP socket of the harness, which stamps
its arrival in the kernel:

- **gateway** — a private router and one ``services.mavlink_gateway`` process; the harness publishes each
  :class:`~arena_common.core.wire.Pose` on ``arena/d1/vision`` (its ``t`` is the send time, so ODOMETRY's
  ``time_usec`` names it) and the gateway encodes and sends ODOMETRY;
- **MAVProxy** — ``mavproxy.py --master udpin:… --out udpout:… --daemon --non-interactive`` with its
  default modules, as users run it; the harness sends ready-made ODOMETRY frames to its master port and
  MAVProxy forwards them.

Latency is send → arrival.  CPU per message is the process's CPU over the stream divided by the
messages it forwarded (``total``), and the same less its idle CPU over the same time (``marginal``).
"""

from __future__ import annotations

import os
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any

from arena_common.bus.session import open_bus
from arena_common.core import keys, wire
from arena_common.core.config import load as load_config
from arena_common.mavlink import px4
from bench.harness import (
    BenchError,
    Collector,
    ProcessSet,
    cpu_ns,
    free_port,
    iter_schedule,
    latency_stats,
    python_module,
    rss_bytes,
    stamped_socket,
    wait_port,
    wait_until,
)
from bench.matching import odometry_of
from bench.pipeline import HOST, RunSettings, _env, router_port, write_config

__all__ = ["mavproxy_command", "run_peers"]


def mavproxy_command() -> str | None:
    """The ``mavproxy.py`` next to this interpreter, or on ``PATH``; ``None`` when not installed."""
    local = Path(sys.executable).parent / "mavproxy.py"
    if local.exists():
        return str(local)
    return shutil.which("mavproxy.py")


def _cpu_window(pid: int, seconds: float) -> float:
    """CPU seconds ``pid`` used over the next ``seconds``."""
    a = cpu_ns(pid, precise=True)
    time.sleep(seconds)
    b = cpu_ns(pid, precise=True)
    if a is None or b is None:
        raise BenchError(f"process {pid} went away while measuring")
    return (b - a) / 1e9


def _figures(
    sent: dict[int, int],
    records: list[tuple[int, bytes]],
    cpu_s: float,
    idle_cpu_s: float,
    duration: float,
    rss: int,
) -> dict[str, Any]:
    lat: list[int] = []
    seen: set[int] = set()
    for stamp, data in records:
        od = odometry_of(data)
        if od is None:
            continue
        usec = od[0]
        if usec in sent and usec not in seen:
            seen.add(usec)
            lat.append(stamp - sent[usec])
    n = len(seen)
    return {
        "sent": len(sent),
        "forwarded": n,
        "lost": len(sent) - n,
        "latency": latency_stats(lat).as_dict(),
        "cpu_percent": 100.0 * cpu_s / duration,
        "idle_cpu_percent": 100.0 * idle_cpu_s / duration,
        "cpu_us_per_msg": 1e6 * cpu_s / n if n else float("nan"),
        "marginal_cpu_us_per_msg": 1e6 * max(0.0, cpu_s - idle_cpu_s) / n if n else float("nan"),
        "rss": rss,
    }


def _run_gateway(rate: float, settings: RunSettings) -> dict[str, Any]:
    workdir = settings.logs / "peer-gateway"
    sock = stamped_socket(0)
    port = int(sock.getsockname()[1])
    path = write_config(workdir, 1, 180.0, [port])
    cfg = load_config(path)
    common = ["-c", str(path), "--host", HOST, "--log-level", "WARNING"]
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector({"out": sock})
    bus = None
    try:
        collector.start()
        procs.spawn(
            "router",
            "router",
            python_module("arena_common.cli", "router", "-c", str(path), "--host", HOST),
            settings.repo,
        )
        wait_port(router_port(cfg), 30, "the Zenoh router", procs)
        bus = open_bus(cfg.zenoh)
        gw = procs.spawn(
            "gateway",
            "gateway",
            python_module("services.mavlink_gateway", *common, "--vehicle", "d1"),
            settings.repo,
        )
        pub = bus.stream_publisher(keys.vision("d1"), wire.Pose)
        q = (1.0, 0.0, 0.0, 0.0)

        def pose(k: int) -> tuple[int, wire.Pose]:
            now = time.time_ns()
            # A fresh t per pose: the gateway sends only poses newer than the last one, at most 0.1 s old.
            return now, wire.Pose(t=now, p=(0.001 * (k % 1000), 0.5, -1.0), q=q, ok=True, fn=k, tp=now)

        def flowing() -> bool:
            pub.put(pose(0)[1])
            return any(odometry_of(d) is not None for _, d in collector.take()["out"])

        wait_until(flowing, settings.start_timeout, "ODOMETRY from the gateway", procs)
        time.sleep(0.5)
        duration = settings.duration
        idle = _cpu_window(gw.pid, settings.idle) / settings.idle if settings.idle > 0 else 0.0
        collector.clear()
        sent: dict[int, int] = {}
        stop = threading.Event()
        a = cpu_ns(gw.pid, precise=True)
        t0 = time.monotonic()
        for k in iter_schedule(rate, stop, duration):
            t_send, p = pose(k + 1)
            pub.put(p)
            sent[p.t // 1000] = t_send
        elapsed = time.monotonic() - t0
        b = cpu_ns(gw.pid, precise=True)
        time.sleep(settings.drain)
        procs.check_alive()
        if a is None or b is None:
            raise BenchError("the gateway went away while measuring")
        return _figures(
            sent,
            collector.take()["out"],
            (b - a) / 1e9,
            idle * elapsed,
            elapsed,
            rss_bytes(gw.pid) or 0,
        )
    finally:
        procs.stop()
        if bus is not None:
            bus.close()
        collector.close()


def _run_mavproxy(rate: float, settings: RunSettings, command: str) -> dict[str, Any]:
    os.environ.setdefault("MAVLINK20", "1")
    from arena_common.mavlink.link import mavlink2

    workdir = settings.logs / "peer-mavproxy"
    sock = stamped_socket(0)
    out_port = int(sock.getsockname()[1])
    master = free_port()
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector({"out": sock})
    import socket as socket_mod

    tx = socket_mod.socket(socket_mod.AF_INET, socket_mod.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        collector.start()
        workdir.mkdir(parents=True, exist_ok=True)
        mp = procs.spawn(
            "mavproxy",
            "mavproxy",
            [
                sys.executable,
                command,
                f"--master=udpin:127.0.0.1:{master}",
                f"--out=udpout:127.0.0.1:{out_port}",
                "--daemon",
                "--non-interactive",
                "--nowait",
                "--no-state",
            ],
            workdir,
        )

        def frame(k: int) -> tuple[int, bytes]:
            now = time.time_ns()
            args = px4.odometry_args(now // 1000, (0.001 * (k % 1000), 0.5, -1.0), (1.0, 0.0, 0.0, 0.0))
            return now, bytes(mav.odometry_encode(**args).pack(mav))

        def flowing() -> bool:
            tx.sendto(frame(0)[1], ("127.0.0.1", master))
            return any(odometry_of(d) is not None for _, d in collector.take()["out"])

        wait_until(flowing, settings.start_timeout, "MAVProxy to forward ODOMETRY", procs)
        time.sleep(0.5)
        duration = settings.duration
        idle = _cpu_window(mp.pid, settings.idle) / settings.idle if settings.idle > 0 else 0.0
        collector.clear()
        # Each frame is encoded just before it is sent; its send time is taken after encoding.
        sent: dict[int, int] = {}
        stop = threading.Event()
        a = cpu_ns(mp.pid, precise=True)
        t0 = time.monotonic()
        for k in iter_schedule(rate, stop, duration):
            _, data = frame(k + 1)
            od = odometry_of(data)
            assert od is not None
            sent[od[0]] = time.time_ns()
            tx.sendto(data, ("127.0.0.1", master))
        elapsed = time.monotonic() - t0
        b = cpu_ns(mp.pid, precise=True)
        time.sleep(settings.drain)
        procs.check_alive()
        if a is None or b is None:
            raise BenchError("MAVProxy went away while measuring")
        return _figures(
            sent,
            collector.take()["out"],
            (b - a) / 1e9,
            idle * elapsed,
            elapsed,
            rss_bytes(mp.pid) or 0,
        )
    finally:
        procs.stop()
        tx.close()
        collector.close()


def run_peers(rate: float, settings: RunSettings) -> dict[str, Any]:
    """The gateway and MAVProxy, each forwarding ``rate`` Hz of vision for ``settings.duration`` s."""
    out: dict[str, Any] = {"rate": rate, "duration": settings.duration}
    out["gateway"] = _run_gateway(rate, settings)
    command = mavproxy_command()
    if command is None:
        out["mavproxy"] = {"unavailable": "mavproxy.py is not installed (pip install mavproxy)"}
    else:
        try:
            out["mavproxy"] = _run_mavproxy(rate, settings, command)
        except BenchError as exc:
            out["mavproxy"] = {"unavailable": str(exc)}
    g, m = out["gateway"], out["mavproxy"]
    if "unavailable" not in m and m.get("cpu_us_per_msg") and g.get("cpu_us_per_msg"):
        out["cpu_ratio"] = g["cpu_us_per_msg"] / m["cpu_us_per_msg"]
        out["marginal_cpu_ratio"] = (
            g["marginal_cpu_us_per_msg"] / m["marginal_cpu_us_per_msg"]
            if m["marginal_cpu_us_per_msg"]
            else float("nan")
        )
    return out
