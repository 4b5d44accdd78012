"""TIMESYNC: answering the autopilot at once, and measuring the link's round trip and offset.

How PX4 v1.16 uses our answers (``src/modules/mavlink/mavlink_timesync.cpp``, ``src/lib/timesync/Timesync.cpp``
and ``Timesync.hpp``): it asks at 10 Hz on the offboard link (the TIMESYNC stream), takes an answer's ``tc1``
(ns, our clock) and echoed ``ts1`` (ns, its own) as one offset sample when the round trip is under 10 ms
(``MAX_RTT_SAMPLE``), and trusts its offset estimate only after 500 accepted samples
(``CONVERGENCE_WINDOW``): about 50 s after we start answering.  Until then it stamps every vision sample
with its arrival time instead of our ``time_usec``; five samples in a row more than 100 ms off a converged
estimate (a step of our clock) start it over.  An answer's TIMESYNC target fields are left 0 (broadcast):
MAVLink 2 drops trailing zero bytes, so the frame is the same as one without those extension fields, and
PX4 v1.16 SITL converged on it after exactly 500 requests (measured).

Our answers carry **the autopilot's own clock**, as we estimate it (MAVSDK answers with its "autopilot
time" the same way), not this host's: PX4's filter then sees an offset that stays put, whatever either
clock does.  Answering with this host's clock made PX4 SITL reset its filter ("time jump"): its lockstep
clock runs 1–3 % slower than the wall clock, at a rate that changes with the machine's load, and stops
now and then (measured: docs/px4.md), which PX4's filter, tuned for two crystals, cannot follow; a step
of this host's wall clock (NTP) would do the same on a real vehicle.  The estimate is a least-squares line
(offset and skew) through our last :data:`WINDOW` round trips on this host's monotonic clock; we ask
each time PX4 asks (10 Hz) and once a second, and answer PX4 only once :data:`MIN_SAMPLES` were measured
(an answer before would start its filter on a clock that is about to jump).  Vision ``time_usec`` is
stamped on the same estimate, so PX4 maps it onto its clock by an offset of about 0.
"""

from __future__ import annotations

import collections
import statistics
import time
from collections.abc import Callable
from typing import Any

from arena_common.mavlink import px4
from arena_common.mavlink.link import MavlinkLink

PX4_CONVERGENCE_WINDOW = px4.TIMESYNC_CONVERGENCE_WINDOW  # accepted samples before PX4 uses its offset
PX4_MAX_RTT_S = px4.TIMESYNC_MAX_RTT_US * 1e-6  # PX4 ignores samples with a longer round trip
MIN_ROUND_TRIPS = 8  # of our own before saying whether PX4 can take our clock
WINDOW = 8  # round trips the clock estimate is fitted through (at 10 Hz, PX4 SITL's wander is followed)
MIN_SAMPLES = 3  # round trips measured before PX4's requests are answered
STEP_NS = 20_000_000  # a sample this far off the fit (and further than its round trip) is a step
MIN_SPAN_NS = 300_000_000  # the skew is fitted through round trips spanning this much at least


class AutopilotClock:
    """The autopilot's clock as seen from ours: offset and skew fitted through recent round trips.

    A round trip gives one sample: the autopilot's time ``tc1`` against the midpoint of our send and
    receive times.  Samples whose round trip is much longer than the window's fastest are left out (their
    midpoint is uncertain by half of it).  All times are ns on our clock (monotonic).
    """

    def __init__(self, window: int = WINDOW) -> None:
        self.samples: collections.deque[tuple[int, int, int]] = collections.deque(maxlen=window)
        self._t0 = 0  # the fit: offset o0 at our time t0, and skew (ns of offset per ns)
        self._o0 = 0.0
        self.skew = 0.0
        self.steps = 0  # steps of either clock seen
        self.known = False  # MIN_SAMPLES round trips were fitted since the last clear (a step keeps it)
        self.skew_fitted = False  # through round trips spanning MIN_SPAN_NS: from then on steps are told

    def add(self, t_mid: int, offset: int, rtt: int) -> None:
        """One round trip: its midpoint on our clock, the autopilot's clock minus ours then, its length.
        A sample further off the fit than :data:`STEP_NS` and its own round trip is a step of either
        clock (SITL's stopped): the fit starts over from it, keeping the skew (told once one was fitted)."""
        if self.skew_fitted and abs(offset - self.offset_at(t_mid)) > max(STEP_NS, rtt):
            self.samples.clear()
            self.steps += 1
        self.samples.append((t_mid, offset, rtt))
        self.known = self.known or len(self.samples) >= MIN_SAMPLES
        fastest = min(r for _, _, r in self.samples)
        good = [(t, o) for t, o, r in self.samples if r <= 2 * fastest + 1_000_000]
        t0 = good[-1][0]
        ts = [t - t0 for t, _ in good]
        os_ = [float(o) for _, o in good]
        t_mean, o_mean = statistics.fmean(ts), statistics.fmean(os_)
        if len(good) >= 3 and ts[-1] - ts[0] >= MIN_SPAN_NS:  # else a few ms of noise would tilt it
            var = sum((t - t_mean) ** 2 for t in ts)
            self.skew = sum((t - t_mean) * (o - o_mean) for t, o in zip(ts, os_, strict=True)) / var
            self.skew_fitted = True
        self._t0, self._o0 = t0, o_mean - self.skew * t_mean

    def offset_at(self, t: int) -> int:
        """The autopilot's clock minus ours at our time ``t`` (ns), from the fit (extrapolated)."""
        return int(self._o0 + self.skew * (t - self._t0))

    def clear(self) -> None:
        """Forget everything (the autopilot rebooted)."""
        self.samples.clear()
        self.skew = 0.0
        self.known = self.skew_fitted = False


class TimeSync:
    """Answers the autopilot's TIMESYNC requests with its own clock, and measures round trip and offset.

    ``clock_ns`` is our clock for round trips and answers (monotonic by default); ``wall_ns`` the clock
    pose times are on (:meth:`autopilot_us` converts them).  The offset is the autopilot's clock minus
    ours (:class:`AutopilotClock`).  ``answered_since_reset`` counts the autopilot's requests answered
    since the gateway started or the autopilot rebooted; :attr:`autopilot_converged` says whether PX4 has
    had enough of them to use our stamps (its own view: ``timesync_status`` / vision ``timestamp_sample``
    in its log).  ``unanswered`` counts its requests met before our estimate stood (not answered).
    """

    def __init__(
        self,
        link: MavlinkLink,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.link = link
        self.clock_ns = clock_ns
        self.wall_ns = wall_ns
        self.autopilot = AutopilotClock()
        self._pending: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._rtts: collections.deque[int] = collections.deque(maxlen=16)  # ns, ours
        self.answered = 0
        self.answered_since_reset = 0
        self.unanswered = 0
        self.rtt_s: float | None = None
        self.offset_s: float | None = None
        self.rtt_min_s: float | None = None
        self.jitter_s: float | None = None
        self.measured = 0  # answers to our own requests measured
        self.accepted_since_reset = 0  # answers given while the link's round trip was under PX4's limit

    @property
    def locked(self) -> bool:
        """Whether the autopilot's clock is known (:data:`MIN_SAMPLES` round trips since the last reset)."""
        return self.autopilot.known

    def autopilot_ns(self, t: int | None = None) -> int | None:
        """Our time ``t`` (ns, :attr:`clock_ns`; now when None) on the autopilot's clock; None before
        :attr:`locked`."""
        if not self.locked:
            return None
        t = self.clock_ns() if t is None else t
        return t + self.autopilot.offset_at(t)

    def autopilot_us(self, t_wall_ns: int) -> int | None:
        """A time on this host's wall clock (a pose's, ns) on the autopilot's clock, µs: how vision is
        stamped.  None before :attr:`locked` (PX4 then stamps on arrival: it has had no answer)."""
        ns = self.autopilot_ns(t_wall_ns + (self.clock_ns() - self.wall_ns()))
        return None if ns is None else ns // 1000

    @property
    def autopilot_converged(self) -> bool:
        """Whether PX4 has had :data:`PX4_CONVERGENCE_WINDOW` answers it could accept since the gateway
        started or it rebooted (each given while the link's last measured round trip was under
        :data:`PX4_MAX_RTT_S`, or before any was measured): from then on it takes our vision stamps, before
        it uses their arrival time.  An estimate: PX4 judges each answer by its own round trip, which ours
        measures on the same link."""
        return self.accepted_since_reset >= PX4_CONVERGENCE_WINDOW

    @property
    def px4_can_converge(self) -> bool | None:
        """Whether PX4 can take our clock over this link: None until :data:`MIN_ROUND_TRIPS` round trips
        were measured (since the gateway started or the autopilot rebooted); then whether at least half of
        the last 16 were under :data:`PX4_MAX_RTT_S` (PX4 drops the others: over a link slower than that,
        it stamps vision on arrival for good)."""
        if len(self._rtts) < MIN_ROUND_TRIPS:
            return None
        fast = sum(1 for rtt in self._rtts if rtt < PX4_MAX_RTT_S * 1e9)
        return 2 * fast >= len(self._rtts)

    @property
    def rtt_median_s(self) -> float | None:
        """The median of the last 16 round trips (s); None before any."""
        if not self._rtts:
            return None
        return statistics.median(self._rtts) * 1e-9

    @property
    def stamps(self) -> str:
        """Whose clock stamps vision in the autopilot: ``ours`` (PX4 took the gateway's clock), ``arrival``
        (it stamps a sample when it arrives: the link's delay is then in every vision sample's age), or
        ``""`` before any round trip was measured."""
        if self.autopilot_converged:
            return "ours"
        return "" if self.rtt_s is None else "arrival"

    def fields(self) -> dict[str, Any]:
        """The gateway's ``timesync`` telemetry: round trip (last, fastest of 16) and offset [s], the
        autopilot clock's skew and the steps of either clock followed, answers given (and requests left
        unanswered before our estimate stood), and whether PX4 should by now take our vision stamps
        (:attr:`autopilot_converged`)."""
        return {
            "rtt": self.rtt_s,
            "rtt_min": self.rtt_min_s,
            "offset": self.offset_s,
            "skew": self.autopilot.skew if self.locked else None,
            "steps": self.autopilot.steps,
            "jitter": self.jitter_s,
            "answered": self.answered,
            "unanswered": self.unanswered,
            "autopilot_converged": self.autopilot_converged,
        }

    def on_timesync(self, msg: Any, now: float) -> None:
        """A TIMESYNC from the autopilot.  A request (``tc1`` 0) is answered at once with its own clock in
        ``tc1`` and its ``ts1`` echoed (both ns), once our estimate stands; and we ask back, so the estimate
        follows its clock at the rate it asks.  An answer to one of ours updates round trip and offset."""
        if msg.tc1 == 0:
            tc1 = self.autopilot_ns()
            if tc1 is None:
                self.unanswered += 1
            else:
                self.answered += 1  # counted first: whoever sees the answer sees it counted
                self.answered_since_reset += 1
                if self.rtt_s is None or self.rtt_s < PX4_MAX_RTT_S:
                    self.accepted_since_reset += 1
                # tc1 0 would read as a request: a clock estimated just after PX4's boot may be there.
                self.link.send(self.link.mav.timesync_encode(max(1, tc1), msg.ts1))
            self.request()
            return
        if msg.ts1 not in self._pending:
            return  # an answer to someone else (a GCS through the forwarder)
        del self._pending[msg.ts1]
        t_now = self.clock_ns()
        rtt = t_now - msg.ts1
        if rtt < 0:
            return
        if self._rtts:  # RFC 3550's interarrival jitter, over round trips: J += (|D| - J) / 16
            change = abs(rtt - self._rtts[-1]) * 1e-9
            self.jitter_s = change if self.jitter_s is None else self.jitter_s + (change - self.jitter_s) / 16
        t_mid = (msg.ts1 + t_now) // 2
        self._rtts.append(rtt)
        self.autopilot.add(t_mid, msg.tc1 - t_mid, rtt)
        self.measured += 1
        self.rtt_s = rtt * 1e-9
        self.rtt_min_s = min(self._rtts) * 1e-9
        self.offset_s = self.autopilot.offset_at(t_now) * 1e-9

    def request(self) -> None:
        """Send one TIMESYNC request (tc1 = 0, ts1 = our clock)."""
        ts = self.clock_ns()
        self._pending[ts] = None
        while len(self._pending) > 8:
            self._pending.popitem(last=False)
        self.link.send(self.link.mav.timesync_encode(0, ts))

    def reset(self) -> None:
        """Forget the measurements (the autopilot rebooted: its clock and its TIMESYNC filter restarted)."""
        self._rtts.clear()
        self.autopilot.clear()
        self.offset_s = None
        self.jitter_s = None
        self.answered_since_reset = 0
        self.accepted_since_reset = 0
