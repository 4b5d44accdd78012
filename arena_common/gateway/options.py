"""The tuning of one gateway (:class:`GatewayOptions`); the vehicle's config section gives the rest."""

from __future__ import annotations

from dataclasses import dataclass

from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.mavlink.link import mavlink2

__all__ = ["GatewayOptions", "stream_ids"]


@dataclass(frozen=True, slots=True)
class GatewayOptions:
    """Tuning of one gateway; the vehicle's config section gives the rest (link, system id, vision)."""

    source_system: int = 245  # our MAVLink system id (255 is QGroundControl's)
    source_component: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    # Hz, arena/<drone>/state; None: the vehicle's ``state_rate`` in the config
    state_rate: float | None = None
    unwatched_rate: float = 10.0  # Hz of the supervisor's checks while nobody subscribes to the state
    idle_rate: float = 2.0  # Hz of them while, besides, the vehicle is disarmed (link loss is 3 s anyway)
    # Hz per message type on arena/<drone>/telemetry/<MSG> (0: none); None: the vehicle's ``telemetry_rate``
    telemetry_rate: float | None = None
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
    allow_gcs_manual: bool = False  # forward RC_CHANNELS_OVERRIDE / MANUAL_CONTROL from the GCS
    check_at_start: bool = True  # read the arena parameters whenever the link comes up
    gcs: str | None = None  # overrides the vehicle's `gcs` connection string when not None
    # EKF global origin (lat deg, lon deg, alt m AMSL) given to an EKF that has none; None: never sent
    origin: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
    estimator_rate: float = 5.0  # Hz of ESTIMATOR_STATUS asked for (position validity); 0: not asked


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
