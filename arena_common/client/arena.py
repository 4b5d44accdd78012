"""A program's connection to the arena: :class:`Arena`.

::

    from arena_common import Arena

    with Arena("deploy/sim.toml") as arena:
        d1 = arena.vehicle("d1")           # fails at once, naming the known vehicles, on a typo
        swarm = arena.swarm()              # every vehicle alive now
        arena.clock.sleep(2.0)             # arena time: follows the simulation's speed

One background thread per :class:`Arena` receives every vehicle's state, poses, vision, events and
telemetry, keeps each :class:`~arena_common.client.vehicle.Vehicle`'s attributes fresh and feeds its
streams and callbacks, in arrival order.
"""

from __future__ import annotations

import collections
import logging
import os
import socket
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from arena_common.bus import exposure
from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import Bus, BusOptions, Channel, Received, open_bus
from arena_common.client.clock import ArenaClock
from arena_common.client.swarm import Swarm
from arena_common.client.vehicle import Vehicle
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, ZenohSpec
from arena_common.core.errors import VehicleNotPresent

__all__ = ["Arena"]

log = logging.getLogger("arena_common.client")


def _src() -> str:
    return f"{socket.gethostname()}/{os.getpid()}"


class Arena:
    """A connection to the arena's bus.  Use as a context manager (or call :meth:`close`).

    ``config`` is a config file path (read by :func:`arena_common.bus.exposure.load`: its shape and what
    it may expose to the network, not the PX4 SITL rules) or :class:`~arena_common.core.config.ArenaConfig`
    (its Zenoh section says how to reach the bus; its vehicles are the known ones); ``connect`` endpoints
    override it (``["tcp/192.168.1.20:7447"]``).  ``host`` names this computer in the config (default: the
    hostname).  The session is a client of the router unless ``mode`` says otherwise.
    """

    def __init__(
        self,
        config: ArenaConfig | str | Path | None = None,
        *,
        connect: Sequence[str] = (),
        mode: str | None = None,
        bus: Bus | None = None,
        name: str = "",
        host: str | None = None,
    ) -> None:
        if isinstance(config, (str, Path)):
            config = exposure.load(config)
        self.config = config
        self.src = name or _src()
        self.clock = ArenaClock.for_config(config)
        """Arena time (:class:`~arena_common.client.clock.ArenaClock`): the simulation's speed, or 1."""
        self.rejected: collections.Counter[str] = collections.Counter()
        """Samples this program could not use, by reason (undecodable, unexpected type)."""
        self._own_bus = bus is None
        # A client of the router by default: the router knows every service's presence at once, while a
        # peer learns it link by link; user programs gain nothing from direct links.
        self.host = host_name(host)
        """This computer's host name in the config (``host``, else ``$ARENA_HOST``, else the hostname)."""
        if bus is None:
            options = host_bus_options(
                config, self.host, BusOptions(mode=mode or "client", connect=tuple(connect))
            )
            bus = open_bus(config.zenoh if config else ZenohSpec(), options)
        self.bus = bus
        self._vehicles: dict[str, Vehicle] = {}
        self._fleet: tuple[wire.Fleet, float] | None = None  # every vehicle's position (arena/sys/fleet)
        self._channel: Channel[Received[Any]] = Channel(8192, ring=True)
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._last_warning = 0.0
        self._thread = threading.Thread(target=self._pump, name="arena-client", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        while not self._closed.is_set():
            item = self._channel.get(0.2)
            if item is None:
                continue
            if item.payload is None:
                self._reject(item.key, f"undecodable: {item.error}")
                continue
            if item.key == keys.FLEET:
                if isinstance(item.payload, wire.Fleet):
                    self._fleet = (item.payload, time.monotonic())
                else:
                    self._reject(item.key, f"unexpected {type(item.payload).__name__}")
                continue
            parts = item.key.split("/")
            v = self._vehicles.get(parts[1]) if len(parts) > 2 else None
            if v is None:
                continue
            try:
                v._update(item)
            except Exception as exc:  # one bad sample must never stop the attributes of every vehicle
                self._reject(item.key, f"{type(exc).__name__}: {exc}")

    def _reject(self, key: str, reason: str) -> None:
        self.rejected[reason.split(":", 1)[0]] += 1
        now = time.monotonic()
        if now - self._last_warning >= 1.0:
            self._last_warning = now
            log.warning("%s: sample not used: %s", key, reason)

    def _subscribe(self, keyexpr: str) -> None:
        self.bus.subscribe(keyexpr, channel=self._channel)

    def positions(self, max_age: float = 1.0) -> dict[str, tuple[float, float, float]]:
        """Every tracked vehicle's position (arena NED), from the frame transform's 10 Hz fleet message
        (``arena/sys/fleet``); empty when it is older than ``max_age`` seconds."""
        fleet = self._fleet
        if fleet is None or time.monotonic() - fleet[1] > max_age:
            return {}
        return {e.n: e.p for e in fleet[0].b}

    def vehicle(self, name: str) -> Vehicle:
        """The :class:`Vehicle` of ``name`` (one per name; created on first use).

        A name the config does not list (without a config: whose gateway is not alive on the bus) raises
        :class:`~arena_common.core.errors.VehicleNotPresent` at once, naming the known vehicles.
        """
        keys.validate_name(name)
        with self._lock:
            v = self._vehicles.get(name)
            if v is not None:
                return v
        if self.config is not None:
            if name not in self.config.vehicles:
                raise VehicleNotPresent(
                    f"unknown vehicle {name!r}: the config lists {', '.join(sorted(self.config.vehicles))}",
                    drone=name,
                )
        elif not self.is_alive(name):
            raise VehicleNotPresent(
                f"unknown vehicle {name!r}: no gateway for this vehicle is alive on the bus; alive: "
                + (", ".join(self.vehicles(0.5)) or "none"),
                drone=name,
            )
        with self._lock:
            v = self._vehicles.get(name)
            if v is None:
                v = Vehicle(self, name)
                if not self._vehicles:
                    self._subscribe(keys.FLEET)  # where the others are: trajectories keep apart
                self._vehicles[name] = v
                for key in v._subscriptions():
                    self._subscribe(key)
            return v

    def vehicles(self, timeout: float = 1.0) -> list[str]:
        """Names of the vehicles whose gateway is alive on the bus right now."""
        names = set()
        for key in self.bus.alive(keys.ALIVE_ALL, timeout):
            service = key.rsplit("/", 1)[-1]
            if service.startswith("gateway."):
                names.add(service[len("gateway.") :])
        return sorted(names)

    def is_alive(self, name: str) -> bool:
        """True when a gateway for ``name`` holds its presence token."""
        return bool(self.bus.alive(f"arena/sys/alive/*/gateway.{name}", 0.5))

    def swarm(self, names: Iterable[str] | None = None) -> Swarm:
        """A :class:`~arena_common.client.swarm.Swarm` of the named vehicles (default: every vehicle
        alive now)."""
        return Swarm(self.vehicle(n) for n in (names if names is not None else self.vehicles()))

    def estop(self, kill: bool = False, reason: str = "") -> None:
        """Stop everything: every gateway lands its vehicle at once (or cuts the motors with ``kill``)."""
        self.bus.put(keys.ESTOP, wire.Estop(t=wire.now_ns(), kill=kill, reason=reason, src=self.src))

    def close(self) -> None:
        """Stop the background thread, end every stream, and close the bus (if this object opened it)."""
        self._closed.set()
        self._thread.join(2.0)
        for v in list(self._vehicles.values()):
            v._close()
        if self._own_bus:
            self.bus.close()

    def __enter__(self) -> Arena:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
