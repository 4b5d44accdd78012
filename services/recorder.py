"""Telemetry recorder: every sample on ``recorder.keys`` (default ``arena/**``) into MCAP files.

Samples go from Zenoh's callbacks through one bounded FIFO to this loop, which writes them (see
:mod:`arena_common.recording.mcap`) with, beside them, the Foxglove 3D scene they make (the room from
the config's ``[arena]``; :mod:`arena_common.recording.scene`); if the disk falls behind, the FIFO
drops and the drops are written into the file.  The file is flushed and fsynced every
``recorder.flush_s``, split by ``split_mb`` / ``split_s``, and a new one starts per experiment:
``arena rec start NAME`` / ``arena rec stop`` query ``arena/sys/rec/<host>`` (ops ``start`` {name},
``stop``, ``ping``), or on arming with ``auto_on_arm``.
Recording starts at once into ``rec_<host>_<time>.mcap``.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Annotated, Any

import typer
import zenoh

from arena_common.bus.session import BusOptions, Channel, Received, Subscription
from arena_common.core import keys
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.recording.mcap import Recorder, Sample
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.recorder").name  # its one name: arena_common/core/services.py

QUEUE_CAPACITY = 50_000  # samples; ≈10 s of a busy arena


def key_exprs(cfg: ArenaConfig) -> list[str]:
    """The key expressions to subscribe to; adds ``arena/*/state`` when ``auto_on_arm`` needs it."""
    exprs = list(cfg.recorder.keys)
    if cfg.recorder.auto_on_arm and not any(
        zenoh.KeyExpr(e).includes(zenoh.KeyExpr("arena/*/state")) for e in exprs
    ):
        exprs.append("arena/*/state")
    return exprs


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
    directory: str | Path | None = None,
    name: str | None = None,
) -> None:
    """Record until ``stop`` is set (or SIGINT/SIGTERM); ``directory`` overrides ``recorder.directory``."""
    with running(SERVICE, cfg, options, host=host, stop=stop) as svc:
        try:
            config_text = Path(cfg.path).read_text(encoding="utf-8")
        except OSError:
            config_text = ""

        def on_event(text: str, severity: int) -> None:
            (svc.log.error if severity <= 3 else svc.log.warning if severity == 4 else svc.log.info)(text)
            if severity <= 4:
                svc.stats.count("trouble")

        rec = Recorder(
            cfg.recorder,
            svc.host,
            directory=directory,
            config_path=cfg.path,
            config_text=config_text,
            on_event=on_event,
            arena=cfg.arena,
        )
        exprs = key_exprs(cfg)
        for i, a in enumerate(exprs):
            for b in exprs[i + 1 :]:
                if zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)):
                    svc.log.warning("keys %r and %r overlap: samples on both are recorded twice", a, b)
        queue: Channel[Received[Any]] = Channel(QUEUE_CAPACITY, ring=False)
        subs = [Subscription(svc.bus, expr, None, queue, keep_raw=False) for expr in exprs]
        rec.start(name)
        svc.bus.serve(keys.rec_control(svc.host), rec.handle)  # answers once the first file is open
        try:
            while not svc.stopped:
                item = queue.get(0.05)
                batch = [item, *queue.drain()] if item is not None else []
                for it in batch:
                    before = rec.undecodable
                    rec.write(Sample(it.key, it.raw, it.encoding, it.t_recv))
                    if rec.undecodable != before:
                        svc.reject("undecodable", f"{it.key}: not a valid payload ({it.encoding})")
                    svc.stats.count("in")
                new = rec.note_drops(queue.dropped)
                if new:
                    svc.stats.count("dropped", new)
                rec.tick()
        finally:
            for s in subs:
                s.close()
            for it in queue.drain():
                rec.write(Sample(it.key, it.raw, it.encoding, it.t_recv))
            rec.note_drops(queue.dropped)
            rec.close()
            svc.log.info("recorded %d samples into %d files", rec.messages, len(rec.files))


@service_command
def cli(
    shared: Shared,
    directory: Annotated[
        Path | None, typer.Option("--dir", "-d", help="Directory of the files (default: recorder.directory).")
    ] = None,
    name: Annotated[str | None, typer.Option("--name", help="Name of the first file (default: rec).")] = None,
) -> None:
    """Record the bus into MCAP files (Foxglove, PlotJuggler, `arena rec info`)."""
    main(shared.config, shared.bus, host=shared.host, directory=directory, name=name)


if __name__ == "__main__":
    typer.run(cli)
