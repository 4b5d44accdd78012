"""The bench harness's Zenoh side: each vehicle's true pose in (as the Motive emulator's truth) and every
service's stats out."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence

from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.geometry.frames import quat_from_yaw

__all__ = ["TRUTH_RATE", "StatsWatcher", "TruthFeeder"]

TRUTH_RATE = 60.0  # Hz per vehicle


class TruthFeeder:
    """Publishes every vehicle's true pose (a small circle each, all different) at ``rate`` Hz."""

    def __init__(self, bus: Bus, vehicles: Sequence[str], rate: float = TRUTH_RATE) -> None:
        self.pubs = [bus.stream_publisher(keys.truth(v), wire.Pose) for v in vehicles]
        self.rate = rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-truth", daemon=True)
        self.sent = 0

    @staticmethod
    def position(i: int, t: float) -> tuple[float, float, float]:
        """Vehicle ``i``'s true NED position at ``t`` s: a 0.2 m circle at 0.5 Hz around its grid cell."""
        col, row = i % 5, i // 5
        cn, ce = -2.4 + 1.2 * col, -1.2 + 0.8 * (row % 4)
        a = 2 * math.pi * 0.5 * t + 0.3 * i
        return cn + 0.2 * math.cos(a), ce + 0.2 * math.sin(a), -1.0 - 0.05 * math.sin(a)

    def _run(self) -> None:
        period = 1.0 / self.rate
        t_start = time.monotonic()
        k = 0
        while not self._stop.is_set():
            due = t_start + k * period
            left = due - time.monotonic()
            if left > 0 and self._stop.wait(left):
                break
            k += 1
            now = time.time_ns()
            t = now * 1e-9
            for i, pub in enumerate(self.pubs):
                q = quat_from_yaw(0.5 * math.sin(0.2 * t + i))
                pub.put(wire.Pose(t=now, p=self.position(i, t), q=q, ok=True, tp=now))
            self.sent += 1

    def start(self) -> TruthFeeder:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


class StatsWatcher:
    """Keeps the latest :class:`~arena_common.core.wire.Stats` of every service."""

    def __init__(self, bus: Bus) -> None:
        self.latest: dict[str, wire.Stats] = {}
        self._lock = threading.Lock()
        self._sub = bus.subscribe("arena/sys/stats/**", capacity=4096, ring=False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-stats", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self._sub.get(0.2)
            if item is not None and isinstance(item.payload, wire.Stats):
                with self._lock:
                    self.latest[item.payload.service] = item.payload

    def counters(self) -> dict[str, dict[str, int]]:
        """Every service's counters and rejections (cumulative), flattened per service."""
        with self._lock:
            return {
                name: {
                    "pid": s.pid,
                    **{k: int(v) for k, v in s.counts.items()},
                    **{f"rejected:{k}": int(v) for k, v in s.rejected.items()},
                }
                for name, s in self.latest.items()
            }

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
