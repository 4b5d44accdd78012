"""Flying Arena: the shared library of the arena services and the user client.

The names a user program needs are re-exported here::

    from arena_common import Arena, Vehicle, CommandRejected
"""

from arena_common.client.vehicle import Arena, OffboardStream, Swarm, Vehicle
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
    PayloadError,
    SafetyRefused,
    VehicleNotPresent,
)

__all__ = [
    "Arena",
    "ArenaConfig",
    "ArenaError",
    "BusError",
    "CommandError",
    "CommandRejected",
    "CommandTimeout",
    "ConfigError",
    "InvalidName",
    "OffboardStream",
    "PayloadError",
    "SafetyRefused",
    "Swarm",
    "Vehicle",
    "VehicleNotPresent",
    "load_config",
]
