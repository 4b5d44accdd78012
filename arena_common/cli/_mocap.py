"""``arena mocap probe``: what a Motive server says and streams, in a few seconds, without the bus.

It performs the NatNet handshake like the ingest service, listens for ``--duration`` seconds and prints the
server's identity (application, versions, clock, where it streams), the rigid bodies with their names,
rates, tracking and latencies, and the problems met. It never waits longer than asked: when nothing
answers it says what to check, and exits with status 1.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Annotated

import typer

from arena_common.mocap import natnet
from arena_common.mocap.client import MocapError, NatNetClient, TimedFrame, local_address_towards

mocap_app = typer.Typer(help="Look at the motion-capture server.", no_args_is_help=True)


@dataclass
class BodyStats:
    """What was seen of one rigid body during a probe."""

    id: int
    frames: int = 0
    tracked: int = 0
    first: int = 0
    last: int = 0
    lat_ns: list[int] = field(default_factory=list)

    def add(self, frame: TimedFrame, tracked: bool) -> None:
        if self.frames == 0:
            self.first = frame.arrival
        self.frames += 1
        self.tracked += tracked
        self.last = frame.arrival
        if frame.lat >= 0:
            self.lat_ns.append(frame.lat)

    @property
    def rate(self) -> float:
        span = (self.last - self.first) / 1e9
        return (self.frames - 1) / span if self.frames > 1 and span > 0 else 0.0


def _ms(ns: float) -> str:
    return f"{ns / 1e6:.2f}"


def probe(
    server: Annotated[str, typer.Option("--server", "-s", help="The Motive computer's IPv4 address.")],
    interface: Annotated[
        str | None,
        typer.Option(
            "--interface", "-i", help="This computer's address on the mocap network (default: the route's)."
        ),
    ] = None,
    command_port: Annotated[
        int, typer.Option("--command-port", help="Motive's command port.")
    ] = natnet.COMMAND_PORT,
    unicast: Annotated[bool, typer.Option("--unicast", help="Ask for unicast instead of multicast.")] = False,
    duration: Annotated[float, typer.Option("--duration", "-d", help="Seconds to listen.")] = 3.0,
) -> None:
    """Handshake with a NatNet server, listen for a while, print what it streams, exit."""
    if not 0 < duration <= 3600:
        raise typer.BadParameter("--duration must be in (0, 3600] seconds")
    iface = interface or local_address_towards(server, command_port)
    try:
        client = NatNetClient(
            server,
            command_port=command_port,
            interface=iface,
            multicast=not unicast,
            loss_timeout=duration + 1.0,  # no reconnection during a probe
            retry=0.25,
            max_backoff=1.0,
        )
        client.open()
    except MocapError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    bodies: dict[int, BodyStats] = {}
    numbers: list[int] = []
    tsrc: dict[str, int] = {}
    start = time.monotonic()
    try:
        while (left := start + duration - time.monotonic()) > 0:
            frame = client.poll(min(0.1, left))
            if frame is None:
                continue
            numbers.append(frame.frame_number)
            tsrc[frame.tsrc] = tsrc.get(frame.tsrc, 0) + 1
            for body in frame.bodies:
                stats = bodies.get(body.id)
                if stats is None:
                    stats = bodies[body.id] = BodyStats(body.id)
                stats.add(frame, body.tracking_valid)
    finally:
        client.close()
    _report(client, server, command_port, iface, unicast, duration, bodies, numbers, tsrc)


def _report(
    client: NatNetClient,
    server: str,
    command_port: int,
    iface: str,
    unicast: bool,
    duration: float,
    bodies: dict[int, BodyStats],
    numbers: list[int],
    tsrc: dict[str, int],
) -> None:
    info = client.last_info
    echo = typer.echo
    if info is None:
        echo(
            f"no answer from {server}:{command_port} within {duration:g} s "
            f"({client.counts.get('connect', 0)} CONNECT sent from {iface}).\n"
            "Check that Motive runs with streaming enabled, that this is its address and command port, "
            "and that no firewall drops UDP on that port.",
            err=True,
        )
        raise typer.Exit(1)
    clock = f", clock {info.clock_frequency:,} Hz" if info.clock_frequency else ""
    echo(
        f"server {server}:{command_port}: {info.app_name} {info.app_version}, NatNet {info.natnet_version}"
        f"{clock}"
    )
    if info.is_multicast is not None:
        where = (
            f"multicast {info.multicast_group}:{info.data_port}"
            if info.is_multicast
            else f"unicast (data port {info.data_port})"
        )
        echo(f"server streams: {where}")
    if unicast:
        listen = "unicast on the command socket"
    else:
        group, port = client.data_address or ("?", "?")
        listen = f"multicast {group}:{port}"
    echo(f"listening: {listen}, interface {iface or '0.0.0.0'}")
    sync = client.clock
    if sync is not None and sync.rtt_ns is not None:
        echo(f"clock sync: echo, best round trip {_ms(sync.rtt_ns)} ms over {sync.samples} round trips")
    elif info.clock_frequency:
        echo("clock sync: no echo answered (times fall back to arrival minus latency)")
    if not numbers:
        echo(
            f"no frame arrived in {duration:g} s. {info.app_name} answered, so check that it streams "
            "(Broadcast Frame Data on), the interface address (the multicast group is joined there), "
            f"and multicast vs unicast ({'--unicast given' if unicast else 'try --unicast'}).",
            err=True,
        )
        _problems(client)
        raise typer.Exit(1)
    span = duration
    echo(
        f"frames: {len(numbers)} in {span:.1f} s, numbers {numbers[0]}..{numbers[-1]}, "
        f"times from {', '.join(f'{k} ({v})' for k, v in sorted(tsrc.items()))}"
    )
    names = client.names
    width = max([4, *(len(names.get(i, "")) for i in bodies)])
    echo(f"rigid bodies ({len(bodies)}):")
    echo(f"  {'id':>5}  {'name':<{width}}  {'rate Hz':>8}  {'tracked':>7}  {'latency p50 / max ms':>20}")
    for body_id in sorted(bodies):
        b = bodies[body_id]
        lats = sorted(b.lat_ns)
        latency = f"{_ms(lats[len(lats) // 2])} / {_ms(lats[-1])}" if lats else "unknown"
        tracked = f"{100.0 * b.tracked / b.frames:.0f}%"
        echo(
            f"  {body_id:>5}  {names.get(body_id, '?'):<{width}}  {b.rate:>8.1f}  {tracked:>7}  {latency:>20}"
        )
    _problems(client)


def _problems(client: NatNetClient) -> None:
    if client.rejected:
        text = ", ".join(f"{k} {v}" for k, v in sorted(client.rejected.items()))
        typer.echo(f"problems: {text}")


def register(app: typer.Typer) -> None:
    """Add ``mocap`` to ``app``."""
    mocap_app.command("probe")(probe)
    app.add_typer(mocap_app, name="mocap")
