"""TIMESYNC: answering the autopilot at once, and measuring the link's round trip and offset."""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from typing import Any

from arena_common.mavlink.link import MavlinkLink


class TimeSync:
    """Answers the autopilot's TIMESYNC requests at once, and measures round trip and offset with our own.

    Our clock is ``clock_ns`` (wall-clock ns by default): the same clock stamps vision ``time_usec``.
    The offset is the autopilot's clock minus ours, from the fastest of the last 16 round trips.
    """

    def __init__(self, link: MavlinkLink, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.link = link
        self.clock_ns = clock_ns
        self._pending: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._samples: collections.deque[tuple[int, int]] = collections.deque(maxlen=16)
        self.answered = 0
        self.rtt_s: float | None = None
        self.offset_s: float | None = None
        self.rtt_min_s: float | None = None

    def on_timesync(self, msg: Any, now: float) -> None:
        if msg.tc1 == 0:
            self.link.send(self.link.mav.timesync_encode(self.clock_ns(), msg.ts1))
            self.answered += 1
            return
        if msg.ts1 not in self._pending:
            return  # an answer to someone else (a GCS through the forwarder)
        del self._pending[msg.ts1]
        t_now = self.clock_ns()
        rtt = t_now - msg.ts1
        if rtt < 0:
            return
        self._samples.append((rtt, msg.tc1 - (msg.ts1 + t_now) // 2))
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
        """Forget the measurements (the autopilot rebooted: its clock restarted)."""
        self._samples.clear()
        self.offset_s = None
