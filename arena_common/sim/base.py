"""What the parts of the simulated autopilot share: its error, the true pose, geodesy, input sanitising.

:class:`AutopilotState` declares the state and the methods the parts of
:class:`~arena_common.sim.autopilot.SimAutopilot` use across module boundaries (the flight logic in
:mod:`~arena_common.sim.flight`, commands and setpoints in :mod:`~arena_common.sim.mavlink_commands`, the
mission protocol in :mod:`~arena_common.sim.mission`, telemetry in :mod:`~arena_common.sim.telemetry`), so
that each part type-checks on its own; the methods here are only placeholders the parts override.

Every number that arrives over MAVLink may be NaN, ±inf or absurdly large: :func:`finite` and
:func:`as_int` are how the parts read them, so that no input, however odd, raises.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from arena_common.sim.params import ParamStore
    from arena_common.sim.physics import QuadSim, Setpoint
    from arena_common.sim.time import SimClock, TimesyncFilter

__all__ = [
    "EARTH_RADIUS_M",
    "AutopilotState",
    "MapProjection",
    "SimAutopilotError",
    "TruePose",
    "as_int",
    "clamp",
    "finite",
]

NAN = math.nan
EARTH_RADIUS_M = 6371000.0  # PX4's CONSTANTS_RADIUS_OF_EARTH
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class SimAutopilotError(ValueError):
    """Bad configuration of a simulated autopilot (system id, connection string, parameter, clock)."""


class TruePose(NamedTuple):
    """The simulated vehicle's true pose, as a motion-capture system would measure it."""

    time_ns: int  # SimClock time of the pose
    position: Vec3  # arena NED, m
    q: Quat  # body FRD → arena NED, (w, x, y, z)
    velocity: Vec3  # arena NED, m/s
    rates: Vec3 = (0.0, 0.0, 0.0)  # body FRD angular velocity, rad/s


def finite(value: Any) -> bool:
    """Whether ``value`` is a finite real number (NaN, ±inf and non-numbers are not)."""
    try:
        return math.isfinite(value)
    except TypeError:
        return False


def as_int(value: Any, lo: int, hi: int) -> int | None:
    """``value`` rounded to an int when finite and within ``lo..hi``, else None (never raises)."""
    if not finite(value):
        return None
    rounded = round(value)
    return rounded if lo <= rounded <= hi else None


class MapProjection:
    """PX4's azimuthal equidistant projection (lib/geo) around an EKF origin (``lat``, ``lon`` in deg).

    :meth:`project` maps a latitude/longitude to north/east metres from the origin; :meth:`reproject` is
    its inverse. Altitudes are ``alt - down`` around the origin's altitude.
    """

    def __init__(self, lat: float, lon: float, alt: float) -> None:
        self.lat, self.lon, self.alt = lat, lon, alt
        self._lat_rad = math.radians(lat)
        self._lon_rad = math.radians(lon)
        self._sin_lat = math.sin(self._lat_rad)
        self._cos_lat = math.cos(self._lat_rad)

    def project(self, lat: float, lon: float) -> tuple[float, float]:
        """North, east (m) of a position (deg)."""
        lat_r, lon_r = math.radians(lat), math.radians(lon)
        sin_lat, cos_lat = math.sin(lat_r), math.cos(lat_r)
        cos_dlon = math.cos(lon_r - self._lon_rad)
        arg = max(-1.0, min(1.0, self._sin_lat * sin_lat + self._cos_lat * cos_lat * cos_dlon))
        c = math.acos(arg)
        k = c / math.sin(c) if abs(c) > 1e-12 else 1.0
        north = k * (self._cos_lat * sin_lat - self._sin_lat * cos_lat * cos_dlon) * EARTH_RADIUS_M
        east = k * cos_lat * math.sin(lon_r - self._lon_rad) * EARTH_RADIUS_M
        return north, east

    def reproject(self, north: float, east: float) -> tuple[float, float]:
        """Latitude, longitude (deg) of a point ``north``, ``east`` metres from the origin."""
        x, y = north / EARTH_RADIUS_M, east / EARTH_RADIUS_M
        c = math.hypot(x, y)
        if c < 1e-15:
            return self.lat, self.lon
        sin_c, cos_c = math.sin(c), math.cos(c)
        lat = math.asin(max(-1.0, min(1.0, cos_c * self._sin_lat + x * sin_c * self._cos_lat / c)))
        lon = self._lon_rad + math.atan2(y * sin_c, c * self._cos_lat * cos_c - x * self._sin_lat * sin_c)
        return math.degrees(lat), math.degrees(lon)


class AutopilotState:
    """State and cross-part methods of a simulated autopilot (declared here, set by its parts)."""

    # identity and links
    system_id: int
    conn: Any
    clock: SimClock
    params: ParamStore
    sim: QuadSim
    timesync: TimesyncFilter
    statustexts: deque[tuple[int, str]]
    # flight state
    armed: bool
    terminated: bool
    _user_mode: tuple[int, int]
    _failsafe: tuple[str, str] | None
    _failsafe_since: float
    _nav: dict[str, Any]
    _home: Vec3
    _home_yaw: float
    _home_set: bool
    _armed_at: float
    ideal: bool  # True: the idealised autopilot (instant takeoff phases, Hold where the mode started)
    _flew_since_arming: bool
    _landed_since: float
    _sp_times: deque[float]
    _offboard_sp: Setpoint
    _frame_warned_at: float
    _battery_level: int
    _battery_action_level: int
    _xy_valid_prev: bool
    _vision_prev: bool
    _was_landed: bool
    _cruise_speed: float
    gps_origin: tuple[float, float, float] | None
    origin_sets: int
    last_vision_sample_us: int
    ignored_mocap: int
    # the ground station link (STATUSTEXT, data link loss)
    _gcs_heard_at: float
    _gcs_lost: bool
    # telemetry
    _rebooting_until_ns: int
    _boot_ns: int
    _closed: bool
    _pending_requests: list[int]
    _intervals: dict[int, float]
    _next_due: dict[int, float]
    _param_queue: deque[int]
    # mission
    _mission: list[Any]
    _mission_current: int
    _mission_done: bool

    COMPONENT_ID: int
    REBOOT_SECONDS: float

    # --- implemented by the parts; declared here for the type checker only ---
    if TYPE_CHECKING:

        def _statustext(self, severity: int, text: str, *, tab: bool = False) -> None: ...

        def _request_message(self, msgid: int) -> bool: ...

        def _pos_ok(self) -> bool: ...

        def _global_ok(self) -> bool: ...

        def _change_mode(self, mode: tuple[int, int], t: float) -> int: ...

        def _enter_nav(self) -> None: ...

        def _arm_request(self, p: tuple[float, ...], t: float) -> int | None: ...

        def _terminate(self) -> None: ...

        def _set_home(self, position: Vec3) -> None: ...

        def _apply_params(self, boot: bool = False) -> None: ...

        def _send_param(self, name: str) -> None: ...

        def _addressed(self, target_system: int, target_component: int, allow_broadcast: bool) -> bool: ...

        def _offboard_stream_ok(self, t: float) -> bool: ...

        def _mission_valid(self) -> bool: ...

        def _mission_start(self, t: float) -> None: ...

        def projection(self) -> MapProjection | None: ...

        def gcs_connected(self, t: float | None = None) -> bool: ...

        def _mission_navigate(self, t: float) -> None: ...

        def _arm_denial(self, t: float) -> list[str]: ...

        def _mode_unavailable(self, mode: tuple[int, int], t: float) -> str | None: ...

        def _carrot(self, target: Vec3, yaw: float) -> Setpoint: ...

        def _land_speed(self) -> float: ...

        def _set_interval(self, msgid: int, interval_us: float, t: float) -> bool: ...

        def _cmd_mission_start(self, p: tuple[float, ...], t: float) -> int: ...

        def _mission_set_current(self, seq: int) -> bool: ...

        @property
        def mode(self) -> tuple[int, int]: ...

        @property
        def landed_state(self) -> int: ...

        on_tick: Callable[[TruePose], None] | None


def clamp(v: float, lo: float, hi: float) -> float:
    """``v`` limited to ``lo..hi``."""
    return lo if v < lo else hi if v > hi else v
