"""Replay: a recording published again on the bus with its original timing, bytes and encodings."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from arena_common.recording.codec import NS, RecordingError, log
from arena_common.recording.reader import RecordingReader

# -- replay -------------------------------------------------------------------------------------------------

# Left out of a replay unless asked for: they would command live vehicles (estop, setpoints) or pass
# for the system's own state (recorder control, past services' stats).
CONTROL_KEYS = ("arena/estop", "arena/*/setpoint", "arena/sys/**")


@dataclass(slots=True)
class ReplayReport:
    """What :func:`replay` sent."""

    sent: int = 0
    skipped: int = 0
    passes: int = 0
    late_max: float = 0.0  # s, the worst lateness against the schedule


def parse_remap(items: Iterable[str]) -> dict[str, str]:
    """``["arena/d1=arena/r1", …]`` → ``{"arena/d1": "arena/r1"}``; :class:`RecordingError` if malformed."""
    out: dict[str, str] = {}
    for item in items:
        a, sep, b = item.partition("=")
        a, b = a.strip().strip("/"), b.strip().strip("/")
        if not sep or not a or not b or any(c in a + b for c in "*$?#"):
            raise RecordingError(f"--remap {item!r}: expected FROM=TO with concrete key prefixes")
        out[a] = b
    return out


def remap_key(key: str, remap: Mapping[str, str]) -> str:
    """Replace the longest matching prefix (on whole chunks) of ``key``."""
    for a in sorted(remap, key=len, reverse=True):
        if key == a or key.startswith(a + "/"):
            return remap[a] + key[len(a) :]
    return key


def key_filter(
    key_exprs: Sequence[str] = ("arena/**",), include_control: bool = False
) -> Callable[[str], bool]:
    """A predicate on keys: matches one of ``key_exprs``, and is no control key unless ``include_control``."""
    try:
        exprs = [zenoh.KeyExpr(k) for k in key_exprs]
    except Exception as exc:
        raise RecordingError(f"bad key expression in {list(key_exprs)}: {exc}") from None
    control = [zenoh.KeyExpr(k) for k in CONTROL_KEYS]
    verdict: dict[str, bool] = {}

    def wanted(key: str) -> bool:
        ok = verdict.get(key)
        if ok is None:
            try:
                ke = zenoh.KeyExpr(key)
            except Exception:
                ok = False
            else:
                ok = any(e.includes(ke) for e in exprs) and (
                    include_control or not any(c.includes(ke) for c in control)
                )
            verdict[key] = ok
        return ok

    return wanted


def _sleep_until(due: float, stop: threading.Event, clock: Callable[[], float]) -> bool:
    """Sleep until ``clock() >= due``; True if ``stop`` was set meanwhile.  (``time.sleep`` wakes up more
    punctually than ``Event.wait`` on a loaded machine; the stop flag is looked at every 50 ms.)"""
    while True:
        if stop.is_set():
            return True
        left = due - clock()
        if left <= 0:
            return False
        time.sleep(min(left, 0.05))


def replay(
    path: str | Path,
    publish: Callable[[str, bytes, str], None],
    *,
    speed: float = 1.0,
    key_exprs: Sequence[str] = ("arena/**",),
    remap: Mapping[str, str] | None = None,
    loop: bool = False,
    include_control: bool = False,
    stop: threading.Event | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> ReplayReport:
    """Send every matching message with ``publish(key, msgpack_bytes, zenoh_encoding)`` on its original
    schedule (by ``log_time``, divided by ``speed``), until the end (or forever with ``loop``).

    Setpoints, emergency stops and ``arena/sys/**`` are left out unless ``include_control``: replaying
    them on a live arena would command real vehicles or pass for the system's current state.
    """
    if not speed > 0 or not math.isfinite(speed):
        raise RecordingError(f"replay speed must be a positive number, got {speed}")
    stop = stop or threading.Event()
    remap = dict(remap or {})
    wanted = key_filter(key_exprs, include_control)
    report = ReplayReport()
    reader = RecordingReader(path)
    while not stop.is_set():
        t0 = 0.0
        first: int | None = None
        for m in reader.messages():
            if stop.is_set():
                break
            if m.channel.scene:
                continue  # the 3D scene is derived from the samples: nothing the bus carried
            if not wanted(m.channel.key):
                report.skipped += 1
                continue
            data = m.wire_bytes()
            if first is None:
                first, t0 = m.log_time, clock()
            due = t0 + (m.log_time - first) / NS / speed
            if _sleep_until(due, stop, clock):
                break
            report.late_max = max(report.late_max, clock() - due)
            publish(remap_key(m.channel.key, remap), data, m.channel.zenoh_encoding)
            report.sent += 1
        report.passes += 1
        if reader.error and report.passes == 1:
            log.warning("%s: read stopped early: %s", reader.path, reader.error)
        if not loop or first is None:
            break
    return report
