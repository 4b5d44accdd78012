"""One vehicle's section of the config (``[vehicles.<name>]``), and the command-line overrides of it.

Every setting of a vehicle's gateway that a user may choose lives here, once, with its bounds: the config
is its one validated home.  A service's flag (``--state-rate``, ``--gcs``…) only overrides a field, through
:func:`override`, which checks the value against the very same bounds.  What is left in
:class:`arena_common.gateway.options.GatewayOptions` is the gateway's internal tuning (timeouts, retries).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from arena_common.core.convert import Spec, convert
from arena_common.core.endpoints import mirror_connection
from arena_common.core.errors import ConfigError

__all__ = ["MavlinkName", "Origin", "Px4ParamName", "SimVehicleSpec", "VehicleSpec", "override"]

#: (latitude deg, longitude deg, altitude m above mean sea level)
Origin = tuple[
    Annotated[float, Meta(ge=-90.0, le=90.0)],
    Annotated[float, Meta(ge=-180.0, le=180.0)],
    Annotated[float, Meta(ge=-1000.0, le=10000.0)],
]


class SimVehicleSpec(Spec, frozen=True):
    """Settings of a simulated vehicle (``start`` and ``yaw_deg`` also place a PX4 SITL vehicle)."""

    start: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mavlink: str = ""  # the simulated autopilot's side; derived from the gateway's string when empty
    # A slow radio link (ms each way, ± jitter): the simulated autopilot talks to its gateway through a
    # relay that holds every datagram that long, in order (arena_common.sim.linkdelay; udp links only).
    link_delay_ms: Annotated[float, Meta(ge=0.0, le=500.0)] = 0.0
    link_jitter_ms: Annotated[float, Meta(ge=0.0, le=500.0)] = 0.0

    @property
    def link_delay_s(self) -> tuple[float, float]:
        """(delay, jitter) in seconds, each way, as the simulated autopilot takes them."""
        return (self.link_delay_ms * 1e-3, self.link_jitter_ms * 1e-3)


Px4ParamName = Annotated[
    str,
    Meta(
        pattern=r"^[A-Z][A-Z0-9_]{0,15}$",
        description="PX4 parameter names (capitals, digits, _; up to 16 characters)",
    ),
]
MavlinkName = Annotated[str, Meta(pattern=r"^[A-Z][A-Z0-9_]{0,49}$")]


class VehicleSpec(Spec, frozen=True):
    """One vehicle: its rigid body, its MAVLink link and its pipeline settings."""

    name: str
    rigid_body: str | int = ""  # the vehicle's name when empty
    mavlink: str = ""  # a pymavlink connection string; required unless a PX4 SITL instance implies it
    # udpin links only: the autopilot's "IP:PORT".  The gateway then talks to that address only and drops
    # (and counts) datagrams from any other; without it, it replies to whoever last sent the vehicle's
    # frames (on an unsigned link, anyone on the network: docs/safety.md §3.3).
    mavlink_peer: str = ""
    # MAV_SYS_ID, never 0 (0: left out); required unless a PX4 SITL instance implies it
    system_id: Annotated[int, Meta(ge=1, le=250)] = 0
    vision_rate: Annotated[float, Meta(ge=1.0, le=400.0)] = 50.0
    max_pose_age: Annotated[float, Meta(ge=0.001, le=1.0)] = 0.1
    vision_message: Literal["odometry", "vision_position_estimate"] = "odometry"
    # Rates of what the gateway publishes, while anyone subscribes: arena/<d>/state, and each raw MAVLink
    # message type on arena/<d>/telemetry/<MSG> (0: none).
    state_rate: Annotated[float, Meta(ge=1.0, le=200.0)] = 50.0
    telemetry_rate: Annotated[float, Meta(ge=0.0, le=200.0)] = 10.0
    # Rates (Hz) the gateway asks the autopilot to stream messages at, by MAVLink name, whenever the link
    # comes up (MAV_CMD_SET_MESSAGE_INTERVAL; 0 stops the stream): e.g. { ATTITUDE = 10, HIGHRES_IMU = 0 }
    # (what mavros' stream rates and MAVSDK's set_rate_* do). Every stream PX4 sends, the gateway reads.
    stream_rates: dict[MavlinkName, Annotated[float, Meta(ge=0.0, le=1000.0)]] = msgspec.field(
        default_factory=dict
    )
    require_setup: bool = True
    gcs: str = ""  # forward MAVLink to a ground station (a pymavlink connection string)
    allow_gcs_manual: bool = False  # forward its RC_CHANNELS_OVERRIDE / MANUAL_CONTROL to the vehicle
    gateway_system_id: Annotated[int, Meta(ge=1, le=254)] = 245  # the gateway's own (255: QGroundControl's)
    # The EKF origin given to an autopilot that has none (SET_GPS_GLOBAL_ORIGIN): [lat, lon, alt m AMSL].
    # PX4 needs one for its AUTO modes without GPS; "off": never sent.
    origin: Origin | Literal["off"] = (0.0, 0.0, 0.0)
    signing_key_file: str = ""  # MAVLink 2 signing: a file holding the 32-byte secret key as 64 hex digits
    sim: SimVehicleSpec = msgspec.field(default_factory=SimVehicleSpec)
    # What flies it: "sim" (the arena's simulated autopilot, started by the ``sim`` service), "px4" (an
    # external PX4: hardware, or a SITL started by hand; nothing is started for it) or "px4-sitl" (PX4
    # SITL instance ``px4_instance``, started by ``arena up`` with its ground-truth bridge).
    autopilot: Literal["sim", "px4", "px4-sitl"] = "sim"
    px4_instance: int | None = None  # its range: runtime.px4_sitl_rules
    px4_params: dict[Px4ParamName, float] = msgspec.field(default_factory=dict)  # PX4 SITL boot parameters

    @property
    def simulated(self) -> bool:
        """True when the arena's simulated autopilot flies it."""
        return self.autopilot == "sim"

    @property
    def px4_sitl(self) -> bool:
        """True when ``arena up`` starts a PX4 SITL instance for it."""
        return self.autopilot == "px4-sitl"

    def sim_mavlink(self) -> str:
        """The connection string the simulated autopilot uses: the mirror of the gateway's."""
        if self.sim.mavlink:
            return self.sim.mavlink
        return mirror_connection(self.mavlink)


def override(v: VehicleSpec, changes: dict[str, Any], source: str) -> VehicleSpec:
    """``v`` with ``changes`` (field → value) checked against the fields' own bounds, as the config's are.

    :class:`ConfigError` names ``source`` (the flag that asked) and the field: ``--state-rate:
    vehicles.d1.state_rate: expected a number in 1.0..200.0, got 0.5``.
    """
    unknown = sorted(set(changes) - set(VehicleSpec.__struct_fields__))
    if unknown:
        raise ConfigError(f"{source}: vehicles.{v.name}.{unknown[0]}: unknown field")
    checked = convert(VehicleSpec, {"name": v.name, **changes}, source, f"vehicles.{v.name}")
    return msgspec.structs.replace(v, **{k: getattr(checked, k) for k in changes})
