"""Peer comparison of ``make bench``: the gateway beside its two floors and MAVProxy, forwarding the same
vision stream.

Every forwarder gets a stream of poses at the same rate and sends ODOMETRY to its own UDP socket of the
harness, which stamps each arrival in the kernel:

- **gateway** — a private router and one ``services.mavlink_gateway`` process; the harness publishes each
  :class:`~arena_common.core.wire.Pose` on ``arena/d1/vision`` (vision lane, as the arena does; its ``t``
  is the send time, so ODOMETRY's ``time_usec`` names it) and the gateway encodes and sends ODOMETRY;
- **floor-zenoh** — the same, with :mod:`bench.forwarders`' Zenoh forwarder in the gateway's place: the
  same config and session settings, the Zenoh receive, a msgspec decode and one ready-made ODOMETRY
  datagram per pose — the least the gateway's path can cost in Python over Zenoh;
- **floor-udp** — :mod:`bench.forwarders`' UDP forwarder: ready-made ODOMETRY frames in, the same bytes
  out (MAVProxy's path, bytes only);
- **MAVProxy** — ``mavproxy.py --master udpin:… --out udpout:… --daemon --non-interactive`` with its
  default modules, as users run it, fed the same ready-made ODOMETRY frames.

All four run side by side for the whole comparison (started once; the Zenoh ones each in its own arena,
so that no pose reaches two of them); each is then measured ``repeats`` times, one at a time, the order
reversed on every other round so that a drift of the machine's load weighs on all alike.  Each round
begins with one idle window in which none gets a message (their idle CPU).

Latency is send → arrival.  CPU per message is the process's CPU over the stream (schedstat, ns) divided
by the messages it forwarded (``total``), and the same less its idle CPU over the same time
(``marginal``).  The summary of each forwarder is the median of its runs with their min–max spread.  A
sweep of higher rates (one short run each) shows how much of a message's cost is the wake-ups it pays.
"""

from __future__ import annotations

import os
import shutil
import socket
import statistics
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena_common.bus.session import Bus, Lane, open_bus
from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError
from arena_common.mavlink import fastframe, px4
from arena_common.runtime.options import read_config as load_config
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

__all__ = ["FORWARDERS", "mavproxy_command", "run_peers", "summarise"]

FORWARDERS = ("gateway", "floor-zenoh", "floor-udp", "mavproxy")
WARM = 0.3  # s of stream before each measured window


def mavproxy_command() -> str | None:
    """The ``mavproxy.py`` next to this interpreter, or on ``PATH``; ``None`` when not installed."""
    local = Path(sys.executable).parent / "mavproxy.py"
    if local.exists():
        return str(local)
    return shutil.which("mavproxy.py")


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


# -- the forwarders ------------------------------------------------------------------------------------------


@dataclass
class _Forwarder:
    """One forwarder under test: its process, how to give it message ``k``, and what it did."""

    name: str
    procs: ProcessSet
    pid: int
    send: Callable[[int], tuple[int, int]]  # k → (ODOMETRY time_usec it will carry, send time ns)
    runs: list[dict[str, Any]] = field(default_factory=list)
    error: str = ""


def _pose_sender(bus: Bus) -> Callable[[int], tuple[int, int]]:
    pub = bus.stream_publisher(keys.vision("d1"), wire.Pose, Lane.VISION)
    q = (1.0, 0.0, 0.0, 0.0)

    def send(k: int) -> tuple[int, int]:
        now = time.time_ns()
        # A fresh t per pose: the gateway sends only poses newer than the last one, at most 0.1 s old.
        pub.put(wire.Pose(t=now, p=(0.001 * (k % 1000), 0.5, -1.0), q=q, ok=True, fn=k, tp=now))
        return now // 1000, now

    return send


def _frame_sender(tx: socket.socket, port: int) -> Callable[[int], tuple[int, int]]:
    state = {"seq": 0}

    def send(k: int) -> tuple[int, int]:
        usec = time.time_ns() // 1000
        args = px4.odometry_args(usec, (0.001 * (k % 1000), 0.5, -1.0), (1.0, 0.0, 0.0, 0.0))
        data = fastframe.ODOMETRY.frame(fastframe.odometry_payload(args), state["seq"], 1, 1)
        state["seq"] = (state["seq"] + 1) & 0xFF
        t_send = time.time_ns()  # after encoding, as a MAVLink source would send it
        tx.sendto(data, ("127.0.0.1", port))
        return usec, t_send

    return send


def _zenoh_arena(
    name: str, settings: RunSettings, port: int, argv: Callable[[Path], list[str]], role: str
) -> tuple[ProcessSet, Bus, Any]:
    """A private router, the forwarder (``argv(config)``) and the harness's session, in ``name``'s arena."""
    workdir = settings.logs / "peer" / name
    path = write_config(workdir, 1, 180.0, [port])
    cfg = load_config(path)
    procs = ProcessSet(workdir, env=_env(settings.repo))
    try:
        procs.spawn(
            "router",
            "router",
            python_module("arena_common.cli", "router", "-c", str(path), "--host", HOST),
            settings.repo,
        )
        wait_port(router_port(cfg), 30, f"the Zenoh router of {name}", procs)
        child = procs.spawn(name, role, argv(path), settings.repo)
        return procs, open_bus(cfg.zenoh), child
    except BaseException:
        procs.stop()
        raise


def _start(
    settings: RunSettings, ports: dict[str, int], tx: socket.socket, buses: list[Bus]
) -> tuple[dict[str, _Forwarder], dict[str, str]]:
    """Start every forwarder; those that cannot run are returned apart with the reason."""
    fwds: dict[str, _Forwarder] = {}
    unavailable: dict[str, str] = {}
    starters: dict[str, Callable[[], _Forwarder]] = {
        "gateway": lambda: _start_gateway(settings, ports["gateway"], buses),
        "floor-zenoh": lambda: _start_floor_zenoh(settings, ports["floor-zenoh"], buses),
        "floor-udp": lambda: _start_floor_udp(settings, ports["floor-udp"], tx),
        "mavproxy": lambda: _start_mavproxy(settings, ports["mavproxy"], tx),
    }
    for name, start in starters.items():
        try:
            fwds[name] = start()
        except (BenchError, ArenaError) as exc:
            unavailable[name] = str(exc)
    return fwds, unavailable


def _start_gateway(settings: RunSettings, port: int, buses: list[Bus]) -> _Forwarder:
    """The arena's gateway for one vehicle, in an arena of its own, fed vision poses over Zenoh."""
    procs, bus, child = _zenoh_arena(
        "gateway",
        settings,
        port,
        lambda p: python_module(
            "services.mavlink_gateway",
            "-c",
            str(p),
            "--host",
            HOST,
            "--log-level",
            "WARNING",
            "--vehicle",
            "d1",
        ),
        "gateway",
    )
    buses.append(bus)
    return _Forwarder("gateway", procs, child.pid, _pose_sender(bus))


def _start_floor_zenoh(settings: RunSettings, port: int, buses: list[Bus]) -> _Forwarder:
    """The Zenoh forwarder of :mod:`bench.forwarders`, in an arena of its own, fed vision poses."""
    out = str(port)
    procs, bus, child = _zenoh_arena(
        "floor-zenoh",
        settings,
        port,
        lambda p: python_module("bench.forwarders", "zenoh", "-c", str(p), "--host", HOST, "--out", out),
        "floor",
    )
    buses.append(bus)
    return _Forwarder("floor-zenoh", procs, child.pid, _pose_sender(bus))


def _start_floor_udp(settings: RunSettings, port: int, tx: socket.socket) -> _Forwarder:
    """The UDP forwarder of :mod:`bench.forwarders`, fed ready-made ODOMETRY frames from ``tx``."""
    procs = ProcessSet(settings.logs / "peer" / "floor-udp", env=_env(settings.repo))
    listen = free_port()
    child = procs.spawn(
        "floor-udp",
        "floor",
        python_module("bench.forwarders", "udp", "--listen", str(listen), "--out", str(port)),
        settings.repo,
    )
    return _Forwarder("floor-udp", procs, child.pid, _frame_sender(tx, listen))


def _start_mavproxy(settings: RunSettings, port: int, tx: socket.socket) -> _Forwarder:
    """MAVProxy as users run it, fed ready-made ODOMETRY frames from ``tx``."""
    command = mavproxy_command()
    if command is None:
        raise BenchError("mavproxy.py is not installed (pip install mavproxy)")
    workdir = settings.logs / "peer" / "mavproxy"
    workdir.mkdir(parents=True, exist_ok=True)
    procs = ProcessSet(workdir, env={**_env(settings.repo), "MAVLINK20": "1"})
    master = free_port()
    child = procs.spawn(
        "mavproxy",
        "mavproxy",
        [
            sys.executable,
            command,
            f"--master=udpin:127.0.0.1:{master}",
            f"--out=udpout:127.0.0.1:{port}",
            "--daemon",
            "--non-interactive",
            "--nowait",
            "--no-state",
        ],
        workdir,
    )
    return _Forwarder("mavproxy", procs, child.pid, _frame_sender(tx, master))


def _wait_flowing(fwd: _Forwarder, collector: Collector, timeout: float) -> None:
    def flowing() -> bool:
        fwd.send(0)
        return any(odometry_of(d) is not None for _, d in collector.take()[fwd.name])

    wait_until(flowing, timeout, f"ODOMETRY from {fwd.name}", fwd.procs)


def _window(
    fwd: _Forwarder, collector: Collector, rate: float, duration: float, idle_rate: float, drain: float
) -> dict[str, Any]:
    """One measurement of ``fwd``: a short warm-up of the stream, then ``duration`` s measured."""
    stop = threading.Event()
    for _ in iter_schedule(rate, stop, WARM):
        fwd.send(0)
    time.sleep(0.05)
    collector.clear()
    sent: dict[int, int] = {}
    a = cpu_ns(fwd.pid, precise=True)
    t0 = time.monotonic()
    for k in iter_schedule(rate, stop, duration):
        usec, t_send = fwd.send(k + 1)
        sent[usec] = t_send
    elapsed = time.monotonic() - t0
    b = cpu_ns(fwd.pid, precise=True)
    time.sleep(drain)
    fwd.procs.check_alive()
    if a is None or b is None:
        raise BenchError(f"{fwd.name} went away while measuring")
    fig = _figures(
        sent, collector.take()[fwd.name], (b - a) / 1e9, idle_rate * elapsed, elapsed, rss_bytes(fwd.pid) or 0
    )
    fig["load"] = os.getloadavg()[0]
    return fig


def _idle_rates(fwds: dict[str, _Forwarder], seconds: float) -> dict[str, float]:
    """Each forwarder's idle CPU (s per s), measured together over ``seconds`` with no message flowing."""
    if seconds <= 0:
        return dict.fromkeys(fwds, 0.0)
    before = {name: cpu_ns(f.pid, precise=True) for name, f in fwds.items()}
    time.sleep(seconds)
    out: dict[str, float] = {}
    for name, f in fwds.items():
        a, b = before[name], cpu_ns(f.pid, precise=True)
        out[name] = (b - a) / 1e9 / seconds if a is not None and b is not None else 0.0
    return out


def _spread(values: list[float]) -> list[float]:
    finite = [v for v in values if v == v]
    return [min(finite), max(finite)] if finite else [float("nan"), float("nan")]


def _median(values: list[float]) -> float:
    finite = [v for v in values if v == v]
    return statistics.median(finite) if finite else float("nan")


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """A forwarder's runs as medians (``cpu_us_per_msg``, latency ``p50``/``p99``…) with min–max spreads."""
    lat = [r["latency"] for r in runs]
    return {
        "repeats": len(runs),
        "sent": sum(r["sent"] for r in runs),
        "forwarded": sum(r["forwarded"] for r in runs),
        "lost": sum(r["lost"] for r in runs),
        "latency": {
            "n": sum(x["n"] for x in lat),
            "p50": _median([x["p50"] for x in lat]),
            "p99": _median([x["p99"] for x in lat]),
            "max": max((x["max"] for x in lat if x["max"] == x["max"]), default=float("nan")),
        },
        "cpu_us_per_msg": _median([r["cpu_us_per_msg"] for r in runs]),
        "marginal_cpu_us_per_msg": _median([r["marginal_cpu_us_per_msg"] for r in runs]),
        "cpu_percent": _median([r["cpu_percent"] for r in runs]),
        "idle_cpu_percent": _median([r["idle_cpu_percent"] for r in runs]),
        "spread": {
            "cpu_us_per_msg": _spread([r["cpu_us_per_msg"] for r in runs]),
            "marginal_cpu_us_per_msg": _spread([r["marginal_cpu_us_per_msg"] for r in runs]),
            "p50": _spread([x["p50"] for x in lat]),
            "p99": _spread([x["p99"] for x in lat]),
        },
        "load": [r["load"] for r in runs],
        "rss": max((r["rss"] for r in runs), default=0),
        "runs": runs,
    }


def _ratio(a: dict[str, Any], b: dict[str, Any], key: str) -> float:
    x, y = a.get(key), b.get(key)
    if x is None or y is None or not y or x != x or y != y:
        return float("nan")
    return float(x / y)


SWEEP_SECONDS = 1.0  # per forwarder and rate of the sweep


def run_peers(
    rate: float, settings: RunSettings, repeats: int = 3, sweep: tuple[float, ...] = ()
) -> dict[str, Any]:
    """The gateway, its two floors and MAVProxy, each forwarding ``rate`` Hz of vision for
    ``settings.duration`` s, ``repeats`` times in alternating order; then one short run of each at every
    rate of ``sweep`` (``out["sweep"][name][rate]``): how the cost per message falls as messages come
    closer together (the wake-ups a message pays are shared)."""
    if repeats < 1:
        raise BenchError("the peer comparison needs at least one repetition")
    out: dict[str, Any] = {"rate": rate, "duration": settings.duration, "repeats": repeats}
    socks = {name: stamped_socket(0) for name in FORWARDERS}
    ports = {name: int(s.getsockname()[1]) for name, s in socks.items()}
    collector = Collector(socks)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    buses: list[Bus] = []
    fwds: dict[str, _Forwarder] = {}
    try:
        collector.start()
        fwds, unavailable = _start(settings, ports, tx, buses)
        _drop_silent(fwds, unavailable, collector, settings.start_timeout)
        time.sleep(0.5)
        order = [n for n in FORWARDERS if n in fwds]
        out["order"] = order
        idle = _rounds(fwds, order, collector, rate, settings, repeats)
        out["sweep"] = _sweep(fwds, order, collector, sweep, idle, settings.drain)
        for name in FORWARDERS:
            out[name] = _summary(fwds.get(name), unavailable.get(name, "not started"))
    finally:
        for fwd in fwds.values():
            fwd.procs.stop()
        for bus in buses:
            bus.close()
        tx.close()
        collector.close()
    out.update(_ratios(out["gateway"], out["mavproxy"], out["floor-zenoh"]))
    return out


def _drop_silent(
    fwds: dict[str, _Forwarder], unavailable: dict[str, str], collector: Collector, timeout: float
) -> None:
    """Every forwarder that sends no ODOMETRY within ``timeout`` stopped and moved to ``unavailable``."""
    for name, fwd in list(fwds.items()):
        try:
            _wait_flowing(fwd, collector, timeout)
        except BenchError as exc:
            unavailable[name] = str(exc)
            fwd.procs.stop()
            del fwds[name]


def _rounds(
    fwds: dict[str, _Forwarder],
    order: list[str],
    collector: Collector,
    rate: float,
    settings: RunSettings,
    repeats: int,
) -> dict[str, float]:
    """``repeats`` rounds, each an idle window then one run of each forwarder, the order reversed every other
    round; a forwarder that fails keeps its error and runs no more.  Returns the last round's idle rates."""
    idle: dict[str, float] = {}
    for rnd in range(repeats):
        live = {n: f for n, f in fwds.items() if not f.error}
        idle = _idle_rates(live, settings.idle)
        for name in order if rnd % 2 == 0 else order[::-1]:
            fwd = fwds[name]
            if fwd.error:
                continue
            try:
                fwd.runs.append(_window(fwd, collector, rate, settings.duration, idle[name], settings.drain))
            except BenchError as exc:
                fwd.error = str(exc)
    return idle


def _sweep(
    fwds: dict[str, _Forwarder],
    order: list[str],
    collector: Collector,
    rates: tuple[float, ...],
    idle: dict[str, float],
    drain: float,
) -> dict[str, dict[str, Any]]:
    """One short run of each forwarder still without error at every rate: ``[name][f"{rate:g}"]``."""
    out: dict[str, dict[str, Any]] = {name: {} for name in order}
    for r in rates:
        for name in order:
            fwd = fwds[name]
            if fwd.error:
                continue
            try:
                fig = _window(fwd, collector, r, SWEEP_SECONDS, idle[name], drain)
            except BenchError as exc:
                fig = {"unavailable": str(exc)}
            out[name][f"{r:g}"] = fig
    return out


def _summary(fwd: _Forwarder | None, why_not: str) -> dict[str, Any]:
    """A forwarder's summary of its runs (:func:`summarise`), or why it has none."""
    if fwd is None:
        return {"unavailable": why_not}
    if not fwd.runs:
        return {"unavailable": fwd.error or "no run"}
    summary = summarise(fwd.runs)
    if fwd.error:
        summary["error"] = fwd.error
    return summary


def _ratios(g: dict[str, Any], m: dict[str, Any], fz: dict[str, Any]) -> dict[str, Any]:
    """The gateway's cost per message against MAVProxy's and its Zenoh floor's, the floor's against MAVProxy's."""
    out: dict[str, Any] = {}
    if "unavailable" not in g and "unavailable" not in m:
        out["cpu_ratio"] = _ratio(g, m, "cpu_us_per_msg")
        out["marginal_cpu_ratio"] = _ratio(g, m, "marginal_cpu_us_per_msg")
        pairs = [
            a["cpu_us_per_msg"] / b["cpu_us_per_msg"]
            for a, b in zip(g["runs"], m["runs"], strict=False)
            if b["cpu_us_per_msg"]
        ]
        out["cpu_ratio_spread"] = _spread(pairs)
    if "unavailable" not in g and "unavailable" not in fz:
        out["floor_ratio"] = _ratio(g, fz, "cpu_us_per_msg")
    if "unavailable" not in fz and "unavailable" not in m:
        out["floor_mavproxy_ratio"] = _ratio(fz, m, "cpu_us_per_msg")
    return out
