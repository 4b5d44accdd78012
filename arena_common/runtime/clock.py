"""Every host's wall-clock offset to the mocap host's clock, measured over the bus like NTP.

Every pose carries its measurement time on the mocap host's wall clock (the mocap ingest's host maps
Motive's camera exposure onto it).  A process on another computer whose clock is off — no NTP on a
companion computer is common — would judge every pose stale, or from the future, and stamp the
autopilot's vision with the wrong time.  So the mocap ingest answers ``arena/sys/time`` (a
:class:`~arena_common.core.wire.Command` with op ``time``) with its clock, and every service measures its
host's offset with request/answer exchanges:

- the client reads its clock ``t1``, the reference reads ``t2`` on receipt and ``t3`` when it answers,
  the client reads ``t4`` on the answer; the reference clock minus ours, θ, then lies in
  ``[t3 − t4, t2 − t1]`` whatever the delays of the two ways (nothing travels back in time): centre
  ``((t2 − t1) + (t3 − t4)) / 2``, half-width half the round trip ``((t4 − t1) − (t3 − t2)) / 2``;
- each such interval widens with time by the clocks' worst drift (``clock.drift_ppm``); the estimate is
  the intersection of the last exchanges' intervals: its centre is the offset, its half-width a bound
  of the error (the uncertainty), never a guess;
- an exchange whose interval misses the current estimate means a clock stepped (NTP, an operator):
  the estimate starts again from it (counted in ``steps``);
- a service on the mocap host itself reads the same wall clock: its offset is exactly 0, with no
  uncertainty, however slow the exchanges.  It is on that host when the answer names the reference's
  host and it is ours, or when the answer comes from this very computer (the same kernel boot id, so the
  same ``CLOCK_REALTIME``: every process of a one-computer arena, whatever its config calls the hosts)
  and every exchange agrees with an offset of 0 — a process whose clock is faked (``faketime``) on the
  same computer fails that and is measured as any other.

:class:`ClockSync` runs the exchanges in its own thread (every ``clock.period`` s), publishes the
estimate as :class:`~arena_common.core.wire.ClockOffset` on ``arena/sys/clock/<host>/<service>``, and
warns in the log when the offset exceeds ``clock.max_offset``.  The reference itself (the mocap ingest,
``reference=True``) serves ``arena/sys/time`` and publishes state ``reference``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from arena_common.bus.session import Bus, Lane
from arena_common.core import keys, wire
from arena_common.core.config import ClockSpec

__all__ = ["ClockStatus", "ClockSync", "Estimate", "OffsetEstimator", "describe_offset"]

WINDOW = 16  # exchanges kept for the estimate
_BOOT_ID = Path("/proc/sys/kernel/random/boot_id")


def machine_id() -> str:
    """This computer's clock identity: the kernel's boot id (Linux), else "" (never the same as another's)."""
    try:
        return _BOOT_ID.read_text().strip()
    except OSError:
        return ""


MACHINE = machine_id()
SAME_HOST_EVERY = 10  # on the mocap host, exchange once in this many periods (the offset is 0 anyway)


@dataclass(frozen=True, slots=True)
class Estimate:
    """The reference clock minus ours lies within ``offset_ns`` ± ``unc_ns`` (as of the last exchange)."""

    offset_ns: int
    unc_ns: int
    rtt_ns: int  # round trip of the last exchange
    samples: int  # exchanges in the estimate

    @property
    def offset(self) -> float:
        """The offset, s."""
        return self.offset_ns * 1e-9

    @property
    def unc(self) -> float:
        """The bound of its error, s."""
        return self.unc_ns * 1e-9


class OffsetEstimator:
    """The intersection of the last ``window`` exchanges' intervals, each widened by ``drift_ppm``.

    Pure arithmetic on integer nanoseconds: feed it :meth:`add` (``t1``, ``t4`` and ``mono`` on our
    clocks, ``t2``, ``t3`` on the reference's), read :meth:`estimate`.
    """

    def __init__(self, window: int = WINDOW, drift_ppm: float = 200.0) -> None:
        if window < 1:
            raise ValueError("the estimator needs a window of at least one exchange")
        self.drift = drift_ppm * 1e-6
        self._samples: collections.deque[tuple[int, int, float, int]] = collections.deque(maxlen=window)
        self.steps = 0
        self.rejected = 0
        self.accepted = 0

    def add(self, t1: int, t2: int, t3: int, t4: int, mono: float) -> str | None:
        """Add one exchange; why it was refused (impossible times), else None."""
        if t4 < t1:
            self.rejected += 1
            return f"our clock went back during the exchange (t4 - t1 = {(t4 - t1) * 1e-9:.6f} s)"
        if t3 < t2:
            self.rejected += 1
            return f"the reference's clock went back while answering (t3 - t2 = {(t3 - t2) * 1e-9:.6f} s)"
        rtt = (t4 - t1) - (t3 - t2)
        if rtt < 0:
            self.rejected += 1
            return "the reference took longer to answer than the whole exchange (a clock stepped)"
        lo, hi = t3 - t4, t2 - t1
        current = self._bounds(mono)
        if current is not None and (lo > current[1] or hi < current[0]):
            self._samples.clear()  # it contradicts every earlier exchange: a clock stepped
            self.steps += 1
        self._samples.append((lo, hi, mono, rtt))
        self.accepted += 1
        return None

    def _bounds(self, mono: float) -> tuple[int, int] | None:
        if not self._samples:
            return None
        lo, hi = -(1 << 62), 1 << 62
        for s_lo, s_hi, s_mono, _ in self._samples:
            widen = int(self.drift * max(0.0, mono - s_mono) * 1e9)
            lo = max(lo, s_lo - widen)
            hi = min(hi, s_hi + widen)
        if lo > hi:  # drift beyond the assumed bound: trust the newest exchange alone
            s_lo, s_hi, _, _ = self._samples[-1]
            return s_lo, s_hi
        return lo, hi

    def estimate(self, mono: float) -> Estimate | None:
        """The offset and its bound at monotonic time ``mono`` (None before the first exchange)."""
        bounds = self._bounds(mono)
        if bounds is None:
            return None
        lo, hi = bounds
        return Estimate((lo + hi) // 2, (hi - lo + 1) // 2, self._samples[-1][3], len(self._samples))

    def reset(self) -> None:
        """Forget every exchange (the reference changed)."""
        self._samples.clear()


def describe_offset(offset: float, host: str, ref: str) -> str:
    """``this host (h2) is 0.300 s ahead of the mocap host (h1)`` for offset = reference − ours."""
    side = "ahead of" if offset < 0 else "behind"
    return f"the clock of {host} is {abs(offset):.3f} s {side} the mocap host's ({ref or '?'})"


@dataclass(frozen=True, slots=True)
class ClockStatus:
    """What a process knows of its host's clock: the state, the estimate, and what is wrong if anything."""

    state: str  # reference, ok, uncertain, unknown, no_reference
    estimate: Estimate | None
    ref: str
    problem: str | None  # why pose times cannot be trusted here (arming is refused), else None
    warning: str | None  # an offset beyond clock.max_offset (corrected, but the clocks need syncing)

    @property
    def offset_ns(self) -> int | None:
        """The correction to add to this host's clock to read the mocap host's (None: unknown)."""
        if self.state == "reference":
            return 0
        return None if self.estimate is None else self.estimate.offset_ns


SYNC_HINT = "synchronise the clocks with chrony or NTP (docs/lab.md)"


class ClockSync:
    """Measures this host's offset to the mocap host's clock (or, with ``reference``, is that clock).

    ``clock_ns`` is this host's wall clock (``time.time_ns``); the estimate is read with :meth:`status`
    from any thread.
    """

    def __init__(
        self,
        bus: Bus,
        host: str,
        service: str,
        spec: ClockSpec | None = None,
        *,
        reference: bool = False,
        clock_ns: Callable[[], int] = time.time_ns,
        log: logging.Logger | None = None,
        machine: str = MACHINE,
    ) -> None:
        self.bus = bus
        self.host = host
        self.service = service
        self.spec = spec or ClockSpec()
        self.reference = reference
        self.clock_ns = clock_ns
        self.log = log or logging.getLogger(f"arena.clock.{service}")
        self.estimator = OffsetEstimator(WINDOW, self.spec.drift_ppm)
        self.ref = host if reference else ""
        self.machine = machine  # the computer's clock identity (:func:`machine_id`)
        self._one_clock: bool | None = None  # the reference runs on this computer, on this clock
        self.answered = 0
        self.unanswered = 0
        self.last_reason = ""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pub = bus.stream_publisher(keys.clock(host, service), wire.ClockOffset, Lane.REPORT)
        self._warned: str | None = None
        # offset_ns runs for every pose: its value, valid until a monotonic time or the next exchange.
        self._cached: tuple[float, int | None] | None = None
        if reference:
            bus.serve(keys.TIME, self._answer, workers=1)

    # -- the reference -------------------------------------------------------------------------------
    def _answer(self, key: str, cmd: wire.Command) -> wire.CommandResult:
        t2 = self.clock_ns()
        if cmd.op != "time":
            return wire.CommandResult(False, "ERROR", f"{key} answers op 'time' only, not {cmd.op!r}")
        return wire.CommandResult(
            True,
            "ACCEPTED",
            value={"t2": t2, "host": self.host, "machine": self.machine, "t3": self.clock_ns()},
        )

    # -- measuring -----------------------------------------------------------------------------------
    def exchange(self, timeout: float = 1.0) -> str | None:
        """One request/answer with the reference; why it gave nothing, else None."""
        src = f"{self.host}/{self.service}"
        command = wire.Command(op="time", src=src, timeout=timeout)
        t1 = self.clock_ns()
        result = self.bus.request(keys.TIME, command, timeout, discovery=0.0)
        t4 = self.clock_ns()
        mono = time.monotonic()
        if not result.ok:
            with self._lock:
                self.unanswered += 1
            return f"no answer on {keys.TIME}: {result.result} {result.reason}".strip()
        problem = _times(result.value)
        if isinstance(problem, str):
            return f"bad answer on {keys.TIME}: {problem}"
        t2, t3, ref = problem
        with self._lock:
            if ref != self.ref:
                if self.ref:
                    self.log.warning("the mocap time reference moved from %s to %s", self.ref, ref)
                self.estimator.reset()
                self._one_clock = None
                self.ref = ref
            self._judge_one_clock(result.value.get("machine"), t1, t2, t3, t4)
            steps = self.estimator.steps
            refused = self.estimator.add(t1, t2, t3, t4, mono)
            self._cached = None
            self.answered += 1
            stepped = self.estimator.steps > steps
        if stepped:
            self.log.warning("a clock stepped (the exchange contradicts the estimate): measuring again")
        return refused

    def _judge_one_clock(self, machine: object, t1: int, t2: int, t3: int, t4: int) -> None:
        """Note whether this exchange shows the reference on this computer's clock (under the lock)."""
        here = isinstance(machine, str) and machine != "" and machine == self.machine
        agrees = t3 - t4 <= 0 <= t2 - t1  # an offset of 0 lies within this exchange's interval
        if here and agrees:
            if self._one_clock is None:
                self._one_clock = True
        elif self._one_clock is not False:
            if here:
                self.log.warning(
                    "the mocap time reference runs on this computer, but its clock disagrees with ours "
                    "(a faked or stepped clock): measuring the offset"
                )
            self._one_clock = False

    @property
    def same_host(self) -> bool:
        """Whether the reference answered from this very host (by name, or the same computer's clock):
        one wall clock, so the offset is exactly 0 (no estimate, whatever the round trips through a busy
        bus)."""
        return self.ref == self.host or bool(self._one_clock)

    def offset_ns(self) -> int | None:
        """The mocap host's clock minus ours now, ns (None while unknown); cheap, for every pose."""
        if self.reference or self.same_host:
            return 0
        now = time.monotonic()
        cached = self._cached
        if cached is not None and now < cached[0]:
            return cached[1]
        # Between exchanges every bound widens alike, so the centre stays: recomputed once a second at most.
        with self._lock:
            est = self.estimator.estimate(now)
        offset = None if est is None else est.offset_ns
        self._cached = (now + 1.0, offset)
        return offset

    def status(self, mono: float | None = None) -> ClockStatus:
        """The state of this host's clock now."""
        if self.reference:
            return ClockStatus("reference", Estimate(0, 0, 0, 0), self.host, None, None)
        mono = time.monotonic() if mono is None else mono
        with self._lock:
            est = self.estimator.estimate(mono)
            ref, answered = self.ref, self.answered
        spec, host = self.spec, self.host
        if est is not None and self.same_host:
            return ClockStatus("ok", Estimate(0, 0, est.rtt_ns, est.samples), ref, None, None)
        if est is None:
            if answered == 0 and self.unanswered > 0:
                problem = (
                    f"clock: no mocap time reference answers on {keys.TIME}, so the offset of the clock of "
                    f"{host} to the mocap host's is unknown (is the mocap ingest running?)"
                )
                return ClockStatus("no_reference", None, ref, problem, None)
            problem = (
                f"clock: the offset of the clock of {host} to the mocap host's ({ref}) is not measured yet"
            )
            return ClockStatus("unknown", None, ref, problem, None)
        warning = None
        if abs(est.offset) > spec.max_offset:
            warning = (
                f"clock: {describe_offset(est.offset, host, ref)} (±{est.unc * 1e3:.1f} ms): pose times are "
                f"corrected, but {SYNC_HINT}"
            )
        if est.unc > spec.max_uncertainty:
            problem = (
                f"clock: the offset of the clock of {host} to the mocap host's ({ref}) is uncertain "
                f"(±{est.unc * 1e3:.1f} ms, more than clock.max_uncertainty {spec.max_uncertainty * 1e3:g} "
                f"ms; last round trip {est.rtt_ns * 1e-6:.1f} ms): pose ages cannot be trusted; check the "
                f"network to the mocap host and {SYNC_HINT}"
            )
            return ClockStatus("uncertain", est, ref, problem, warning)
        return ClockStatus("ok", est, ref, None, warning)

    def payload(self, status: ClockStatus | None = None) -> wire.ClockOffset:
        """The :class:`~arena_common.core.wire.ClockOffset` of this host now."""
        st = status or self.status()
        est = st.estimate
        return wire.ClockOffset(
            t=self.clock_ns(),
            host=self.host,
            service=self.service,
            state=st.state,
            ref=st.ref,
            off=None if est is None else est.offset,
            unc=None if est is None else est.unc,
            rtt=None if est is None or self.reference else est.rtt_ns * 1e-9,
            n=self.answered,
            steps=self.estimator.steps,
        )

    def publish(self) -> ClockStatus:
        """Publish the estimate now (and log a warning when the offset crossed ``max_offset``)."""
        st = self.status()
        self._pub.put(self.payload(st))
        text = (st.warning or st.problem) if st.state != "no_reference" else None
        said = None if text is None else f"{st.state} {st.warning is not None}"
        if said != self._warned:  # once per change of state, not for every new figure
            if text is not None:
                self.log.warning("%s", text)
            elif self._warned is not None:
                self.log.info("clock: within %.1f ms of the mocap host's again", self.spec.max_offset * 1e3)
            self._warned = said
        return st

    def _run(self) -> None:
        period = self.spec.period
        tick = 0
        while not self._stop.is_set():
            started = time.monotonic()
            tick += 1
            # On the mocap host itself there is nothing to measure: one exchange in SAME_HOST_EVERY only
            # watches that the reference is still here.
            if not self.reference and (not self.same_host or tick % SAME_HOST_EVERY == 0):
                try:
                    reason = self.exchange(timeout=min(1.0, max(period, 0.2)))
                except Exception as exc:  # the bus is closing; never take the process down
                    reason = f"{type(exc).__name__}: {exc}"
                self.last_reason = reason or ""
            try:
                self.publish()
            except Exception as exc:  # the bus is closing
                self.log.debug("clock offset not published: %s", exc)
            self._stop.wait(max(0.0, period - (time.monotonic() - started)))

    def start(self) -> ClockSync:
        """Measure (and publish) in a background thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"{self.service}:clock", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread (the bus endpoints close with the bus)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)


def _times(value: Mapping[str, Any]) -> tuple[int, int, str] | str:
    """(t2, t3, reference host) of an answer, or what is wrong with it."""
    t2, t3, ref = value.get("t2"), value.get("t3"), value.get("host")
    for name, v in (("t2", t2), ("t3", t3)):
        if isinstance(v, bool) or not isinstance(v, int):
            return f"{name} must be an integer time in ns, got {v!r}"
    if not isinstance(ref, str) or not ref:
        return f"host must be the reference's host name, got {ref!r}"
    assert isinstance(t2, int) and isinstance(t3, int)
    return t2, t3, ref
