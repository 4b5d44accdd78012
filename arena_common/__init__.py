"""Flying Arena: the shared library of the arena services and the user client.

The names a user program needs are re-exported here::

    from arena_common import Arena, Vehicle, CommandRejected, AsyncArena, Trajectory, FlightMode
"""

from arena_common.client import (
    Arena,
    ArenaClock,
    AsyncArena,
    AsyncVehicle,
    Battery,
    EstimatorStatus,
    FlightMode,
    Imu,
    LandedState,
    OffboardStream,
    PoseReading,
    Status,
    Stream,
    StreamTimeout,
    Swarm,
    Trajectory,
    Vehicle,
)
from arena_common.core.config import ArenaConfig
from arena_common.core.config import load as load_config
from arena_common.core.errors import (
    ArenaError,
    BusError,
    CommandError,
    CommandRejected,
    CommandTimeout,
    ConfigError,
    InvalidName,
    NotPermitted,
    PayloadError,
    SafetyRefused,
    VehicleNotPresent,
)

__all__ = [
    "Arena",
    "ArenaClock",
    "ArenaConfig",
    "ArenaError",
    "AsyncArena",
    "AsyncVehicle",
    "Battery",
    "BusError",
    "CommandError",
    "CommandRejected",
    "CommandTimeout",
    "ConfigError",
    "EstimatorStatus",
    "FlightMode",
    "Imu",
    "InvalidName",
    "LandedState",
    "NotPermitted",
    "OffboardStream",
    "PayloadError",
    "PoseReading",
    "SafetyRefused",
    "Status",
    "Stream",
    "StreamTimeout",
    "Swarm",
    "Trajectory",
    "Vehicle",
    "VehicleNotPresent",
    "load_config",
]
