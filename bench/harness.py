"""Measuring tools of ``make bench``: kernel-stamped sockets, child processes, CPU and memory, percentiles.

Every latency the benchmark reports is the difference of two **kernel receive stamps** (``SO_TIMESTAMPNS``,
``CLOCK_REALTIME``) taken on sockets the harness owns: the NatNet frame as the harness's own multicast
socket receives it (the same datagram the ingest receives, at the same instant on loopback) and the
MAVLink frame the gateway sends to the harness's vehicle socket.  The harness's own scheduling therefore
never enters a figure: a :class:`Collector` thread only drains the sockets and keeps ``(stamp, bytes)``.

CPU is read from ``/proc``: the sum of ``/proc/<pid>/task/<tid>/schedstat`` (nanoseconds, the threads
alive now), checked against ``utime + stime`` of ``/proc/<pid>/stat`` (clock ticks, every thread, the
ended ones too), which it falls back to when a thread ended in the window.
Memory is ``VmRSS`` of ``/proc/<pid>/status``.
"""

from __future__ import annotations

import contextlib
import math
import os
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena_common.core import waiting
from arena_common.core.errors import ArenaError, WaitTimeout
from arena_common.runtime.process import ChildProcess

__all__ = [
    "BenchError",
    "Collector",
    "LatencyStats",
    "ProcessSet",
    "cpu_ns",
    "free_port",
    "latency_stats",
    "rss_bytes",
    "stamped_socket",
]

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; Python does not export the constant
SCM_TIMESTAMPNS = SO_TIMESTAMPNS
_TIMESPEC = struct.Struct("@qq")
_RCVBUF = 8 << 20
_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


class BenchError(ArenaError):
    """A benchmark that cannot run: a process that does not start, data that never flows, bad options."""


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A loopback port nobody uses right now (UDP by default)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stamped_socket(port: int = 0, *, group: str | None = None, interface: str = "127.0.0.1") -> socket.socket:
    """A UDP socket on loopback whose datagrams carry kernel receive stamps.

    With ``group`` it joins that multicast group on ``interface`` and binds the group's ``port`` (shared
    with other receivers through ``SO_REUSEADDR``), the way a NatNet client does.
    """
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        if group is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((group, port))
            mreq = socket.inet_aton(group) + socket.inet_aton(interface)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        else:
            sock.bind(("127.0.0.1", port))
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        where = f"{group}:{port}" if group else f"127.0.0.1:{port}"
        raise BenchError(f"cannot open the harness socket {where}: {exc}") from None
    return sock


def _stamp(ancdata: list[tuple[int, int, bytes]]) -> int:
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SCM_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return int(sec * 1_000_000_000 + nsec)
    return time.time_ns()  # no stamp (not Linux): the receive time, a little late


class Collector:
    """Drains tagged sockets on its own thread and keeps every datagram with its kernel receive stamp.

    ``records[tag]`` is a list of ``(stamp_ns, data)``; :meth:`clear` empties them between runs.  The
    thread does nothing else, so a slow harness never delays a stamp (the kernel took it).
    """

    def __init__(self, sockets: Mapping[Any, socket.socket]) -> None:
        self.sockets = dict(sockets)
        self.records: dict[Any, list[tuple[int, bytes]]] = {tag: [] for tag in self.sockets}
        self._selector = selectors.DefaultSelector()
        for tag, sock in self.sockets.items():
            self._selector.register(sock, selectors.EVENT_READ, tag)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="bench-collector", daemon=True)

    def start(self) -> Collector:
        self._thread.start()
        return self

    def _run(self) -> None:
        space = socket.CMSG_SPACE(_TIMESPEC.size)
        records = self.records
        while not self._stop.is_set():
            for key, _ in self._selector.select(0.1):
                sock: socket.socket = key.fileobj  # type: ignore[assignment]
                out = records[key.data]
                for _ in range(1024):  # bounded burst per wake-up
                    try:
                        data, anc, _flags, _addr = sock.recvmsg(65536, space)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break
                    with self._lock:
                        out.append((_stamp(anc), data))

    def count(self, tag: Any) -> int:
        """Datagrams received on ``tag`` so far."""
        return len(self.records[tag])

    def take(self) -> dict[Any, list[tuple[int, bytes]]]:
        """Every record so far (a copy), leaving them in place."""
        with self._lock:
            return {tag: list(items) for tag, items in self.records.items()}

    def clear(self) -> None:
        """Forget every record."""
        with self._lock:
            for items in self.records.values():
                items.clear()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self._selector.close()
        for sock in self.sockets.values():
            sock.close()

    def __enter__(self) -> Collector:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- processes -----------------------------------------------------------------------------------------------


def cpu_ns(pid: int, precise: bool = False) -> int | None:
    """CPU time used so far by process ``pid`` (all threads), in ns; ``None`` when it is gone.

    By default ``utime + stime`` of ``/proc/<pid>/stat`` (clock ticks; it keeps the time of threads
    that have exited).  ``precise`` sums ``/proc/<pid>/task/*/schedstat`` instead (nanoseconds, but only
    for the threads alive now: use it over windows in which no thread ends).
    """
    if precise:
        total = 0
        found = False
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            return None
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                    total += int(f.read().split()[0])
                    found = True
            except (OSError, ValueError, IndexError):
                continue
        if found:
            return total
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) * 1_000_000_000 // _CLK_TCK
    except (OSError, ValueError, IndexError):
        return None


def rss_bytes(pid: int) -> int | None:
    """Resident memory of process ``pid`` (bytes), ``None`` when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


@dataclass
class Child:
    """One process the benchmark started."""

    name: str
    role: str  # what it stands for: router, emulator, ingest, transform, downsampler, gateway, floor…
    proc: ChildProcess
    log: Path
    cpu_mark: int | None = None
    cpu_mark_precise: int | None = None
    mark_t: float = 0.0

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 12) -> str:
        """The end of its output (for error messages)."""
        try:
            text = self.log.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


@dataclass
class ProcessSet:
    """Processes started for a measurement, stopped together (SIGTERM, then SIGKILL) on :meth:`stop`."""

    logs: Path
    env: Mapping[str, str] | None = None
    children: list[Child] = field(default_factory=list)

    def spawn(self, name: str, role: str, argv: Sequence[str], cwd: str | Path | None = None) -> Child:
        """Start ``argv`` (output to ``<logs>/<name>.log``)."""
        self.logs.mkdir(parents=True, exist_ok=True)
        log = self.logs / f"{name}.log"
        log.write_bytes(b"")
        try:
            proc = ChildProcess(argv, name=name, cwd=cwd, env=self.env, log=log, death_signal=None)
        except OSError as exc:
            raise BenchError(f"cannot start {name} ({argv[0]}): {exc}") from None
        child = Child(name, role, proc, log)
        self.children.append(child)
        return child

    def check_alive(self) -> None:
        """Raise :class:`BenchError` with its output if a child exited."""
        for c in self.children:
            code = c.proc.poll()
            if code is not None:
                raise BenchError(f"{c.name} exited with status {code}:\n{c.tail()}")

    def mark(self) -> None:
        """Start a CPU measurement window for every child."""
        now = time.monotonic()
        for c in self.children:
            c.cpu_mark, c.cpu_mark_precise, c.mark_t = cpu_ns(c.pid), cpu_ns(c.pid, precise=True), now

    def usage(self) -> dict[str, dict[str, Any]]:
        """Per child since :meth:`mark`: ``cpu`` (% of one core), ``rss`` (bytes), ``role``, ``pid``.

        CPU from the threads' schedstat (ns), unless that disagrees with the clock ticks of
        ``/proc/<pid>/stat`` by more than a few ticks and a quarter (a thread ended in the window and
        took its time with it): then from the ticks."""
        now = time.monotonic()
        out: dict[str, dict[str, Any]] = {}
        tick = 1_000_000_000 // _CLK_TCK
        for c in self.children:
            end, end_precise = cpu_ns(c.pid), cpu_ns(c.pid, precise=True)
            dt = now - c.mark_t
            used: float | None = None
            if end is not None and c.cpu_mark is not None:
                used = end - c.cpu_mark
                if end_precise is not None and c.cpu_mark_precise is not None:
                    precise = end_precise - c.cpu_mark_precise
                    if precise >= 0 and abs(precise - used) <= max(3 * tick, 0.25 * used):
                        used = precise
            cpu = 100.0 * used / 1e9 / dt if used is not None and dt > 0 else math.nan
            out[c.name] = {"role": c.role, "pid": c.pid, "cpu": cpu, "rss": rss_bytes(c.pid) or 0}
        return out

    def rss(self) -> dict[str, int]:
        """Resident memory of every child now."""
        return {c.name: rss_bytes(c.pid) or 0 for c in self.children}

    def stop(self, child: Child | None = None, grace: float = 8.0) -> None:
        """Stop one child, or all of them (in reverse start order): SIGTERM, then SIGKILL."""
        targets = [child] if child is not None else list(reversed(self.children))
        for c in targets:
            if c.alive:
                with contextlib.suppress(ProcessLookupError):
                    c.proc.send_signal(signal.SIGTERM, group=False)
        deadline = time.monotonic() + grace
        for c in targets:
            try:
                c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    c.proc.send_signal(signal.SIGKILL, group=False)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    c.proc.wait(5.0)
        for c in targets:
            if c in self.children:
                self.children.remove(c)

    def __enter__(self) -> ProcessSet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def python_module(module: str, *args: str) -> list[str]:
    """``python -m module args`` with this interpreter."""
    return [sys.executable, "-m", module, *args]


def wait_until(predicate: Any, timeout: float, what: str, procs: ProcessSet | None = None) -> None:
    """The library's :func:`~arena_common.core.waiting.wait_until`, checking that ``procs`` still run;
    :class:`BenchError` naming ``what`` after ``timeout``."""
    check = procs.check_alive if procs is not None else None
    try:
        waiting.wait_until(predicate, timeout, what, interval=0.05, check=check)
    except WaitTimeout as exc:
        raise BenchError(str(exc)) from None


def wait_port(port: int, timeout: float, what: str, procs: ProcessSet | None = None) -> None:
    """Wait until a TCP port on loopback accepts connections."""

    def ready() -> bool:
        with socket.socket() as s:
            s.settimeout(0.2)
            return s.connect_ex(("127.0.0.1", port)) == 0

    wait_until(ready, timeout, what, procs)


# -- figures -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LatencyStats:
    """Percentiles of a latency sample, in milliseconds."""

    n: int
    p50: float
    p99: float
    p999: float
    max: float
    mean: float

    def as_dict(self) -> dict[str, float]:
        return {
            "n": self.n,
            "p50": self.p50,
            "p99": self.p99,
            "p999": self.p999,
            "max": self.max,
            "mean": self.mean,
        }


def _percentile(sorted_values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile ``q`` (0–100) of already sorted values."""
    if not sorted_values:
        return math.nan
    pos = (len(sorted_values) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (pos - lo)


def latency_stats(values_ns: Sequence[int] | Sequence[float]) -> LatencyStats:
    """p50, p99, p99.9, max and mean (ms) of latencies given in ns (NaN everywhere when empty)."""
    ms = sorted(v / 1e6 for v in values_ns)
    if not ms:
        nan = math.nan
        return LatencyStats(0, nan, nan, nan, nan, nan)
    return LatencyStats(
        len(ms),
        _percentile(ms, 50),
        _percentile(ms, 99),
        _percentile(ms, 99.9),
        ms[-1],
        sum(ms) / len(ms),
    )


def iter_schedule(rate: float, stop: threading.Event, duration: float | None = None) -> Iterator[int]:
    """Yield 0, 1, 2… at ``rate`` Hz on a drift-free clock until ``stop`` is set (or ``duration`` ends)."""
    period = 1e9 / rate
    start = time.perf_counter_ns()
    k = 0
    while not stop.is_set():
        due = start + round(k * period)
        if duration is not None and due - start > duration * 1e9:
            return
        left = due - time.perf_counter_ns()
        if left > 0 and stop.wait(left / 1e9):
            return
        yield k
        k += 1
