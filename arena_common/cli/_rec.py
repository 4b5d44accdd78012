"""Recordings: ``arena rec info|repair|start|stop|status``, ``arena replay|export|plot``."""

from __future__ import annotations

import gc
import threading
import time
from pathlib import Path
from typing import Annotated, Any

import typer
import zenoh

from arena_common.bus.session import open_bus
from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError
from arena_common.core.services import missing_extra
from arena_common.recording import mcap as recording
from arena_common.runtime.options import (
    HostOpt,
)
from arena_common.runtime.service import running, setup_logging

rec_app = typer.Typer(help="Recordings: inspect, repair, and start/stop the recorders.", no_args_is_help=True)

FileArg = Annotated[Path, typer.Argument(help="An MCAP recording.", exists=True, dir_okay=False)]
RecorderOpt = Annotated[
    str, typer.Option("--recorder", "-r", help="Host of the recorder to control ('*': every recorder).")
]
STREAM_KINDS = frozenset(
    {"mocap", "frames", "pose", "vision", "state", "telemetry", "setpoint", "truth", "stats", "bodies"}
)


def _fail(exc: Exception) -> typer.Exit:
    typer.echo(f"error: {exc}", err=True)
    return typer.Exit(2)


@rec_app.command("info")
def info_cmd(files: Annotated[list[Path], typer.Argument(help="MCAP recordings.")]) -> None:
    """Duration, channels (key, schema, encoding), counts, rates, largest gaps and drops of each file."""
    for i, f in enumerate(files):
        try:
            ri = recording.info(f)
        except (ArenaError, OSError) as exc:
            raise _fail(exc) from None
        if i:
            typer.echo("")
        typer.echo(recording.format_info(ri))


@rec_app.command("repair")
def repair_cmd(
    file: FileArg,
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Default: FILE.repaired.mcap.")
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the output if it exists.")] = False,
) -> None:
    """Write a complete copy (index, summary) of everything readable in an unfinished recording."""
    try:
        rep = recording.repair(file, output, force=force)
    except (ArenaError, OSError) as exc:
        raise _fail(exc) from None
    state = (
        "was complete" if rep.source_complete else f"was not finalized ({rep.source_error or 'no footer'})"
    )
    typer.echo(f"{rep.output}: {rep.messages} messages on {rep.channels} channels ({rep.source} {state})")


def _control(
    op: str,
    args: dict[str, Any],
    target: str,
    timeout: float = 5.0,
) -> None:
    if target != "*":
        keys.validate_name(target, "host name")
    cfg = global_config(required=False)
    key = f"{keys.ROOT}/sys/rec/{target}"
    command = wire.Command(op=op, args=args, src="arena rec", timeout=timeout, t=wire.now_ns())
    results: list[tuple[str, wire.CommandResult]] = []
    with open_bus(cfg.zenoh if cfg else None, global_bus()) as bus:
        deadline = time.monotonic() + timeout

        def ask(cmd: wire.Command) -> list[tuple[str, wire.CommandResult]]:
            out: list[tuple[str, wire.CommandResult]] = []
            replies = bus.session.get(
                key,
                payload=cmd.encode(),
                encoding=zenoh.Encoding(cmd.encoding()),
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,  # every recorder's answer, not the latest
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for reply in replies:
                if reply.ok is not None:
                    src = str(reply.ok.key_expr)
                    try:
                        out.append((src, wire.CommandResult.decode(reply.ok.payload.to_bytes(), src)))
                    except ArenaError as exc:
                        out.append((src, wire.CommandResult(False, "ERROR", f"bad reply: {exc}")))
            return out

        # A fresh session learns the recorders' queryables one by one: ping (harmless to repeat) until every
        # recorder alive has answered, then send the order once, so that it reaches all of them.
        alive = {k.split("/")[-2] for k in bus.alive(f"{keys.ROOT}/sys/alive/{target}/recorder")}
        ping = wire.Command(op="ping", src="arena rec", timeout=timeout, t=wire.now_ns())
        while alive and time.monotonic() < deadline:  # no recorder alive: nobody to wait for
            results = ask(ping)
            if results and alive <= {src.rsplit("/", 1)[-1] for src, _ in results}:
                break
            time.sleep(0.2)
        if op != "ping" and results:
            results = ask(command)
    if not results:
        typer.echo(f"error: no recorder answers on {key}", err=True)
        raise typer.Exit(1)
    failed = False
    for src, res in sorted(results, key=lambda r: str(r[1].value.get("host", r[0]))):
        v = res.value
        host = str(v.get("host") or src.rsplit("/", 1)[-1])
        if op == "ping":
            typer.echo(
                f"{host}: {v.get('state')} {v.get('file') or '-'} — {v.get('file_messages', 0)} messages in "
                f"this file, {v.get('messages', 0)} in all, {v.get('undecodable', 0)} undecodable, "
                f"{v.get('dropped', 0)} dropped{'; ' + str(v.get('reason')) if v.get('reason') else ''}"
            )
        else:
            typer.echo(f"{host}: {res.result} {res.reason}")
        failed = failed or not res.ok
    if failed:
        raise typer.Exit(1)


@rec_app.command("start")
def start_cmd(
    name: Annotated[str, typer.Argument(help="Experiment name (letters, digits, '_', '-', '.').")],
    recorder: RecorderOpt = "*",
) -> None:
    """Start a new file NAME_<host>_<time>.mcap on the recorders."""
    try:
        keys.validate_name(name, "experiment name")
    except ArenaError as exc:
        raise _fail(exc) from None
    _control("start", {"name": name}, recorder)


@rec_app.command("stop")
def stop_cmd(
    recorder: RecorderOpt = "*",
) -> None:
    """Close the current file; the recorders idle until the next `rec start` (or arming)."""
    _control("stop", {}, recorder)


@rec_app.command("status")
def status_cmd(
    recorder: RecorderOpt = "*",
) -> None:
    """What each recorder is doing: state, file, counters."""
    _control("ping", {}, recorder)


def _declare(session: zenoh.Session, key: str, encoding: str) -> zenoh.Publisher:
    """A publisher with the QoS the key has in the arena (streams drop when congested, the rest block)."""
    try:
        stream = keys.parse(key).kind in STREAM_KINDS
    except ArenaError:
        stream = False
    return session.declare_publisher(
        key,
        encoding=zenoh.Encoding(encoding or "zenoh/bytes"),
        congestion_control=zenoh.CongestionControl.DROP if stream else zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.BEST_EFFORT if stream else zenoh.Reliability.RELIABLE,
    )


def replay_cmd(
    file: FileArg,
    speed: Annotated[float, typer.Option("--speed", help="Time factor (2: twice as fast).")] = 1.0,
    key_exprs: Annotated[
        list[str] | None,
        typer.Option("--keys", "-k", help="Only keys matching (repeatable; default arena/**)."),
    ] = None,
    remap: Annotated[
        list[str] | None, typer.Option("--remap", help="Rename a key prefix: FROM=TO (repeatable).")
    ] = None,
    loop: Annotated[bool, typer.Option("--loop", help="Start again at the end, until Ctrl-C.")] = False,
    include_control: Annotated[
        bool,
        typer.Option("--all", help="Also setpoints, estop and arena/sys/** (commands live vehicles!)."),
    ] = False,
    start_delay: Annotated[
        float,
        typer.Option("--start-delay", help="Wait up to this long for a subscriber before the first message."),
    ] = 2.0,
    host: HostOpt = None,
) -> None:
    """Publish a recording again with its original timing, bytes and encodings."""
    try:
        mapping = recording.parse_remap(remap or [])
    except ArenaError as exc:
        raise _fail(exc) from None
    cfg = global_config(required=False)
    setup_logging("WARNING")
    stop = threading.Event()
    with running("replay", cfg, global_bus(), host=host, stop=stop) as svc:
        pubs: dict[tuple[str, str], Any] = {}

        def publish(key: str, data: bytes, encoding: str) -> None:
            pub = pubs.get((key, encoding))
            if pub is None:
                pub = pubs[(key, encoding)] = _declare(svc.bus.session, key, encoding)
            pub.put(data)
            svc.stats.count("out")

        try:
            # Declare every publisher first and wait until a subscriber is known, so that the first
            # messages are not sent before the bus has routes for them.
            wanted = recording.key_filter(key_exprs or ["arena/**"], include_control)
            for ch in recording.channels(file):
                if wanted(ch.key):
                    publish_key = recording.remap_key(ch.key, mapping)
                    pubs[(publish_key, ch.zenoh_encoding)] = _declare(
                        svc.bus.session, publish_key, ch.zenoh_encoding
                    )
            # Everything allocated so far is long-lived: keep the collector from scanning it mid-schedule.
            gc.collect()
            gc.freeze()
            deadline = time.monotonic() + max(0.0, start_delay)
            while time.monotonic() < deadline and not any(p.matching_status.matching for p in pubs.values()):
                if svc.sleep(0.02):
                    return
            rep = recording.replay(
                file,
                publish,
                speed=speed,
                key_exprs=key_exprs or ["arena/**"],
                remap=mapping,
                loop=loop,
                include_control=include_control,
                stop=stop,
            )
        except (ArenaError, OSError) as exc:
            raise _fail(exc) from None
        finally:
            for p in pubs.values():
                p.undeclare()
    typer.echo(
        f"replayed {rep.sent} messages in {rep.passes} pass(es), skipped {rep.skipped}, "
        f"worst lateness {rep.late_max * 1000:.1f} ms"
    )


def export_cmd(
    file: FileArg,
    fmt: Annotated[str, typer.Option("--format", "-f", help="csv or parquet.")] = "csv",
    output: Annotated[Path, typer.Option("--output", "-o", help="Directory of the tables.")] = Path("export"),
    ros2: Annotated[
        bool,
        typer.Option(
            "--ros2",
            help="Write a ROS 2 MCAP instead (ros2msg schemas, CDR): <output>/<name>.ros2.mcap, or --output "
            "FILE.mcap; for ros2 bag play, Foxglove, PlotJuggler (docs/ros2.md).",
        ),
    ] = False,
) -> None:
    """One table per key, nested fields flattened (p.0, p.1, p.2…), with time columns; or a ROS 2 bag."""
    if ros2:
        why = missing_extra("ros2")
        if why:
            raise _fail(ArenaError(f"--ros2: {why}"))
        from arena_common.ros2.export import export_ros2  # rosbags loads only when asked for

        try:
            target, count = export_ros2(file, output)
        except (ArenaError, OSError) as exc:
            raise _fail(exc) from None
        typer.echo(f"{target} ({count} ROS 2 messages)")
        return
    try:
        written = recording.export(file, output, fmt)
    except (ArenaError, OSError) as exc:
        raise _fail(exc) from None
    for p in written:
        typer.echo(str(p))


def plot_cmd(
    file: FileArg,
    output: Annotated[Path, typer.Option("--output", "-o", help="Directory of the PNG figures.")] = Path(
        "plots"
    ),
) -> None:
    """PNG figures: paths in the arena (top and side), pose vs estimate, tracking error, vision, battery."""
    from arena_common.recording import plots  # matplotlib is slow to import: only when plotting

    try:
        written = plots.plot_recording(file, output)
    except (ArenaError, OSError) as exc:
        raise _fail(exc) from None
    for p in written:
        typer.echo(str(p))


def register(app: typer.Typer) -> None:
    """Add ``rec``, ``replay``, ``export`` and ``plot`` to ``app``."""
    app.add_typer(rec_app, name="rec")
    app.command("replay")(replay_cmd)
    app.command("export")(export_cmd)
    app.command("plot")(plot_cmd)
