"""Raw autopilot messages published on ``arena/<drone>/telemetry/<MSG>``, rate-limited per type."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from arena_common.bus.session import Bus, Lane, Publisher
from arena_common.core import keys, wire
from arena_common.mavlink.link import mavlink2


def _plain(value: Any) -> Any:
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


class TelemetryPublisher:
    """Publishes raw messages on ``arena/<drone>/telemetry/<MSG>``, at most ``rate`` Hz per message type.

    Only while someone subscribes to the message's key (a program's ``d1.telemetry(...)``, the recorder,
    ``arena echo``).  :meth:`due` is asked before decoding: a message type that is not due, or that nobody
    watches, costs a lookup, not a decode (an unwatched one is counted in :attr:`unwatched`, at most
    ``rate`` times a second per type).
    """

    def __init__(self, bus: Bus | None, drone: str, rate: float = 10.0, exclude: Iterable[int] = ()) -> None:
        self.bus = bus
        self.drone = drone
        self.period = 1.0 / rate if rate > 0 else math.inf
        self.exclude = frozenset(exclude)
        self._next: dict[int, float] = {}
        self._pubs: dict[str, Publisher[wire.Telemetry]] = {}
        self.published = 0
        self.unwatched = 0

    def due(self, msgid: int, now: float) -> bool:
        """Whether a message of ``msgid`` is to be decoded and published now."""
        if self.bus is None or now < self._next.get(msgid, 0.0) or msgid in self.exclude:
            return False
        cls = mavlink2.mavlink_map.get(msgid)
        if cls is None or self._watched(cls.msgname) is None:
            self._next[msgid] = now + self.period  # asked again at the rate, not for every frame
            return False
        return True

    def publish(self, msg: Any, now: float, t_ns: int) -> None:
        """Publish one decoded message (the caller checked :meth:`due`)."""
        self._next[msg.get_msgId()] = now + self.period
        name = msg.get_type()
        fields = {k: _plain(v) for k, v in msg.to_dict().items() if k != "mavpackettype"}
        self._publisher(name).put(wire.Telemetry(t=t_ns, msg=name, f=fields))
        self.published += 1

    def put(self, name: str, fields: Mapping[str, Any], t_ns: int) -> None:
        """Publish fields under a message name (also used for the gateway's own measurements)."""
        pub = self._watched(name)
        if pub is not None:
            pub.put(wire.Telemetry(t=t_ns, msg=name, f=dict(fields)))
            self.published += 1

    @property
    def watched(self) -> list[str]:
        """The message names someone subscribes to now (as the bus's matching status says)."""
        return [name for name, pub in self._pubs.items() if pub.matching]

    def _publisher(self, name: str) -> Publisher[wire.Telemetry]:
        pub = self._pubs.get(name)
        if pub is None:
            assert self.bus is not None
            pub = self._pubs[name] = self.bus.stream_publisher(
                keys.telemetry(self.drone, name), wire.Telemetry, Lane.REPORT
            )
        return pub

    def _watched(self, name: str) -> Publisher[wire.Telemetry] | None:
        """The publisher of ``name`` if anyone subscribes to it (else counted as unwatched)."""
        if self.bus is None:
            return None
        pub = self._publisher(name)
        if not pub.matching:
            self.unwatched += 1
            return None
        return pub
