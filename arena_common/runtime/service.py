"""What every arena process needs once: shutdown on signals, presence, counters on a stats key, logging.

A service module does::

    def main(cfg: ArenaConfig, options: BusOptions, *, stop: threading.Event | None = None) -> None:
        with running("transform", cfg, options, stop=stop) as svc:
            sub = svc.bus.subscribe("arena/*/mocap")
            while not svc.stopped:
                item = sub.get(0.2)
                ...
                svc.stats.count("in")

``running`` opens the bus, declares the presence token ``arena/sys/alive/<host>/<service>``, publishes
:class:`~arena_common.core.wire.Stats` every second and closes everything on the way out (SIGINT, SIGTERM and
SIGHUP set the stop event when called from the main thread; a second SIGINT or SIGTERM ends the process at once:
:class:`~arena_common.runtime.process.StopSignals`).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import Bus, BusOptions, Lane, Received, Subscription, open_bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.services import CpuShare
from arena_common.runtime.clock import ClockSync
from arena_common.runtime.process import StopSignals

LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def setup_logging(level: str | int = "INFO") -> None:
    """Configure the root logger once (services call it from their command-line entry)."""
    if not logging.getLogger().handlers:
        logging.basicConfig(level=level, format=LOG_FORMAT)
    else:
        logging.getLogger().setLevel(level)


@dataclass
class Stats:
    """Counters of one service.  Thread-safe; :meth:`snapshot` computes rates and latency figures."""

    counts: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    _lat: list[float] = field(default_factory=list)
    _prev: dict[str, int] = field(default_factory=dict)
    _prev_t: float = field(default_factory=time.monotonic)
    _prev_cpu: float = field(default_factory=time.process_time)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to counter ``name``."""
        with self._lock:
            self.counts[name] = self.counts.get(name, 0) + n

    def set(self, name: str, value: int) -> None:
        """Set counter ``name`` to a level (children alive, clients connected…)."""
        with self._lock:
            self.counts[name] = value

    def reject(self, reason: str, n: int = 1) -> None:
        """Count ``n`` rejected inputs (one by default) under ``reason``."""
        if n <= 0:
            return
        with self._lock:
            self.rejected[reason] = self.rejected.get(reason, 0) + n

    def latency(self, seconds: float) -> None:
        """Record one latency sample (kept until the next snapshot, at most 10,000)."""
        with self._lock:
            if len(self._lat) < 10_000:
                self._lat.append(seconds)

    def snapshot(self) -> tuple[dict[str, float], dict[str, float], float]:
        """(rates per counter, latency p50/p99/max, cpu percent) since the previous snapshot."""
        now, cpu = time.monotonic(), time.process_time()
        with self._lock:
            dt = max(now - self._prev_t, 1e-6)
            rates = {k: (v - self._prev.get(k, 0)) / dt for k, v in self.counts.items()}
            lat = sorted(self._lat)
            self._lat = []
            self._prev = dict(self.counts)
            cpu_pct = 100.0 * (cpu - self._prev_cpu) / dt
            self._prev_t, self._prev_cpu = now, cpu
        figures: dict[str, float] = {}
        if lat:
            figures = {
                "p50": lat[len(lat) // 2],
                "p99": lat[min(len(lat) - 1, int(len(lat) * 0.99))],
                "max": lat[-1],
                "n": float(len(lat)),
            }
        return rates, figures, cpu_pct


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


class Service:
    """A running service: its bus, stop event, stats, logger and presence."""

    def __init__(
        self, name: str, cfg: ArenaConfig | None, bus: Bus, host: str, vehicle: str, stop: threading.Event
    ) -> None:
        self.name = name
        self.id = f"{name}.{vehicle}" if vehicle else name
        self.cfg = cfg
        self.bus = bus
        self.host = host
        self.vehicle = vehicle
        self.stop = stop
        self.stats = Stats()
        self.log = logging.getLogger(f"arena.{self.id}")
        self.started = time.monotonic()
        self._last_warn: dict[str, float] = {}
        self._stats_pub = bus.stream_publisher(keys.stats(host, self.id), wire.Stats, Lane.REPORT)
        #: This host's clock offset to the mocap host's (set by :func:`running`).
        self.clock: ClockSync | None = None

    @property
    def stopped(self) -> bool:
        """True once a stop was asked for."""
        return self.stop.is_set()

    def read(self, sub: Subscription, timeout: float, count: str = "in") -> Received[Any] | None:
        """The next sample of ``sub`` (None after ``timeout``), counted under ``count``; what its channel
        dropped meanwhile is counted as ``dropped``.  Check its type with
        :func:`~arena_common.bus.session.typed`."""
        item = sub.get(timeout)
        dropped = sub.newly_dropped()
        if dropped:
            self.stats.count("dropped", dropped)
        if item is not None:
            self.stats.count(count)
        return item

    def reject(self, reason: str, detail: str = "", interval: float = 5.0) -> None:
        """Count a rejected input and log it, once per reason per ``interval`` seconds."""
        self.stats.reject(reason)
        now = time.monotonic()
        if now - self._last_warn.get(reason, -1e9) >= interval:
            self._last_warn[reason] = now
            n = self.stats.rejected.get(reason, 0)
            self.log.warning("rejected (%s, %d so far): %s", reason, n, detail or reason)

    def publish_stats(self) -> wire.Stats:
        """Publish one :class:`~arena_common.core.wire.Stats` snapshot now."""
        rates, lat, cpu = self.stats.snapshot()
        with self.stats._lock:
            counts, rejected = dict(self.stats.counts), dict(self.stats.rejected)
        msg = wire.Stats(
            t=wire.now_ns(),
            service=self.id,
            host=self.host,
            pid=os.getpid(),
            up=time.monotonic() - self.started,
            counts=counts,
            rejected=rejected,
            rates=rates,
            lat=lat,
            cpu=cpu,
            rss=_rss_bytes(),
            vehicle=self.vehicle,
            lost=self.bus.lost(),
        )
        self._stats_pub.put(msg)
        return msg

    def _stats_loop(self, period: float) -> None:
        while not self.stop.wait(period):
            try:
                self.publish_stats()
            except Exception as exc:  # the bus may be closing; never take the service down
                self.log.debug("stats not published: %s", exc)

    def sleep(self, seconds: float) -> bool:
        """Wait up to ``seconds``; returns True if a stop was asked for meanwhile."""
        return self.stop.wait(seconds)


BACKGROUND_NICE = 10  # added to the niceness of a process the vehicles do not depend on
VISION_NICE = -5  # the niceness of a process the vehicles' vision passes through, where it may take it
AUTOGROUP = Path("/proc/self/autogroup")  # this session's scheduling group (Linux autogroup scheduling)


def take_cpu_share(share: CpuShare, log: logging.Logger | None = None) -> int:
    """Share the CPU as :data:`~arena_common.core.services.SERVICES` says of this process; its niceness.

    ``vision`` goes first (:func:`favour_cpu`), ``background`` yields (:func:`yield_cpu`), ``normal`` keeps
    what it was given.  For a process's entry point, once it leads its session (every process ``arena up``
    starts does; :func:`~arena_common.runtime.process.lead_own_session` for a command typed in a terminal).
    """
    if share == "vision":
        return favour_cpu(log)
    if share == "background":
        return yield_cpu(log)
    return os.nice(0)


def favour_cpu(log: logging.Logger | None = None) -> int:
    """Raise this process (and its session's scheduling group) to niceness :data:`VISION_NICE`; the niceness.

    For the processes every pose passes through on its way to a vehicle (and the simulated world, which
    stands for hardware with processors of its own): on a computer busy with other work (two CPU-bound
    programs beside a lab's arena on two cores), each stage at the weight of any other program waited
    behind them at every hop, and poses reached the gateways older than ``gateway.max_pose_age``: vision
    went stale by itself and PX4 landed the vehicle.  A weight of -5 (about three times the default) keeps
    a stage's wake-up ahead of them; the stages use a small share of the CPU each, so nothing else starves.
    Raising a priority needs ``CAP_SYS_NICE`` (root, or ``LimitNICE=`` / ``Nice=`` under systemd): without
    it the process runs as before and says so once.
    """
    current = os.nice(0)
    if current > VISION_NICE:
        try:
            current = os.nice(VISION_NICE - current)
        except OSError as exc:
            if log is not None:
                log.info("runs at CPU niceness %d (cannot raise it to %d: %s)", current, VISION_NICE, exc)
            return current
    problem = _set_session_group(VISION_NICE)
    if log is not None:
        if problem is None:
            log.info("running at CPU niceness %d: the vision pipeline goes first", current)
        else:
            log.info("running at CPU niceness %d, but %s", current, problem)
    return current


def yield_cpu(log: logging.Logger | None = None) -> int:
    """Lower this process's CPU priority by :data:`BACKGROUND_NICE`; the new niceness.

    For processes no vehicle depends on (the recorder, the live viewer): on a computer that cannot keep
    up, the kernel then gives the CPU to the vision pipeline (ingest, transform, downsamplers, gateways)
    first, and these fall behind and shed (counted) instead.

    Linux's autogroup scheduling (on by default in most distributions) shares the CPU between sessions
    first and weighs a niceness only among the processes of one session — and every process ``arena up``
    starts leads a session of its own.  A niceness alone then changes nothing: the viewer took as much of
    the CPU as each stage of the pipeline, and vision went stale.  So a process that leads its session
    (:func:`~arena_common.runtime.process.lead_own_session`) lowers its session's group by as much
    (``/proc/self/autogroup``); one that does not says so in the log.
    """
    try:
        value = os.nice(BACKGROUND_NICE)
    except OSError as exc:  # not allowed here: run as before, and say so
        if log is not None:
            log.warning("cannot lower this process's CPU priority: %s", exc)
        return os.nice(0)
    problem = _set_session_group(BACKGROUND_NICE)
    if log is not None:
        if problem is None:
            log.info("running at CPU niceness %d: the vision pipeline goes first", value)
        else:
            log.warning(
                "running at CPU niceness %d, but %s: the vision pipeline may wait for it", value, problem
            )
    return value


def _set_session_group(nice: int) -> str | None:
    """Give this process's session group (its autogroup) the niceness ``nice`` (lower for a background
    process, higher for a vision stage: never the other way); why it could not, or None (done, or no
    autogroup scheduling here: the process's niceness is enough)."""
    if os.getsid(0) != os.getpid():
        return "its session's CPU share stays as it was (it does not lead its session)"
    try:
        current = int(AUTOGROUP.read_text().split()[-1])  # "/autogroup-42 nice 0"
    except (OSError, ValueError, IndexError):
        return None  # not Linux, or a kernel without autogroup scheduling
    if (current >= nice) if nice > 0 else (current <= nice):  # already as far as asked, or further
        return None
    for _ in range(10):
        try:
            AUTOGROUP.write_text(str(nice))
            return None
        except BlockingIOError:  # EAGAIN: the kernel allows one such change every 100 ms, machine-wide
            time.sleep(0.11)
        except OSError as exc:
            return f"its session's CPU share stays as it was ({exc})"
    return "its session's CPU share stays as it was (the kernel kept refusing the change)"


def exit_now(log: logging.Logger, signum: int) -> None:
    """End this process at once (a second stop signal: the orderly stop takes too long for its user).

    Its children go too: each one asked the kernel for a signal when this process dies
    (:class:`~arena_common.runtime.process.ChildProcess`).
    """
    try:
        log.warning("%s again: exiting at once", signal.Signals(signum).name)
        for handler in logging.getLogger().handlers:
            handler.flush()
    finally:
        os._exit(128 + signum)


@contextmanager
def running(
    name: str,
    cfg: ArenaConfig | None,
    options: BusOptions | None = None,
    *,
    vehicle: str = "",
    host: str | None = None,
    stop: threading.Event | None = None,
    stats_period: float = 1.0,
    bus: Bus | None = None,
    clock: bool = True,
    clock_reference: bool = False,
) -> Iterator[Service]:
    """Run a service: open the bus, declare presence, publish stats, stop cleanly on SIGINT/SIGTERM/SIGHUP
    (from the main thread; a second SIGINT or SIGTERM exits at once, see :func:`exit_now`).

    With ``clock`` the service measures its host's clock offset to the mocap host's
    (:class:`~arena_common.runtime.clock.ClockSync`, ``svc.clock``); ``clock_reference`` makes it that
    reference (the mocap ingest: its clock stamps every pose).
    """
    stop = stop or threading.Event()
    own_bus = bus is None
    host = host_name(host)
    the_bus = (
        open_bus(cfg.zenoh if cfg else None, host_bus_options(cfg, host, options, vehicle=vehicle))
        if bus is None
        else bus
    )
    svc = Service(name, cfg, the_bus, host, vehicle, stop)
    signals = StopSignals(stop, again=lambda signum: exit_now(svc.log, signum)).install()
    token = the_bus.token(keys.alive(svc.host, svc.id))
    if clock or clock_reference:
        spec = cfg.clock if cfg is not None else None
        svc.clock = ClockSync(the_bus, svc.host, svc.id, spec, reference=clock_reference, log=svc.log).start()
    stats_thread = threading.Thread(
        target=svc._stats_loop, args=(stats_period,), name=f"{svc.id}:stats", daemon=True
    )
    stats_thread.start()
    svc.log.info("started (host %s, pid %d)", svc.host, os.getpid())
    try:
        yield svc
    finally:
        stop.set()
        stats_thread.join(timeout=2.0)
        if svc.clock is not None:
            svc.clock.close()
        try:
            token.undeclare()
        except Exception:
            pass
        if own_bus:
            the_bus.close()
        svc.log.info("stopped")
        signals.restore()
