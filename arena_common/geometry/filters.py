"""Pose stream filters: velocity estimation, time-based decimation and outlier (jump) rejection.

All filters are driven by the caller's timestamps (integer nanoseconds, the pose's measurement time), never
by the wall clock, so they behave identically live, in replay and in tests. They are plain single-threaded
objects: one instance per vehicle stream.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

from arena_common.geometry.frames import Quat, Vec3, quat_angle, quat_multiply

__all__ = [
    "FilterError",
    "GateDecision",
    "JumpGate",
    "RejectReason",
    "TimeDecimator",
    "Velocity",
    "VelocityEstimator",
]

_NAN3: Vec3 = (math.nan, math.nan, math.nan)


class FilterError(ValueError):
    """Invalid filter configuration or input (non-positive rate, malformed vector...)."""


def _positive(value: float, what: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise FilterError(f"{what} must be a positive finite number, got {value!r}")
    return v


def _finite3(v: Sequence[float], what: str) -> Vec3 | None:
    """The vector as floats, or None if it has a non-finite component. Raises for a wrong length."""
    if len(v) != 3:
        raise FilterError(f"{what} must have 3 components, got {len(v)}")
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    if not math.isfinite(x + y + z):
        return None
    return (x, y, z)


def _finite4(q: Sequence[float], what: str) -> Quat | None:
    if len(q) != 4:
        raise FilterError(f"{what} must have 4 components (w, x, y, z), got {len(q)}")
    w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    n2 = w * w + x * x + y * y + z * z
    if not math.isfinite(n2) or n2 < 1e-12:
        return None
    inv = 1.0 / math.sqrt(n2)
    return (w * inv, x * inv, y * inv, z * inv)


# --------------------------------------------------------------------------------------------------
# Velocity
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Velocity:
    """One velocity estimate. When ``valid`` is False both vectors are NaN (unknown, not zero)."""

    t_ns: int
    valid: bool
    linear_ned: Vec3
    angular_frd: Vec3


class VelocityEstimator:
    """Linear (world NED, m/s) and angular (body FRD, rad/s) velocity from a pose stream.

    Finite differences between consecutive samples, smoothed by a first-order low-pass filter with cut-off
    ``cutoff_hz`` discretised on the real sample interval (``α = 1 − exp(−dt/τ)``, ``τ = 1/(2π f_c)``), so
    jittery or changing input rates need no retuning. The filter starts from the first difference (no
    ramp-up from zero).

    The estimate is invalid until two consecutive valid samples have been seen; an invalid pose, a gap
    longer than ``max_gap_s`` or a timestamp going backwards restart it (the sample that restarts it becomes
    the first one). A repeated timestamp is ignored.
    """

    def __init__(
        self, cutoff_hz: float = 15.0, max_gap_s: float = 0.1, angular_cutoff_hz: float | None = None
    ) -> None:
        self._tau = 1.0 / (2.0 * math.pi * _positive(cutoff_hz, "cutoff_hz"))
        ang = cutoff_hz if angular_cutoff_hz is None else angular_cutoff_hz
        self._tau_ang = 1.0 / (2.0 * math.pi * _positive(ang, "angular_cutoff_hz"))
        self._max_gap_ns = int(_positive(max_gap_s, "max_gap_s") * 1e9)
        self.reset()

    def reset(self) -> None:
        """Forget all history: the next valid sample starts a new estimate."""
        self._t_ns: int | None = None
        self._p: Vec3 = (0.0, 0.0, 0.0)
        self._q: Quat = (1.0, 0.0, 0.0, 0.0)
        self._v: Vec3 | None = None
        self._w: Vec3 = (0.0, 0.0, 0.0)
        self._last = Velocity(0, False, _NAN3, _NAN3)

    @property
    def last(self) -> Velocity:
        """The most recent estimate (invalid before any)."""
        return self._last

    def update(
        self, t_ns: int, position: Sequence[float], quaternion: Sequence[float], valid: bool = True
    ) -> Velocity:
        """Feed one pose (measurement time ``t_ns``, NED position, FRD quaternion) and get the estimate."""
        t_ns = int(t_ns)
        p = _finite3(position, "position")
        q = _finite4(quaternion, "quaternion")
        if not valid or p is None or q is None:
            self.reset()
            self._last = Velocity(t_ns, False, _NAN3, _NAN3)
            return self._last
        if self._t_ns is not None and t_ns == self._t_ns:
            return self._last  # duplicate sample
        if self._t_ns is None or t_ns < self._t_ns or t_ns - self._t_ns > self._max_gap_ns:
            self.reset()
            self._t_ns, self._p, self._q = t_ns, p, q
            self._last = Velocity(t_ns, False, _NAN3, _NAN3)
            return self._last

        dt = (t_ns - self._t_ns) * 1e-9
        raw_v = ((p[0] - self._p[0]) / dt, (p[1] - self._p[1]) / dt, (p[2] - self._p[2]) / dt)
        raw_w = _body_rate(self._q, q, dt)
        if self._v is None:
            v, w = raw_v, raw_w
        else:
            a = 1.0 - math.exp(-dt / self._tau)
            b = 1.0 - math.exp(-dt / self._tau_ang)
            pv, pw = self._v, self._w
            v = (
                pv[0] + a * (raw_v[0] - pv[0]),
                pv[1] + a * (raw_v[1] - pv[1]),
                pv[2] + a * (raw_v[2] - pv[2]),
            )
            w = (
                pw[0] + b * (raw_w[0] - pw[0]),
                pw[1] + b * (raw_w[1] - pw[1]),
                pw[2] + b * (raw_w[2] - pw[2]),
            )
        self._t_ns, self._p, self._q, self._v, self._w = t_ns, p, q, v, w
        self._last = Velocity(t_ns, True, v, w)
        return self._last


def _body_rate(q0: Quat, q1: Quat, dt: float) -> Vec3:
    """Constant body-frame angular velocity taking ``q0`` to ``q1`` in ``dt`` seconds (shortest way)."""
    # q1 = q0 ⊗ dq  →  dq = q0* ⊗ q1 is the rotation expressed in the body frame.
    w, x, y, z = quat_multiply((q0[0], -q0[1], -q0[2], -q0[3]), q1)
    if w < 0.0:  # q and −q are the same attitude: take the short way round
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # angle / sin(angle / 2) scaling; its small-angle limit is 2
    k = 2.0 / dt if s < 1e-9 else 2.0 * math.atan2(s, w) / (s * dt)
    return (x * k, y * k, z * k)


# --------------------------------------------------------------------------------------------------
# Decimation
# --------------------------------------------------------------------------------------------------


class TimeDecimator:
    """Decimate a timestamped stream to ``rate_hz`` by time, not by count.

    Output slots are spaced exactly one period apart. A sample is emitted if it is the first one at or after
    the next slot — or up to half an input interval early, so that the sample *nearest* the slot wins; this
    keeps the spacing steady when the input rate is a multiple of the output rate and timestamps jitter
    around the slot. Slots then advance by one period (phase-locked, so the mean output rate is exact). If
    the input was silent past a whole slot, the schedule re-anchors on the emitted sample instead of
    bursting to catch up. A sample never goes out twice: timestamps at or before the last emitted one are
    refused, except that a jump back by more than ``restart_after_s`` is taken as the source restarting its
    clock and starts a new schedule. The rate can be changed at run time with :meth:`set_rate`.
    """

    def __init__(self, rate_hz: float, restart_after_s: float = 1.0) -> None:
        self._period_ns = 0
        self._next_slot: int | None = None
        self._restart_ns = int(_positive(restart_after_s, "restart_after_s") * 1e9)
        self.set_rate(rate_hz)
        self.offered = 0
        self.emitted = 0
        self.reset()

    @property
    def rate_hz(self) -> float:
        """Target output rate (Hz)."""
        return self._rate_hz

    @property
    def period_ns(self) -> int:
        """Target output period (ns)."""
        return self._period_ns

    def set_rate(self, rate_hz: float) -> None:
        """Change the target rate; the next slot is one new period after the last emitted slot."""
        self._rate_hz = _positive(rate_hz, "rate_hz")
        old = self._period_ns
        self._period_ns = max(1, round(1e9 / self._rate_hz))
        if old and self._next_slot is not None:
            self._next_slot += self._period_ns - old

    def reset(self) -> None:
        """Forget the schedule: the next offered sample is emitted and anchors new slots."""
        self._next_slot = None
        self._last_in: int | None = None
        self._last_out: int | None = None
        self._input_interval = 0.0  # running estimate of the input interval (ns), 0 = unknown

    def offer(self, t_ns: int) -> bool:
        """Offer a sample with timestamp ``t_ns``; True if it should be forwarded."""
        t_ns = int(t_ns)
        self.offered += 1
        if self._last_in is not None and self._last_in - t_ns > self._restart_ns:
            self.reset()  # the source's clock restarted far in the past: start a new schedule
        period = self._period_ns
        if self._last_in is not None and t_ns > self._last_in:
            dt = t_ns - self._last_in
            if dt < period:  # silence gaps must not inflate the interval estimate
                est = self._input_interval
                self._input_interval = float(dt) if est == 0.0 else est + 0.1 * (dt - est)
        if self._last_in is None or t_ns > self._last_in:
            self._last_in = t_ns
        if self._last_out is not None and t_ns <= self._last_out:
            return False
        slot = self._next_slot
        if slot is None:
            self._emit(t_ns, t_ns)
            return True
        early = min(self._input_interval * 0.5, period * 0.5)
        if t_ns < slot - early:
            return False
        self._emit(t_ns, slot)
        return True

    def _emit(self, t_ns: int, slot: int) -> None:
        period = self._period_ns
        early = min(self._input_interval * 0.5, period * 0.5)
        nxt = slot + period
        if t_ns >= nxt - early:  # input skipped past a whole slot: re-anchor, never burst
            nxt = t_ns + period
        self._next_slot = nxt
        self._last_out = t_ns
        self.emitted += 1


# --------------------------------------------------------------------------------------------------
# Outlier rejection
# --------------------------------------------------------------------------------------------------


class RejectReason(StrEnum):
    """Why :class:`JumpGate` dropped a pose."""

    JUMP = "jump"  # moved further than max speed allows
    ROTATION = "rotation"  # turned faster than max angular rate allows
    STALE = "stale"  # timestamp not after the last accepted pose
    NON_FINITE = "non_finite"  # NaN/inf position or zero quaternion


@dataclass(frozen=True)
class GateDecision:
    """Outcome of :meth:`JumpGate.check`.

    ``reset`` is True when the pose was accepted as a new truth after a discontinuity (re-acquired after
    rejections or after a long gap): the gateway should bump its reset counter.
    """

    accepted: bool
    reset: bool = False
    reason: RejectReason | None = None


@dataclass
class _Track:
    t_ns: int
    p: Vec3
    q: Quat | None
    count: int = 1


@dataclass
class JumpGate:
    """Drop poses that moved (or turned) further than physically possible since the last accepted pose.

    A pose is rejected if ``|p − p_last| > max_speed_m_s · dt + margin_m`` (and, when quaternions are given
    and ``max_rate_rad_s`` is set, if its rotation exceeds ``max_rate_rad_s · dt + margin_rad``).
    Re-acquisition: once ``reacquire_after`` consecutive poses have been rejected while being consistent with
    each other (each within the same bound of the previous rejected one), the next pose consistent with them
    is accepted as the truth with ``reset=True``; a pose arriving more than ``max_gap_s`` after the last
    accepted one is also accepted with ``reset=True``. The first pose (or the first after :meth:`reset`) is
    accepted without a reset flag.
    Counters: ``accepted``, ``resets`` and ``rejected`` per :class:`RejectReason`.
    """

    max_speed_m_s: float = 10.0
    margin_m: float = 0.05
    max_rate_rad_s: float | None = 30.0
    margin_rad: float = 0.2
    reacquire_after: int = 10
    max_gap_s: float = 0.5
    accepted: int = field(default=0, init=False)
    resets: int = field(default=0, init=False)
    rejected: dict[RejectReason, int] = field(default_factory=dict, init=False)
    _last: _Track | None = field(default=None, init=False, repr=False)
    _candidate: _Track | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        _positive(self.max_speed_m_s, "max_speed_m_s")
        if not (math.isfinite(self.margin_m) and self.margin_m >= 0.0):
            raise FilterError(f"margin_m must be >= 0, got {self.margin_m!r}")
        if self.max_rate_rad_s is not None:
            _positive(self.max_rate_rad_s, "max_rate_rad_s")
        if not (math.isfinite(self.margin_rad) and self.margin_rad >= 0.0):
            raise FilterError(f"margin_rad must be >= 0, got {self.margin_rad!r}")
        if int(self.reacquire_after) < 1:
            raise FilterError(f"reacquire_after must be >= 1, got {self.reacquire_after!r}")
        _positive(self.max_gap_s, "max_gap_s")
        self.rejected = {r: 0 for r in RejectReason}

    def reset(self) -> None:
        """Forget the last accepted pose (the next pose is accepted as a fresh start); counters stay."""
        self._last = None
        self._candidate = None

    def check(
        self, t_ns: int, position: Sequence[float], quaternion: Sequence[float] | None = None
    ) -> GateDecision:
        """Judge one pose; returns whether to forward it and whether it starts a new track (reset)."""
        t_ns = int(t_ns)
        p = _finite3(position, "position")
        q = None if quaternion is None else _finite4(quaternion, "quaternion")
        if p is None or (quaternion is not None and q is None):
            return self._reject(RejectReason.NON_FINITE)
        last = self._last
        if last is None:
            return self._accept(t_ns, p, q, reset=False)
        if t_ns <= last.t_ns:
            return self._reject(RejectReason.STALE)
        dt = (t_ns - last.t_ns) * 1e-9
        if dt > self.max_gap_s:
            return self._accept(t_ns, p, q, reset=True)
        reason = self._violation(last, dt, p, q)
        if reason is None:
            return self._accept(t_ns, p, q, reset=False)
        # Count towards re-acquisition only while the rejected poses form a consistent track of their own.
        cand = self._candidate
        if (
            cand is not None
            and t_ns > cand.t_ns
            and self._violation(cand, (t_ns - cand.t_ns) * 1e-9, p, q) is None
        ):
            cand = _Track(t_ns, p, q, cand.count + 1)
        else:
            cand = _Track(t_ns, p, q)
        if cand.count > self.reacquire_after:
            return self._accept(t_ns, p, q, reset=True)
        self._candidate = cand
        return self._reject(reason)

    def _violation(self, ref: _Track, dt: float, p: Vec3, q: Quat | None) -> RejectReason | None:
        dx, dy, dz = p[0] - ref.p[0], p[1] - ref.p[1], p[2] - ref.p[2]
        if math.sqrt(dx * dx + dy * dy + dz * dz) > self.max_speed_m_s * dt + self.margin_m:
            return RejectReason.JUMP
        if (
            self.max_rate_rad_s is not None
            and q is not None
            and ref.q is not None
            and quat_angle(ref.q, q) > self.max_rate_rad_s * dt + self.margin_rad
        ):
            return RejectReason.ROTATION
        return None

    def _accept(self, t_ns: int, p: Vec3, q: Quat | None, *, reset: bool) -> GateDecision:
        self._last = _Track(t_ns, p, q)
        self._candidate = None
        self.accepted += 1
        if reset:
            self.resets += 1
        return GateDecision(True, reset, None)

    def _reject(self, reason: RejectReason) -> GateDecision:
        self.rejected[reason] += 1
        return GateDecision(False, False, reason)
