"""Flying Arena: the shared library of the arena services and the user client.

The names a user program needs are re-exported here::

    from arena_common import Arena, Vehicle, CommandRejected, AsyncArena, Trajectory, FlightMode

They load when first asked for (PEP 562): a service that imports ``arena_common.gateway`` does not carry
the user's client, asyncio and all, in its memory.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from arena_common.bus.exposure import load as load_config
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

#: Where each public name lives.
_HOMES = {
    **{name: "arena_common.client" for name in __all__ if name not in ("ArenaConfig", "load_config")},
    "ArenaConfig": "arena_common.core.config",
    "load_config": "arena_common.bus.exposure",  # the config's shape and what it may expose
}
_HOMES.update(
    {
        name: "arena_common.core.errors"
        for name in (
            "ArenaError", "BusError", "CommandError", "CommandRejected", "CommandTimeout", "ConfigError",
            "InvalidName", "NotPermitted", "PayloadError", "SafetyRefused", "VehicleNotPresent",
        )
    }
)  # fmt: skip


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'arena_common' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), "load" if name == "load_config" else name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
