"""Events of one vehicle: logged at once, published in order from their own thread."""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from arena_common.bus.session import Channel
from arena_common.core import wire


class EventSink:
    """Events of one vehicle: logged at once, published in order by :meth:`run` (its own thread).

    Publishing is reliable (it may block when the bus is congested), so nothing time-critical ever
    waits on it; the last 500 events stay in :attr:`recent`.
    """

    def __init__(self, publish: Callable[[wire.Event], None] | None, log: logging.Logger) -> None:
        self._publish = publish
        self._log = log
        self._channel: Channel[wire.Event] = Channel(4096, ring=False)
        self.recent: collections.deque[wire.Event] = collections.deque(maxlen=500)
        self._limits: dict[str, float] = {}

    def emit(
        self, kind: str, text: str, sev: int = 6, *, every: float = 0.0, **data: Any
    ) -> wire.Event | None:
        """Record one event; with ``every`` > 0, at most one per ``every`` s for the same kind and text."""
        if every > 0:
            now = time.monotonic()
            key = f"{kind}:{text}"
            if now < self._limits.get(key, -math.inf):
                return None
            self._limits[key] = now + every
        event = wire.Event(t=wire.now_ns(), kind=kind, text=text[:4096], sev=max(0, min(7, sev)), data=data)
        level = logging.ERROR if sev <= 3 else logging.WARNING if sev == 4 else logging.INFO
        self._log.log(level, "%s: %s", kind, text)
        self.recent.append(event)
        self._channel.put(event)
        return event

    def run(self, stop: threading.Event) -> None:
        """Publish queued events until ``stop`` (then flush what is left)."""
        while not stop.is_set() or len(self._channel):
            event = self._channel.get(0.5)  # an event wakes it at once; the timeout only sees ``stop``
            if event is not None and self._publish is not None:
                try:
                    self._publish(event)
                except Exception as exc:  # the bus is closing; events are also in the log
                    self._log.debug("event not published: %s", exc)

    def close(self) -> None:
        self._channel.close()
