"""Several vehicles' gateways in one process: one Zenoh session, one clock, one wake-up per mocap frame.

:func:`serve` runs a :class:`~arena_common.gateway.gateway.Gateway` per vehicle named, each as the gateway
service runs it (its own :func:`~arena_common.runtime.service.running` service: presence, stats, logger;
its own link, lease and safety rules; its supervisor in a thread of its own), over one bus session and one
clock measurement for the process.  With the transform decimating, vision comes as one
:class:`~arena_common.core.wire.VisionFrame` per mocap frame on ``arena/sys/vision``
(:class:`VisionDispatch`): one Zenoh callback hands each vehicle its pose, instead of one callback per
vehicle per pose.

What stays each vehicle's own: a fault in one vehicle's vision (an exception in its sender) is that
vehicle's counted failure and the frame goes on to the others; each link, lease and safety rule is its
own Gateway's.  A vehicle whose gateway fails (its supervisor raises) restarts alone (:class:`HostedVehicle`):
its gateway closes, its endpoints go with it (each vehicle declares through a
:class:`~arena_common.bus.view.BusView` of its own), and it opens again after :data:`RESTART_AFTER_S`
while the others fly on; its service (presence, stats) stays.  A flood on one vehicle's link costs its
reader the link's budget (``GatewayOptions.link_budget``), not the others' vision.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import Bus, Handler, Received, open_bus, typed
from arena_common.bus.view import BusView
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.gateway.gateway import Gateway
from arena_common.gateway.options import GatewayOptions
from arena_common.runtime.clock import ClockSync
from arena_common.runtime.service import Service, running

__all__ = ["GatewayHost", "HostedVehicle", "VisionDispatch", "serve"]

SERVICE = by_module("services.mavlink_gateway")
RESTART_AFTER_S = 1.0  # a failed vehicle's gateway opens again after this (as systemd restarts a process)


class VisionDispatch:
    """Hands each vehicle of this process its pose of one :class:`~arena_common.core.wire.VisionFrame`.

    ``gateways``: the served vehicles' gateways by name, read live (a vehicle restarting is absent: each
    of its poses meanwhile is counted in ``missed`` and told to ``on_missed``).  A frame that is no
    VisionFrame is every served vehicle's counted reject (each lost it); a body of a vehicle served
    elsewhere is skipped (counted ``others``); an exception in one vehicle's sender is that vehicle's
    counted failure, and the frame goes on.
    """

    def __init__(self, gateways: dict[str, Gateway], on_missed: Callable[[str], None] | None = None) -> None:
        self.gateways = gateways
        self.on_missed = on_missed
        self.served = frozenset(gateways)
        self.frames = 0
        self.others = 0  # bodies of vehicles this process does not serve
        self.missed: dict[str, int] = {}  # poses of a served vehicle while its gateway restarted

    def __call__(self, item: Received[Any]) -> None:
        frame = typed(item, wire.VisionFrame, self._reject)
        if frame is None:
            return
        self.frames += 1
        for body in frame.b:
            gw = self.gateways.get(body.n)
            if gw is None:
                if body.n in self.served:
                    self.missed[body.n] = self.missed.get(body.n, 0) + 1
                    if self.on_missed is not None:
                        self.on_missed(body.n)
                else:
                    self.others += 1
                continue
            try:
                gw.offer_vision(body.pose())
            except Exception as exc:  # this vehicle's fault: the others' vision goes on
                gw.health.failed("vision", exc)

    def _reject(self, kind: str, detail: str) -> None:
        for gw in list(self.gateways.values()):
            gw.health.vision_reject(kind, detail, "VisionFrame")

    def failed(self, exc: BaseException) -> None:
        """The dispatch itself failed (a bug): every served vehicle's counted failure."""
        for gw in list(self.gateways.values()):
            gw.health.failed("vision", exc)


class HostedVehicle:
    """One vehicle of a :class:`GatewayHost`: its service (presence, stats, logger) for the host's
    lifetime, and its current :class:`Gateway` over a bus view of its own, opened again alone when its
    supervisor fails (counted ``restarts``, the failure as ``supervisor: error``)."""

    def __init__(self, host: GatewayHost, svc: Service, clock: ClockSync | None) -> None:
        self.host, self.svc, self.clock = host, svc, clock
        self.name = svc.vehicle
        self.restarts = 0
        self.gateway, self._part = self._open()

    def _open(self) -> tuple[Gateway, BusView]:
        part = BusView(self.svc.bus)
        try:
            gw = Gateway(
                self.host.cfg,
                self.name,
                part,
                stats=self.svc.stats,
                log=self.svc.log,
                options=self.host.options,
                clock=self.clock,
                own_vision=not self.host.per_frame,
            ).__enter__()
        except BaseException:
            part.close()
            raise
        return gw, part

    def close(self) -> None:
        """Close the vehicle's gateway and undeclare its endpoints."""
        try:
            self.gateway.close()
        finally:
            self._part.close()

    def run(self, stop: threading.Event) -> None:
        """The gateway's supervisor until ``stop`` is set; a failure restarts this vehicle alone."""
        while not stop.is_set():
            try:
                self.gateway.run(stop)
                return
            except Exception as exc:
                self.gateway.health.failed("supervisor", exc)
            self.host.gateways.pop(self.name, None)  # its poses meanwhile: counted missed
            self.svc.log.error(
                "%s: its gateway failed; restarting it alone in %g s", self.name, RESTART_AFTER_S
            )
            try:
                self.close()
            except Exception as exc:
                self.svc.log.error("%s: closing the failed gateway: %s", self.name, exc)
            while not stop.wait(RESTART_AFTER_S):
                try:
                    self.gateway, self._part = self._open()
                    break
                except Exception as exc:  # tried again after the same wait, counted each time
                    self.svc.stats.reject("restart: error")
                    self.svc.log.error("%s: cannot open its gateway again: %s", self.name, exc)
            else:
                return
            self.restarts += 1
            self.svc.stats.count("restarts")
            self.host.gateways[self.name] = self.gateway
            self.svc.log.info("%s: its gateway restarted (%d so far)", self.name, self.restarts)


class GatewayHost:
    """The gateways of ``vehicles`` in this process: ``with GatewayHost(cfg, names, stop) as h: h.run()``.

    ``bus``: a session to share (else one is opened for the host and closed with it).  Vision comes per
    frame on ``arena/sys/vision`` when the transform decimates (``[pipeline] decimate = "transform"``) and
    ``per_frame``, else on each vehicle's own ``vision`` key.  ``options``: every gateway's tuning.
    ``gateways``: each vehicle's current one.
    """

    def __init__(
        self,
        cfg: ArenaConfig,
        vehicles: Sequence[str],
        stop: threading.Event,
        *,
        host: str | None = None,
        bus: Bus | None = None,
        per_frame: bool = True,
        options: GatewayOptions | None = None,
    ) -> None:
        if not vehicles:
            raise ValueError("a gateway host needs at least one vehicle")
        for v in vehicles:
            cfg.vehicle(v)  # an unknown vehicle fails before anything opens
        self.cfg, self.vehicles, self.stop = cfg, list(vehicles), stop
        self.host = host_name(host)
        self.per_frame = per_frame and cfg.pipeline.decimate == "transform"
        self.options = options
        self.hosted: dict[str, HostedVehicle] = {}
        self.gateways: dict[str, Gateway] = {}
        self.dispatch: VisionDispatch | None = None
        self._bus = bus
        self._stack = ExitStack()

    def __enter__(self) -> GatewayHost:
        stack, cfg = self._stack, self.cfg
        try:
            bus = self._bus
            if bus is None:
                bus = open_bus(cfg.zenoh, host_bus_options(cfg, self.host, None, vehicle=self.vehicles[0]))
                stack.callback(bus.close)
            clock: ClockSync | None = None
            for i, v in enumerate(self.vehicles):
                part = stack.enter_context(BusView(bus))  # the vehicle's presence and stats, its losses
                svc = stack.enter_context(
                    running(
                        SERVICE.name, cfg, bus=part, vehicle=v, host=self.host, stop=self.stop, clock=i == 0
                    )
                )
                if i == 0:
                    clock = svc.clock  # the first vehicle's service measures the clock for them all
                hosted = self.hosted[v] = HostedVehicle(self, svc, clock)
                stack.callback(hosted.close)
                self.gateways[v] = hosted.gateway
            if self.per_frame:
                self.dispatch = VisionDispatch(self.gateways, self._missed)
                bus.subscribe(keys.VISIONS, channel=Handler(self.dispatch, self.dispatch.failed))
        except BaseException:
            stack.close()
            raise
        return self

    def _missed(self, name: str) -> None:
        self.hosted[name].svc.stats.reject("vision: gateway restarting")

    def run(self) -> None:
        """Each vehicle's supervisor in a thread of its own, until ``stop`` is set."""
        threads = [
            threading.Thread(target=h.run, args=(self.stop,), name=f"{h.name}:supervisor", daemon=True)
            for h in self.hosted.values()
        ]
        for t in threads:
            t.start()
        self.stop.wait()
        for t in threads:
            t.join(timeout=2.0)

    def __exit__(self, *exc: object) -> None:
        self._stack.close()


def serve(
    cfg: ArenaConfig,
    vehicles: Sequence[str],
    stop: threading.Event,
    *,
    host: str | None = None,
    bus: Bus | None = None,
    per_frame: bool = True,
) -> None:
    """Run the gateways of ``vehicles`` in this process until ``stop`` is set (or SIGINT/SIGTERM)."""
    with GatewayHost(cfg, vehicles, stop, host=host, bus=bus, per_frame=per_frame) as h:
        h.run()
