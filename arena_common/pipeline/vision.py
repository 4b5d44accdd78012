"""The vision filter: which of a vehicle's poses go to its autopilot, shared by the downsampler and the
frame transform (which can decimate in-process, see ``[pipeline] decimate``).

Each pose goes through, in order:

1. validity — poses Motive lost (``ok`` false) are never forwarded;
2. a :class:`~arena_common.geometry.filters.JumpGate` — poses that moved or turned faster than physically possible
   are dropped and counted; when the gate accepts a new track (re-acquired after a jump, or after a long
   gap) the vision reset counter ``rc`` is bumped (mod 256) so the gateway bumps ODOMETRY's
   ``reset_counter`` and PX4 resets onto the new pose instead of fusing a jump;
3. a :class:`~arena_common.geometry.filters.TimeDecimator` at the vehicle's vision rate — chosen by measurement
   time, not by count, so the output stays evenly spaced under jittery input.

Nothing is ever sent twice and nothing is sent without an input: when poses stop, vision stops, which is
what lets PX4 detect position loss. Velocities computed across a dropped outlier are unreliable, so the
vision poses of the next :data:`VELOCITY_SETTLE_S` carry ``vok=False``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

from arena_common.core import wire
from arena_common.geometry.filters import JumpGate, TimeDecimator

if TYPE_CHECKING:
    from arena_common.runtime.service import Service

__all__ = ["RESTART_AFTER_S", "VELOCITY_SETTLE_S", "Decision", "Outcome", "VisionFilter", "account"]

VELOCITY_SETTLE_S = 0.1  # velocities are marked unknown this long after a dropped outlier or a reset
RESTART_AFTER_S = 1.0  # a timestamp this far behind the last accepted one means the source restarted
_ZERO3: wire.Vec3 = (0.0, 0.0, 0.0)


class Outcome(StrEnum):
    """What :meth:`VisionFilter.process` did with one pose."""

    SENT = "sent"  # forwarded as vision
    INVALID = "invalid"  # not tracked: never forwarded
    SKIPPED = "skipped"  # accepted, but not the sample the decimator wanted
    OUTLIER = "outlier"  # dropped by the jump gate


@dataclass(frozen=True)
class Decision:
    """The result of one :meth:`VisionFilter.process` call: the vision pose to send, if any, and why."""

    outcome: Outcome
    vision: wire.Pose | None = None
    reason: str = ""  # the gate's reject reason for an outlier
    reset: bool = False  # this pose started a new track (rc was bumped)


@dataclass
class VisionFilter:
    """Validity check, jump gate and time decimation of one vehicle's pose stream (single-threaded)."""

    rate_hz: float = 50.0
    gate: JumpGate = field(default_factory=JumpGate)
    settle_s: float = VELOCITY_SETTLE_S
    restart_after_s: float = RESTART_AFTER_S
    rc: int = 0
    decimator: TimeDecimator = field(init=False)
    _last_t: int | None = field(default=None, init=False, repr=False)
    _settle_until: int = field(default=-(2**62), init=False, repr=False)

    def __post_init__(self) -> None:
        self.decimator = TimeDecimator(self.rate_hz, self.restart_after_s)

    def process(self, pose: wire.Pose, tp: int | None = None) -> Decision:
        """Judge one pose; the returned decision carries the vision pose to publish when there is one."""
        if not pose.ok:
            return Decision(Outcome.INVALID)
        t = pose.t
        if self._last_t is not None and self._last_t - t > int(self.restart_after_s * 1e9):
            self.gate.reset()  # the source's clock restarted: the old track says nothing about this one
            self._last_t = None
            self._bump()
        fresh_track = self._last_t is None and self.gate.accepted > 0
        decision = self.gate.check(t, pose.p, pose.q)
        if not decision.accepted:
            self._settle_until = t + int(self.settle_s * 1e9)
            return Decision(Outcome.OUTLIER, reason=decision.reason.value if decision.reason else "")
        self._last_t = t
        reset = decision.reset or fresh_track
        if decision.reset:
            self._bump()
        if reset:
            self._settle_until = t + int(self.settle_s * 1e9)
        if not self.decimator.offer(t):
            return Decision(Outcome.SKIPPED, reset=reset)
        vok = pose.vok and t >= self._settle_until
        out = pose.replace(
            rc=self.rc,
            vok=vok,
            v=pose.v if vok else _ZERO3,
            w=pose.w if vok else _ZERO3,
            tp=wire.now_ns() if tp is None else tp,
        )
        return Decision(Outcome.SENT, out, reset=reset)

    def _bump(self) -> None:
        self.rc = (self.rc + 1) % 256


def account(svc: Service, vehicle: str, pose: wire.Pose, d: Decision, rc: int, prefix: str = "") -> None:
    """Count (and log resets and refusals of) one :meth:`VisionFilter.process` decision, sent or not.

    Counters and rejection reasons are ``prefix`` + ``resets``/``skipped``/``invalid``/``stale``/
    ``outlier_<why>`` (the transform uses ``vision_`` to keep them apart from its own).  The sent ones
    are counted by the caller, which publishes them.
    """
    if d.reset:
        svc.stats.count(f"{prefix}resets")
        svc.log.info("%s: new track at t=%d: reset counter %d", vehicle, pose.t, rc)
    if d.outcome is Outcome.OUTLIER:
        # A timestamp not after the last accepted one is stale (or a duplicate), not an outlier.
        reason = "stale" if d.reason == "stale" else f"outlier_{d.reason}"
        svc.reject(f"{prefix}{reason}", f"{vehicle}: pose at t={pose.t} dropped ({d.reason})")
    elif d.outcome is not Outcome.SENT:
        svc.stats.count(f"{prefix}{d.outcome.value}")
