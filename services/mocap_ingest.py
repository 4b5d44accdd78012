"""Mocap ingest: rigid bodies from Motive (or another source) → ``arena/sys/frames`` and ``arena/<drone>/mocap``.

Reads frames from the source ``mocap.source`` names (NatNet by default, see
:mod:`arena_common.mocap.sources`), maps each rigid body to its vehicle by the name or id the config gives
(``vehicles.<name>.rigid_body``) and publishes, still in Motive's frame and with its measurement time, one
:class:`~arena_common.core.wire.MocapFrame` per frame with every claimed body on ``arena/sys/frames`` (what
the frame transform reads: one message per frame, not one per body) and, while someone subscribes to it, a
:class:`~arena_common.core.wire.MocapPose` per body on its vehicle's ``mocap`` key. Untracked bodies are
published with ``ok=False``;
bodies no vehicle claims are counted and, with ``mocap.publish_unknown``, published on
``arena/sys/bodies/<body>``. Every problem the source meets is counted in the service's stats under its
reason; the service reconnects by itself and never stops on bad input.
"""

from __future__ import annotations

import threading

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.mocap.client import MocapError
from arena_common.mocap.sources import MocapSource, describe_source, open_source
from arena_common.pipeline.ingest import Ingest
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.mocap_ingest").name  # its one name: arena_common/core/services.py


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
    loss_timeout: float = 1.0,
) -> None:
    """Run until ``stop`` is set (or SIGINT/SIGTERM)."""
    # The ingest's clock stamps every pose: it is the arena's time reference (arena/sys/time).
    with running(SERVICE, cfg, options, host=host, stop=stop, clock_reference=True) as svc:
        ingest = Ingest(svc, cfg)
        source: MocapSource | None = None
        backoff = 0.5
        finished = False
        svc.log.info("source %s (%s), %d vehicles", cfg.mocap.source, describe_source(cfg), len(cfg.vehicles))
        try:
            while not svc.stopped:
                if source is None:
                    candidate = open_source(
                        cfg, on_reject=svc.reject, on_count=svc.stats.count, loss_timeout=loss_timeout
                    )
                    try:
                        candidate.open()
                    except MocapError as exc:
                        svc.reject("setup", str(exc))
                        svc.sleep(backoff)
                        backoff = min(backoff * 2, 5.0)
                        continue
                    source, backoff = candidate, 0.5
                frame = source.poll(0.2)
                if frame is not None:
                    ingest.handle(frame)
                elif not finished and getattr(source, "finished", False):
                    finished = True
                    svc.log.info("the source has no more frames")
        finally:
            if source is not None:
                source.close()


@service_command
def cli(
    shared: Shared,
) -> None:
    """Receive Motive's rigid bodies; publish each frame on arena/sys/frames and each vehicle's on
    arena/<drone>/mocap."""
    main(shared.config, shared.bus, host=shared.host)


if __name__ == "__main__":
    typer.run(cli)
