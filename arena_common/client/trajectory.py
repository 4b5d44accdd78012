"""Trajectories: a smooth reference (position, velocity, acceleration, yaw) as a function of time.

A :class:`Trajectory` is a sequence of polynomial pieces, as Crazyswarm2's uploaded trajectories are.
Build one from timed waypoints (:meth:`Trajectory.waypoints`: quintic pieces whose velocities follow
the path and whose accelerations are continuous), a single rest-to-rest move
(:meth:`Trajectory.min_jerk`), or your own coefficients (:meth:`Trajectory.polynomial`).  Fly it with
:meth:`OffboardStream.follow <arena_common.client.offboard.OffboardStream.follow>` or
:meth:`Vehicle.follow <arena_common.client.vehicle.Vehicle.follow>`; :meth:`Trajectory.check` finds the
first point the gateway's safety rules would refuse before anything flies.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Trajectory", "TrajectoryPoint"]

Vec3 = tuple[float, float, float]
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]


@dataclass(frozen=True, slots=True)
class TrajectoryPoint:
    """The reference at one time: NED position [m], velocity [m/s], acceleration [m/s²], yaw [rad]
    (None: keep the heading) and yaw rate [rad/s]."""

    t: float
    p: Vec3
    v: Vec3
    a: Vec3
    yaw: float | None
    yaw_rate: float


def _poly(c: Sequence[float], t: float) -> tuple[float, float, float]:
    """Value, first and second derivative of the polynomial with ascending coefficients ``c`` at ``t``."""
    p = v = a = 0.0
    for k in range(len(c) - 1, -1, -1):
        a = a * t + 2.0 * v
        v = v * t + p
        p = p * t + c[k]
    return p, v, a


def _quintic(p0: float, v0: float, a0: float, p1: float, v1: float, a1: float, T: float) -> list[float]:
    """Coefficients of the quintic joining (p0, v0, a0) at 0 to (p1, v1, a1) at ``T``."""
    T2, T3 = T * T, T * T * T
    c3 = (20 * (p1 - p0) - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    c4 = (30 * (p0 - p1) + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T3 * T)
    c5 = (12 * (p1 - p0) - 6 * (v1 + v0) * T - (a0 - a1) * T2) / (2 * T3 * T2)
    return [p0, v0, a0 / 2.0, c3, c4, c5]


@dataclass(frozen=True, slots=True)
class _Piece:
    t0: float
    duration: float
    axes: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]
    yaw: tuple[float, ...] | None


class Trajectory:
    """Polynomial pieces in time; :meth:`sample` gives the reference at any time (clamped to the ends)."""

    def __init__(self, pieces: Sequence[_Piece], yaw: float | None = None) -> None:
        if not pieces:
            raise ValueError("a trajectory needs at least one piece")
        self._pieces = list(pieces)
        self._yaw = yaw
        self.duration = pieces[-1].t0 + pieces[-1].duration

    @classmethod
    def min_jerk(
        cls, start: Sequence[float], goal: Sequence[float], duration: float, yaw: float | None = None
    ) -> Trajectory:
        """Rest to rest from ``start`` to ``goal`` (NED, m) in ``duration`` s, minimum jerk; fixed ``yaw``."""
        return cls.waypoints([(0.0, start), (duration, goal)], yaw=yaw)

    @classmethod
    def waypoints(
        cls, points: Sequence[tuple[float, Sequence[float]]], yaw: float | None = None
    ) -> Trajectory:
        """Through ``(time, (north, east, down))`` waypoints, at rest at the first and the last.

        Inner waypoints are passed with the velocity of the line joining their neighbours (Catmull-Rom)
        and no acceleration, so position, velocity and acceleration are continuous.  Times must increase.
        """
        if len(points) < 2:
            raise ValueError("a trajectory needs at least two waypoints")
        ts = [float(t) for t, _ in points]
        ps = [tuple(float(x) for x in p) for _, p in points]
        for i, p in enumerate(ps):
            if len(p) != 3 or not all(math.isfinite(x) for x in p):
                raise ValueError(f"waypoint {i}: {p!r} is not a finite (north, east, down) point")
        for i in range(1, len(ts)):
            if not ts[i] > ts[i - 1]:
                raise ValueError(f"waypoint {i}: time {ts[i]} s does not come after {ts[i - 1]} s")
        vs: list[tuple[float, ...]] = [(0.0, 0.0, 0.0)]
        for i in range(1, len(ps) - 1):
            dt = ts[i + 1] - ts[i - 1]
            vs.append(tuple((ps[i + 1][k] - ps[i - 1][k]) / dt for k in range(3)))
        vs.append((0.0, 0.0, 0.0))
        pieces = []
        for i in range(len(ps) - 1):
            T = ts[i + 1] - ts[i]
            axes = tuple(
                tuple(_quintic(ps[i][k], vs[i][k], 0.0, ps[i + 1][k], vs[i + 1][k], 0.0, T)) for k in range(3)
            )
            pieces.append(_Piece(ts[i] - ts[0], T, axes, None))  # type: ignore[arg-type]
        return cls(pieces, yaw)

    @classmethod
    def polynomial(
        cls,
        pieces: Sequence[
            tuple[float, Sequence[float], Sequence[float], Sequence[float], Sequence[float] | None]
        ],
    ) -> Trajectory:
        """From pieces ``(duration, north, east, down, yaw)``: coefficients in ascending powers of the time
        since the piece's start (as Crazyswarm2's poly4d pieces); ``yaw`` None keeps the heading."""
        out, t0 = [], 0.0
        for i, (dur, cn, ce, cd, cy) in enumerate(pieces):
            if not (math.isfinite(dur) and dur > 0.0):
                raise ValueError(f"piece {i}: duration {dur!r} must be a positive number of seconds")
            axes = (tuple(map(float, cn)), tuple(map(float, ce)), tuple(map(float, cd)))
            if any(not c or not all(math.isfinite(x) for x in c) for c in axes):
                raise ValueError(f"piece {i}: every axis needs finite coefficients")
            out.append(_Piece(t0, float(dur), axes, tuple(map(float, cy)) if cy is not None else None))
            t0 += float(dur)
        return cls(out)

    def sample(self, t: float) -> TrajectoryPoint:
        """The reference at ``t`` seconds from the start (before: the start; after: the end, at rest)."""
        tc = min(max(t, 0.0), self.duration)
        piece = self._pieces[-1]
        for pc in self._pieces:
            if tc <= pc.t0 + pc.duration:
                piece = pc
                break
        local = tc - piece.t0
        vals = [_poly(c, local) for c in piece.axes]
        p = (vals[0][0], vals[1][0], vals[2][0])
        if t >= self.duration or t < 0.0:
            v = a = (0.0, 0.0, 0.0)
        else:
            v = (vals[0][1], vals[1][1], vals[2][1])
            a = (vals[0][2], vals[1][2], vals[2][2])
        yaw, yaw_rate = self._yaw, 0.0
        if piece.yaw is not None:
            y, yr, _ = _poly(piece.yaw, local)
            yaw, yaw_rate = math.remainder(y, 2 * math.pi), (yr if 0.0 <= t < self.duration else 0.0)
        return TrajectoryPoint(t, p, v, a, yaw, yaw_rate)

    def check(
        self,
        box: Box | None = None,
        max_speed: float = math.inf,
        max_climb: float = math.inf,
        max_accel: float = math.inf,
        step: float = 0.02,
    ) -> str | None:
        """The first point that breaks a limit (the gateway would refuse it), in words, or None."""
        n = max(1, math.ceil(self.duration / step))
        for i in range(n + 1):
            s = self.sample(self.duration * i / n)
            if not all(math.isfinite(x) for x in (*s.p, *s.v, *s.a)):
                return f"t={s.t:.2f} s: not a finite reference"
            if box is not None:
                for k, axis in enumerate(("north", "east", "down")):
                    lo, hi = box[k]
                    if not lo - 1e-9 <= s.p[k] <= hi + 1e-9:
                        return f"t={s.t:.2f} s: {axis} {s.p[k]:.2f} m outside [{lo:.2f}, {hi:.2f}]"
            speed = math.hypot(s.v[0], s.v[1])
            if speed > max_speed:
                return f"t={s.t:.2f} s: horizontal speed {speed:.2f} m/s above {max_speed:.2f}"
            if abs(s.v[2]) > max_climb:
                return f"t={s.t:.2f} s: vertical speed {abs(s.v[2]):.2f} m/s above {max_climb:.2f}"
            acc = math.sqrt(sum(x * x for x in s.a))
            if acc > max_accel:
                return f"t={s.t:.2f} s: acceleration {acc:.2f} m/s² above {max_accel:.2f}"
        return None

    @property
    def start(self) -> Vec3:
        """The first point."""
        return self.sample(0.0).p

    @property
    def end(self) -> Vec3:
        """The last point."""
        return self.sample(self.duration).p
