"""Downsampler: ``arena/<drone>/pose`` (full mocap rate) → ``arena/<drone>/vision`` at the vision rate.

One process per vehicle (``--vehicle NAME``), running that vehicle's
:class:`~arena_common.pipeline.vision.VisionFilter` (validity, jump gate, time decimation; nothing is ever sent
twice, nothing without an input). The frame transform can run the same filter in-process instead
(``[pipeline] decimate = "transform"``), which saves this process and its hop.

Subscription: a FIFO of :data:`QUEUE_CAPACITY`, not a ring. The decimator must see every timestamp to pick
the sample nearest each slot (and to estimate the input interval); a latest-only ring would let a later
sample overwrite the one it wants whenever this thread wakes late, making the spacing jitter and the rate
drop. The FIFO is small so that a stalled process cannot build up a long backlog of stale poses: beyond
it, new samples are dropped and counted (``dropped``).
"""

from __future__ import annotations

import threading
import time
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions, Lane, typed
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.core.services import by_module
from arena_common.geometry.filters import FilterError
from arena_common.pipeline.vision import VisionFilter, account
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.downsampler").name  # its one name: arena_common/core/services.py
QUEUE_CAPACITY = 16  # ≈ 90 ms of input at 180 Hz


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicle: str,
    rate: float | None = None,
    host: str | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Decimate ``vehicle``'s poses into vision poses until ``stop`` is set (or SIGINT/SIGTERM).

    ``rate`` overrides ``vehicles.<vehicle>.vision_rate`` (Hz).
    """
    spec = cfg.vehicle(vehicle)
    try:
        filt = VisionFilter(spec.vision_rate if rate is None else rate)
    except FilterError as exc:
        raise ConfigError(f"{vehicle}: {exc}") from None
    with running(SERVICE, cfg, options, vehicle=vehicle, host=host, stop=stop) as svc:
        svc.log.info("%s → %s at %.1f Hz", keys.pose(vehicle), keys.vision(vehicle), filt.rate_hz)
        sub = svc.bus.subscribe(keys.pose(vehicle), capacity=QUEUE_CAPACITY, ring=False)
        pub = svc.bus.stream_publisher(keys.vision(vehicle), wire.Pose, Lane.VISION)
        while not svc.stopped:
            item = svc.read(sub, 0.2)
            pose = typed(item, wire.Pose, svc.reject) if item is not None else None
            if item is None or pose is None:
                continue
            d = filt.process(pose)
            account(svc, vehicle, pose, d, filt.rc)
            if d.vision is not None:
                pub.put(d.vision)
                svc.stats.count("out")
                svc.stats.latency((time.time_ns() - item.t_recv) * 1e-9)


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The vehicle to serve.")],
    rate: Annotated[
        float | None, typer.Option("--rate", help="Vision rate in Hz (default: the vehicle's vision_rate).")
    ] = None,
) -> None:
    """One vehicle's poses decimated by time to its vision rate (arena/<drone>/vision)."""
    main(shared.config, shared.bus, vehicle=vehicle, rate=rate, host=shared.host)


if __name__ == "__main__":
    typer.run(cli)
