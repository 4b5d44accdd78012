"""Downsampler: ``arena/<drone>/pose`` (full mocap rate) → ``arena/<drone>/vision`` at the vision rate.

One process per vehicle (``--vehicle NAME``). Each pose goes through, in order:

1. validity — poses Motive lost (``ok`` false) are never forwarded;
2. a :class:`~arena_common.filters.JumpGate` — poses that moved or turned faster than physically possible
   are dropped and counted; when the gate accepts a new track (re-acquired after a jump, or after a long
   gap) the vision reset counter ``rc`` is bumped (mod 256) so the gateway bumps ODOMETRY's
   ``reset_counter`` and PX4 resets onto the new pose instead of fusing a jump;
3. a :class:`~arena_common.filters.TimeDecimator` at ``vehicles.<name>.vision_rate`` — chosen by
   measurement time, not by count, so the output stays evenly spaced under jittery input.

Nothing is ever sent twice and nothing is sent without an input: when poses stop, vision stops, which is
what lets PX4 detect position loss. Velocities computed across a dropped outlier are unreliable, so the
vision poses of the next :data:`VELOCITY_SETTLE_S` carry ``vok=False``.

Subscription: a FIFO of :data:`QUEUE_CAPACITY`, not a ring. The decimator must see every timestamp to pick
the sample nearest each slot (and to estimate the input interval); a latest-only ring would let a later
sample overwrite the one it wants whenever this thread wakes late, making the spacing jitter and the rate
drop. The FIFO is small so that a stalled process cannot build up a long backlog of stale poses: beyond
it, new samples are dropped and counted (``dropped``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated

import typer

from arena_common import keys, wire
from arena_common.bus import BusOptions
from arena_common.config import ArenaConfig
from arena_common.errors import ConfigError
from arena_common.filters import FilterError, JumpGate, TimeDecimator
from arena_common.options import (
    ConfigOpt,
    ConnectOpt,
    HostOpt,
    ListenOpt,
    LogOpt,
    ModeOpt,
    ZConfigOpt,
    bus_options,
    load_config,
)
from arena_common.service import running, setup_logging

SERVICE = "downsampler"
QUEUE_CAPACITY = 16  # ≈ 90 ms of input at 180 Hz
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


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicle: str,
    rate: float | None = None,
    host: str | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Decimate ``vehicle``'s poses into vision poses until ``stop`` is set (or SIGINT/SIGTERM).

    ``rate`` overrides ``vehicles.<vehicle>.vision_rate`` (Hz).
    """
    spec = cfg.vehicle(vehicle)
    try:
        filt = VisionFilter(spec.vision_rate if rate is None else rate)
    except FilterError as exc:
        raise ConfigError(f"{vehicle}: {exc}") from None
    with running(SERVICE, cfg, options, vehicle=vehicle, host=host, stop=stop) as svc:
        svc.log.info("%s → %s at %.1f Hz", keys.pose(vehicle), keys.vision(vehicle), filt.rate_hz)
        sub = svc.bus.subscribe(keys.pose(vehicle), capacity=QUEUE_CAPACITY, ring=False)
        pub = svc.bus.stream_publisher(keys.vision(vehicle), wire.Pose)
        dropped = 0
        while not svc.stopped:
            item = sub.get(0.2)
            if sub.channel.dropped != dropped:
                svc.stats.count("dropped", sub.channel.dropped - dropped)
                dropped = sub.channel.dropped
            if item is None:
                continue
            svc.stats.count("in")
            if item.error is not None:
                svc.reject("bad_payload", str(item.error))
                continue
            if not isinstance(item.payload, wire.Pose):
                svc.reject("wrong_type", f"{item.key} carried {type(item.payload).__name__}, not Pose")
                continue
            d = filt.process(item.payload)
            if d.reset:
                svc.stats.count("resets")
                svc.log.info("new track at t=%d: reset counter %d", item.payload.t, filt.rc)
            if d.outcome is Outcome.SENT:
                assert d.vision is not None
                pub.put(d.vision)
                svc.stats.count("out")
                svc.stats.latency((time.time_ns() - item.t_recv) * 1e-9)
            elif d.outcome is Outcome.OUTLIER:
                # A timestamp not after the last accepted one is stale (or a duplicate), not an outlier.
                reason = "stale" if d.reason == "stale" else f"outlier_{d.reason}"
                svc.reject(reason, f"pose at t={item.payload.t} dropped ({d.reason})")
            else:
                svc.stats.count(d.outcome.value)


def cli(
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The vehicle to serve.")],
    rate: Annotated[
        float | None, typer.Option("--rate", help="Vision rate in Hz (default: the vehicle's vision_rate).")
    ] = None,
    config: ConfigOpt = None,
    mode: ModeOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    zconfig: ZConfigOpt = None,
    host: HostOpt = None,
    log_level: LogOpt = "INFO",
) -> None:
    """One vehicle's poses decimated by time to its vision rate (arena/<drone>/vision)."""
    setup_logging(log_level)
    cfg = load_config(config)
    try:
        main(cfg, bus_options(mode, connect, listen, zconfig), vehicle=vehicle, rate=rate, host=host)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


if __name__ == "__main__":
    typer.run(cli)
