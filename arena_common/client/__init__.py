"""The user's API, by facet (as MAVSDK-Python's plugins and cflib's modules):

- :mod:`.arena` — :class:`Arena`, the connection; :mod:`.vehicle` — :class:`Vehicle`, one drone: typed
  readings with source, age and validity, streams and callbacks, blocking commands;
- :mod:`.offboard` — :class:`OffboardStream`, a program's own setpoints; :mod:`.trajectory` —
  :class:`Trajectory`, smooth references to follow;
- :mod:`.streams` — :class:`Stream` iterators and callbacks; :mod:`.types` — :class:`FlightMode`,
  :class:`LandedState`, :class:`Status`, :class:`PoseReading`, :class:`Imu`, :class:`Battery`,
  :class:`EstimatorStatus`;
- :mod:`.params` — :class:`Params`; :mod:`.telemetry` — raw autopilot messages;
- :mod:`.swarm` — :class:`Swarm`; :mod:`.clock` — :class:`ArenaClock`, arena time;
- :mod:`.aio` — :class:`AsyncArena`, :class:`AsyncVehicle`: the asyncio facade.
"""

from arena_common.client.aio import AsyncArena, AsyncOffboard, AsyncStream, AsyncVehicle
from arena_common.client.arena import Arena
from arena_common.client.clock import ArenaClock, Rate
from arena_common.client.offboard import OffboardStream
from arena_common.client.params import Params
from arena_common.client.streams import Callback, Stream, StreamClosed, StreamTimeout, Topic
from arena_common.client.swarm import Swarm
from arena_common.client.telemetry import Telemetry
from arena_common.client.trajectory import Trajectory, TrajectoryPoint
from arena_common.client.types import (
    Battery,
    EstimatorStatus,
    FlightMode,
    Imu,
    LandedState,
    PoseReading,
    Status,
)
from arena_common.client.vehicle import Vehicle

__all__ = [
    "Arena",
    "ArenaClock",
    "AsyncArena",
    "AsyncOffboard",
    "AsyncStream",
    "AsyncVehicle",
    "Battery",
    "Callback",
    "EstimatorStatus",
    "FlightMode",
    "Imu",
    "LandedState",
    "OffboardStream",
    "Params",
    "PoseReading",
    "Rate",
    "Status",
    "Stream",
    "StreamClosed",
    "StreamTimeout",
    "Swarm",
    "Telemetry",
    "Topic",
    "Trajectory",
    "TrajectoryPoint",
    "Vehicle",
]
