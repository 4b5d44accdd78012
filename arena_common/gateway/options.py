"""The internal tuning of one gateway (:class:`GatewayOptions`: timeouts, retries, loop rates).

Every setting a user chooses (link, system ids, rates, ground station, origin) is the vehicle's config
section, checked with its bounds there (:mod:`arena_common.core.vehiclespec`); a service's flags override
those fields through :func:`arena_common.core.vehiclespec.override`.  The tuning here is for tests and
benchmarks; each value is checked against :data:`BOUNDS` when an options object is made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.mavlink.link import mavlink2

__all__ = ["BOUNDS", "GatewayOptions", "stream_ids"]

#: Each numeric field's allowed range (inclusive).
BOUNDS: dict[str, tuple[float, float]] = {
    "source_component": (1, 255),
    "unwatched_rate": (0.1, 200.0),
    "idle_rate": (0.1, 200.0),
    "stream_rate": (2.0, 100.0),  # PX4 needs setpoints at 2 Hz at least to stay in OFFBOARD
    "link_timeout": (0.1, 60.0),
    "ack_timeout": (0.01, 30.0),
    "attempts": (1, 10),
    "prestream": (0.0, 10.0),
    "fused_tolerance": (0.001, 10.0),
    "vision_stale": (0.01, 10.0),
    "goto_speed": (0.01, 20.0),
    "goto_climb": (0.01, 10.0),
    "estimator_rate": (0.0, 100.0),
    "link_budget": (0, 1_000_000),
}


@dataclass(frozen=True, slots=True)
class GatewayOptions:
    """Tuning of one gateway; the vehicle's config section gives the rest (link, system id, vision)."""

    source_component: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    unwatched_rate: float = 10.0  # Hz of the supervisor's checks while nobody subscribes to the state
    idle_rate: float = 2.0  # Hz of them while, besides, the vehicle is disarmed (link loss is 3 s anyway)
    stream_rate: float = 20.0  # Hz, offboard setpoints repeated while their lease runs
    link_timeout: float = 3.0  # s without HEARTBEAT = link lost
    ack_timeout: float = 0.8  # s per COMMAND_LONG attempt
    attempts: int = 3  # COMMAND_LONG attempts (confirmation 0, 1, 2)
    prestream: float = 0.5  # s of setpoint stream before OFFBOARD may be requested
    fused_tolerance: float = 0.2  # m between the EKF position and the vision pose to call it fused
    vision_stale: float = 0.2  # s since the last pose sent beyond which arming is refused
    send_velocity: bool = True  # put the pose's velocity (when valid) in ODOMETRY
    goto_speed: float = 1.0  # m/s, horizontal speed of the goto carrot (capped by arena.max_speed)
    goto_climb: float = 0.5  # m/s, vertical speed of the goto carrot (capped by arena.max_climb)
    check_at_start: bool = True  # read the arena parameters whenever the link comes up
    estimator_rate: float = 5.0  # Hz of ESTIMATOR_STATUS asked for (position validity); 0: not asked
    # Datagrams per second a UDP link reads at most (0: no cap): a flood on one vehicle's link costs its
    # reader little (PX4 sends a few hundred a second; the rest is dropped, counted 'mavlink: over budget').
    link_budget: int = 5000

    def __post_init__(self) -> None:
        for name, (lo, hi) in BOUNDS.items():
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ConfigError(f"GatewayOptions.{name}: expected a number in {lo}..{hi}, got {value!r}")


def stream_ids(cfg: ArenaConfig, vehicle: str) -> dict[int, float]:
    """A vehicle's ``stream_rates`` by MAVLink message id; :class:`ConfigError` naming an unknown message."""
    out: dict[int, float] = {}
    for name, hz in cfg.vehicle(vehicle).stream_rates.items():
        msgid = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None)
        if not isinstance(msgid, int):
            raise ConfigError(
                f"{cfg.path}: vehicles.{vehicle}.stream_rates: no MAVLink message named {name!r}"
            )
        out[msgid] = hz
    return out
