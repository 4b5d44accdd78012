"""Raw autopilot messages from a program: ``d1.telemetry("HIGHRES_IMU")``.

The gateway publishes every message it receives from the autopilot on
``arena/<drone>/telemetry/<MSG>``, at most ``telemetry_rate`` Hz per message type (10 Hz by default),
as :class:`~arena_common.core.wire.Telemetry` (its name, receive time and fields by MAVLink name).  A
message is subscribed to the first time it is asked for.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

from arena_common.client.streams import Callback, Stream, Topic
from arena_common.core import keys, wire

if TYPE_CHECKING:
    from arena_common.client.vehicle import Vehicle

__all__ = ["SENSOR_MESSAGES", "Telemetry"]

#: Subscribed for every vehicle: the typed sensor readings come from these.
SENSOR_MESSAGES = ("HIGHRES_IMU", "SCALED_IMU", "BATTERY_STATUS", "ESTIMATOR_STATUS")


class Telemetry:
    """The raw-message facet of a :class:`~arena_common.client.vehicle.Vehicle`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.vehicle = vehicle
        self._topics: dict[str, Topic[wire.Telemetry]] = {}
        self._lock = threading.Lock()

    def topic(self, name: str) -> Topic[wire.Telemetry]:
        """The topic of message ``name`` (MAVLink name, e.g. ``"ATTITUDE"``), subscribed on first use."""
        keys.validate_name(name, "message name")
        with self._lock:
            t = self._topics.get(name)
            if t is not None:
                return t
            t = self._topics[name] = Topic(f"{self.vehicle.name}/telemetry/{name}")
        if name not in SENSOR_MESSAGES:
            self.vehicle.arena._subscribe(keys.telemetry(self.vehicle.name, name))
        return t

    def __call__(self, name: str, timeout: float = 2.0) -> wire.Telemetry | None:
        """The latest message ``name``, waiting up to ``timeout`` s for a first one (None if none came)."""
        return self.topic(name).wait(timeout)

    def stream(self, name: str, timeout: float | None = None, capacity: int = 1024) -> Stream[wire.Telemetry]:
        """Every new message ``name``, in order."""
        return self.topic(name).stream(capacity, timeout)

    def on(self, name: str, fn: Callable[[wire.Telemetry], object]) -> Callback:
        """Call ``fn(message)`` for every new message ``name``."""
        return self.topic(name).on(fn)

    def names(self) -> list[str]:
        """The messages received so far."""
        with self._lock:
            return sorted(n for n, t in self._topics.items() if t.count)

    def _publish(self, name: str, tm: wire.Telemetry) -> None:
        with self._lock:
            t = self._topics.get(name)
            if t is None:
                t = self._topics[name] = Topic(f"{self.vehicle.name}/telemetry/{name}")
        t.publish(tm)

    def _close(self) -> None:
        with self._lock:
            topics = list(self._topics.values())
        for t in topics:
            t.close()
