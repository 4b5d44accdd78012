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
"""

from __future__ import annotations

import collections
import statistics
import time
from collections.abc import Callable
from typing import Any

from arena_common.mavlink.link import MavlinkLink

PX4_CONVERGENCE_WINDOW = 500  # accepted samples before PX4 uses its offset (Timesync.hpp)
PX4_MAX_RTT_S = 0.010  # PX4 ignores samples with a longer round trip (Timesync.hpp MAX_RTT_SAMPLE)
MIN_ROUND_TRIPS = 8  # of our own (one a second) before saying whether PX4 can take our clock


class TimeSync:
    """Answers the autopilot's TIMESYNC requests at once, and measures round trip and offset with our own.

    Our clock is ``clock_ns`` (wall-clock ns by default): the same clock stamps vision ``time_usec``.
    The offset is the autopilot's clock minus ours, from the fastest of the last 16 round trips.
    ``answered_since_reset`` counts the autopilot's requests answered since the gateway started or the
    autopilot rebooted; :attr:`autopilot_converged` says whether PX4 has had enough of them to use our
    stamps (its own view: ``timesync_status`` / vision ``timestamp_sample`` in its log).
    """

    def __init__(self, link: MavlinkLink, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.link = link
        self.clock_ns = clock_ns
        self._pending: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._samples: collections.deque[tuple[int, int]] = collections.deque(maxlen=16)
        self.answered = 0
        self.answered_since_reset = 0
        self.rtt_s: float | None = None
        self.offset_s: float | None = None
        self.rtt_min_s: float | None = None
        self.jitter_s: float | None = None
        self.measured = 0  # answers to our own requests measured
        self.accepted_since_reset = 0  # answers given while the link's round trip was under PX4's limit

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
        if len(self._samples) < MIN_ROUND_TRIPS:
            return None
        fast = sum(1 for rtt, _ in self._samples if rtt < PX4_MAX_RTT_S * 1e9)
        return 2 * fast >= len(self._samples)

    @property
    def rtt_median_s(self) -> float | None:
        """The median of the last 16 round trips (s); None before any."""
        if not self._samples:
            return None
        return statistics.median(rtt for rtt, _ in self._samples) * 1e-9

    @property
    def stamps(self) -> str:
        """Whose clock stamps vision in the autopilot: ``ours`` (PX4 took the gateway's clock), ``arrival``
        (it stamps a sample when it arrives: the link's delay is then in every vision sample's age), or
        ``""`` before any round trip was measured."""
        if self.autopilot_converged:
            return "ours"
        return "" if self.rtt_s is None else "arrival"

    def fields(self) -> dict[str, Any]:
        """The gateway's ``timesync`` telemetry: round trip (last, fastest of 16) and offset [s], answers
        given, and whether PX4 should by now take our vision stamps (:attr:`autopilot_converged`)."""
        return {
            "rtt": self.rtt_s,
            "rtt_min": self.rtt_min_s,
            "offset": self.offset_s,
            "jitter": self.jitter_s,
            "answered": self.answered,
            "autopilot_converged": self.autopilot_converged,
        }

    def on_timesync(self, msg: Any, now: float) -> None:
        """A TIMESYNC from the autopilot: a request (``tc1`` 0) is answered at once with our clock in
        ``tc1`` and its ``ts1`` echoed (both ns); an answer to one of ours updates round trip and offset."""
        if msg.tc1 == 0:
            self.answered += 1  # counted first: whoever sees the answer sees it counted
            self.answered_since_reset += 1
            if self.rtt_s is None or self.rtt_s < PX4_MAX_RTT_S:  # unmeasured yet: as PX4 on loopback
                self.accepted_since_reset += 1
            self.link.send(self.link.mav.timesync_encode(self.clock_ns(), msg.ts1))
            return
        if msg.ts1 not in self._pending:
            return  # an answer to someone else (a GCS through the forwarder)
        del self._pending[msg.ts1]
        t_now = self.clock_ns()
        rtt = t_now - msg.ts1
        if rtt < 0:
            return
        if self._samples:  # RFC 3550's interarrival jitter, over round trips: J += (|D| - J) / 16
            change = abs(rtt - self._samples[-1][0]) * 1e-9
            self.jitter_s = change if self.jitter_s is None else self.jitter_s + (change - self.jitter_s) / 16
        self._samples.append((rtt, msg.tc1 - (msg.ts1 + t_now) // 2))
        self.measured += 1
        best = min(self._samples)
        self.rtt_s = rtt * 1e-9
        self.rtt_min_s = best[0] * 1e-9
        self.offset_s = best[1] * 1e-9

    def request(self) -> None:
        """Send one TIMESYNC request (tc1 = 0, ts1 = our clock)."""
        ts = self.clock_ns()
        self._pending[ts] = None
        while len(self._pending) > 8:
            self._pending.popitem(last=False)
        self.link.send(self.link.mav.timesync_encode(0, ts))

    def reset(self) -> None:
        """Forget the measurements (the autopilot rebooted: its clock and its TIMESYNC filter restarted)."""
        self._samples.clear()
        self.offset_s = None
        self.jitter_s = None
        self.answered_since_reset = 0
        self.accepted_since_reset = 0
