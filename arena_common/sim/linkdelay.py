"""A slow radio link, for a simulated vehicle: a UDP relay that holds every datagram for a delay.

A lab's MAVLink often crosses Wi-Fi or a telemetry radio: tens of milliseconds each way, varying.  PX4
then cannot take the gateway's clock (its TIMESYNC filter drops round trips of 10 ms or more) and stamps
vision on arrival, so the link's delay is in every vision sample (docs/px4.md).  :class:`LinkDelay` stands
between a simulated autopilot's ``udpout`` and its gateway's ``udpin``: the autopilot sends to
:attr:`LinkDelay.port`, the relay sends on to the gateway from a socket of its own and back to whoever last
sent it the vehicle's frames (or to ``vehicle``, when given: a PX4 SITL's own port, poked first with
:meth:`poke` so that PX4 takes the relay as its peer).  Each datagram waits ``delay ± jitter`` (uniform,
each way, in wall-clock time whatever the simulation's speed, as a radio's would), and leaves in the order
it came, as a radio link keeps order.  Both sockets are bound to the gateway's own address (loopback for
a gateway on this computer), never to every interface.
"""

from __future__ import annotations

import heapq
import itertools
import random
import select
import socket
import threading
import time

__all__ = ["LinkDelay"]


class LinkDelay:
    """Holds each datagram between a simulated autopilot and its gateway ``delay_s ± jitter_s`` (each way)."""

    def __init__(
        self,
        gateway: tuple[str, int],
        delay_s: float,
        jitter_s: float = 0.0,
        seed: int = 0,
        vehicle: tuple[str, int] | None = None,
    ) -> None:
        if not 0.0 <= jitter_s <= delay_s <= 0.5:
            raise ValueError(f"link delay: need 0 <= jitter <= delay <= 0.5 s, got {delay_s} ± {jitter_s}")
        self.gateway = gateway
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self._rng = random.Random(seed)
        self._vehicle_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the autopilot sends here
        self._gateway_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # we send on from here
        for s in (self._vehicle_side, self._gateway_side):
            s.bind((gateway[0], 0))
        self.port: int = self._vehicle_side.getsockname()[1]
        self.source: tuple[str, int] = self._gateway_side.getsockname()  # where the gateway sees frames from
        self._vehicle: tuple[str, int] | None = vehicle  # where the autopilot's frames come from
        self._heap: list[tuple[float, int, socket.socket, bytes, tuple[str, int]]] = []
        self._order = itertools.count()
        self._last_due = {id(self._vehicle_side): 0.0, id(self._gateway_side): 0.0}
        self.forwarded = 0
        self.dropped = 0  # the gateway's datagrams before the autopilot sent any (nowhere to go)
        self.send_errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-link-delay", daemon=True)
        self._thread.start()

    def _hold(self, out: socket.socket, data: bytes, to: tuple[str, int], now: float) -> None:
        due = now + self.delay_s + self._rng.uniform(-self.jitter_s, self.jitter_s)
        due = max(due, self._last_due[id(out)])  # in order, as a radio link keeps it
        self._last_due[id(out)] = due
        heapq.heappush(self._heap, (due, next(self._order), out, data, to))

    def _run(self) -> None:
        sockets = [self._vehicle_side, self._gateway_side]
        while not self._stop.is_set():
            now = time.monotonic()
            while self._heap and self._heap[0][0] <= now:
                _, _, out, data, to = heapq.heappop(self._heap)
                try:
                    out.sendto(data, to)
                    self.forwarded += 1
                except OSError:
                    self.send_errors += 1
            wait = min(0.05, max(0.0, self._heap[0][0] - now)) if self._heap else 0.05
            try:
                ready, _, _ = select.select(sockets, [], [], wait)
            except (OSError, ValueError):
                return  # closed
            now = time.monotonic()
            for s in ready:
                try:
                    data, addr = s.recvfrom(65535)
                except OSError:
                    continue
                if s is self._vehicle_side:
                    self._vehicle = addr
                    self._hold(self._gateway_side, data, self.gateway, now)
                elif self._vehicle is not None:
                    self._hold(self._vehicle_side, data, self._vehicle, now)
                else:
                    self.dropped += 1

    def poke(self, data: bytes) -> None:
        """Send ``data`` to the vehicle now, from the relay's vehicle-side socket: an autopilot that answers
        only the first peer that speaks to it (PX4) then takes the relay as its peer."""
        if self._vehicle is None:
            raise ValueError("link delay: no vehicle address to poke")
        self._vehicle_side.sendto(data, self._vehicle)

    def close(self) -> None:
        """Stop relaying and close both sockets (what is still held is lost, as on a radio switched off)."""
        self._stop.set()
        self._thread.join(1.0)
        for s in (self._vehicle_side, self._gateway_side):
            s.close()
