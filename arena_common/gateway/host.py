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
own Gateway's.  Not yet here: restarting one vehicle alone, and a cap on what a flooded link may take of
the process (docs/performance.md, issue #35).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from contextlib import ExitStack
from typing import Any

from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import Bus, Handler, Received, open_bus, typed
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.gateway.gateway import Gateway
from arena_common.runtime.service import running

__all__ = ["GatewayHost", "VisionDispatch", "serve"]

SERVICE = by_module("services.mavlink_gateway")


class VisionDispatch:
    """Hands each vehicle of this process its pose of one :class:`~arena_common.core.wire.VisionFrame`.

    A frame that is no VisionFrame is every served vehicle's counted reject (each lost it); a body of a
    vehicle served elsewhere is skipped (counted ``others``); an exception in one vehicle's sender is that
    vehicle's counted failure, and the frame goes on to the rest.
    """

    def __init__(self, gateways: Sequence[Gateway]) -> None:
        self.gateways = {gw.name: gw for gw in gateways}
        self.frames = 0
        self.others = 0  # bodies of vehicles this process does not serve

    def __call__(self, item: Received[Any]) -> None:
        frame = typed(item, wire.VisionFrame, self._reject)
        if frame is None:
            return
        self.frames += 1
        for body in frame.b:
            gw = self.gateways.get(body.n)
            if gw is None:
                self.others += 1
                continue
            try:
                gw.offer_vision(body.pose())
            except Exception as exc:  # this vehicle's fault: the others' vision goes on
                gw.health.failed("vision", exc)

    def _reject(self, kind: str, detail: str) -> None:
        for gw in self.gateways.values():
            gw.health.vision_reject(kind, detail, "VisionFrame")

    def failed(self, exc: BaseException) -> None:
        """The dispatch itself failed (a bug): every served vehicle's counted failure."""
        for gw in self.gateways.values():
            gw.health.failed("vision", exc)


class GatewayHost:
    """The gateways of ``vehicles`` in this process: ``with GatewayHost(cfg, names, stop) as h: h.run()``.

    ``bus``: a session to share (else one is opened for the host and closed with it).  Vision comes per
    frame on ``arena/sys/vision`` when the transform decimates (``[pipeline] decimate = "transform"``) and
    ``per_frame``, else on each vehicle's own ``vision`` key.
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
    ) -> None:
        if not vehicles:
            raise ValueError("a gateway host needs at least one vehicle")
        for v in vehicles:
            cfg.vehicle(v)  # an unknown vehicle fails before anything opens
        self.cfg, self.vehicles, self.stop = cfg, list(vehicles), stop
        self.host = host_name(host)
        self.per_frame = per_frame and cfg.pipeline.decimate == "transform"
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
            for i, v in enumerate(self.vehicles):
                svc = stack.enter_context(
                    running(
                        SERVICE.name, cfg, bus=bus, vehicle=v, host=self.host, stop=self.stop, clock=i == 0
                    )
                )
                clock = svc.clock if i == 0 else next(iter(self.gateways.values())).clock
                self.gateways[v] = stack.enter_context(
                    Gateway(
                        cfg, v, bus, stats=svc.stats, log=svc.log, clock=clock, own_vision=not self.per_frame
                    )
                )
            if self.per_frame:
                self.dispatch = VisionDispatch(list(self.gateways.values()))
                bus.subscribe(keys.VISIONS, channel=Handler(self.dispatch, self.dispatch.failed))
        except BaseException:
            stack.close()
            raise
        return self

    def run(self) -> None:
        """Each gateway's supervisor in a thread of its own, until ``stop`` is set."""
        threads = [
            threading.Thread(target=gw.run, args=(self.stop,), name=f"{gw.name}:supervisor", daemon=True)
            for gw in self.gateways.values()
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
