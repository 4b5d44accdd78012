"""The user's API: one :class:`Arena` connection, one :class:`Vehicle` per drone, :class:`Swarm` for
several, :class:`OffboardStream` for a program's own setpoints (:mod:`.vehicle`)."""

from arena_common.client.vehicle import Arena, OffboardStream, Swarm, Vehicle

__all__ = ["Arena", "OffboardStream", "Swarm", "Vehicle"]
