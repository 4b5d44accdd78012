"""``EKF2_EV_DELAY`` as the link needs it: 0 where PX4 takes the gateway's clock, the measured delay where
it cannot — and a warning when the link drifts from what the autopilot has.

The arena stamps every vision sample with the camera's exposure time on the gateway's clock, which PX4 maps
to its own through TIMESYNC; then ``EKF2_EV_DELAY`` holds only what those stamps miss: 0 (docs/px4.md).
Over a slow link (a radio, Wi-Fi) PX4 drops every TIMESYNC round trip of 10 ms or more, never converges,
and stamps each sample when it arrives instead (:attr:`TimeSync.px4_can_converge`): the sample is then
older than its stamp by the pose's age when it left the gateway plus the link's one-way delay, and that
is what ``EKF2_EV_DELAY`` must say.  :class:`EvDelay` sets the parameter's wanted value before every
check (so ``arena px4 check`` judges it and ``arena px4 setup`` writes it, saying why), and watches the
link: when the delay it needs drifts from the value the autopilot has by more than the tolerance, an
event says so, once, until it is back.  A wrong value makes PX4 fly worse, not unsafely: the check
reports it (``advice``) and setup writes it, but arming is never refused for it.
"""

from __future__ import annotations

import math

from arena_common.gateway.events import EventSink
from arena_common.gateway.timesync import PX4_MAX_RTT_S, TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink import px4
from arena_common.mavlink.protocols import SetupChecker

__all__ = ["EV_DELAY", "EvDelay", "tolerance_ms"]

EV_DELAY = "EKF2_EV_DELAY"
WATCH_PERIOD = 5.0  # s between looks at the link's drift


def tolerance_ms(want_ms: float) -> float:
    """How far ``EKF2_EV_DELAY`` may be from the delay the link needs and still be right: 10 ms (at the
    arena's speeds, up to 1 m/s, at most 1 cm of position: below a hover's wander; and a busy computer's
    loopback, a few ms, stays within it), or a quarter of the delay when larger (a radio's delay varies
    by that much from minute to minute)."""
    return max(10.0, 0.25 * want_ms)


class EvDelay:
    """The ``EKF2_EV_DELAY`` a vehicle's link needs, set into its :class:`SetupChecker` before each check,
    and the drift watch."""

    def __init__(
        self, name: str, timesync: TimeSync, vision: VisionSender, setup: SetupChecker, events: EventSink
    ) -> None:
        self.name = name
        self.timesync = timesync
        self.vision = vision
        self.setup = setup
        self.events = events
        self.default_ms = float(setup.required[EV_DELAY][0])
        self.drifted = False
        self._next_watch = 0.0
        setup.before = self.prepare
        setup.advisory.add(EV_DELAY)  # a slow link flies worse, not unsafely: told, never refused

    def need(self) -> tuple[float, str] | None:
        """The delay (ms) the link needs and why, in words: 0 while PX4 can take our clock, half the round
        trip plus a pose's age as it leaves while it cannot; None until the link was measured."""
        can = self.timesync.px4_can_converge
        rtt = self.timesync.rtt_median_s
        if can is None or rtt is None:
            return None
        if can:
            return (
                self.default_ms,
                f"this link's round trip is {rtt * 1e3:.0f} ms: PX4 takes the gateway's clock",
            )
        age = self.vision.sent_age_median() or 0.0
        why = (
            f"this link's round trip is {rtt * 1e3:.0f} ms (PX4 drops round trips of {PX4_MAX_RTT_S * 1e3:.0f} "
            f"ms or more and stamps vision on arrival): half of it plus a pose's {age * 1e3:.0f} ms age as it "
            "leaves the gateway"
        )
        return float(round((rtt / 2.0 + age) * 1000.0)), why

    def prepare(self) -> None:
        """Before a check: the wanted value and its tolerance (anything while the link is unmeasured)."""
        need = self.need()
        want = self.default_ms if need is None else need[0]
        self.setup.required[EV_DELAY] = (want, px4.MAV_PARAM_TYPE_REAL32)
        self.setup.tolerance[EV_DELAY] = math.inf if need is None else tolerance_ms(want)
        if need is None:
            self.setup.notes.pop(EV_DELAY, None)
        else:
            self.setup.notes[EV_DELAY] = f"{EV_DELAY} {want:g} ms: {need[1]}"

    def watch(self, now: float) -> None:
        """Every :data:`WATCH_PERIOD` s: an event when the delay the link needs drifted from the value the
        autopilot was last read to have (and once when it is back within the tolerance)."""
        if now < self._next_watch:
            return
        self._next_watch = now + WATCH_PERIOD
        row = self.setup.report.get("params", {}).get(EV_DELAY)
        need = self.need()
        if row is None or row.get("have") is None or need is None:
            return
        (want, why), have = need, float(row["have"])
        off = abs(have - want) > tolerance_ms(want)
        if off and not self.drifted:
            self.events.emit(
                "setup",
                f"the link's delay drifted: {EV_DELAY} is {have:g} ms, this link needs {want:g} ms "
                f"({why}): run `arena px4 setup {self.name}` on the ground",
                4,
                have=have,
                want=want,
            )
        elif not off and self.drifted:
            self.events.emit("setup", f"the link's delay is back within {EV_DELAY} ({have:g} ms)", 6)
        self.drifted = off
