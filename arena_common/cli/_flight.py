"""Flight commands and live views: ``status``, ``top``, ``arm``…``kill`` and ``estop``."""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Iterable
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.live import Live
from rich.table import Table

from arena_common.bus.session import Bus
from arena_common.cli._globals import config as global_config
from arena_common.cli._globals import current as global_options
from arena_common.client import Arena, Vehicle
from arena_common.core import keys, ops, wire
from arena_common.core.arrival import ARRIVAL_TOLERANCE
from arena_common.core.errors import ArenaError

console = Console()
err_console = Console(stderr=True)

Target = Annotated[str, typer.Argument(help="Vehicle name, or 'all' for every vehicle alive on the bus.")]
Timeout = Annotated[float, typer.Option("--timeout", help="Seconds to wait for the vehicle.")]


def _arena() -> Arena:
    cfg = global_config(required=False)
    g = global_options()
    return Arena(cfg, connect=g.connect, mode=g.mode, name="arena-cli")


def _rtt(s: wire.State) -> str:
    """The link's round trip and its jitter, in ms."""
    if s.rtt is None:
        return ""
    return f"{1000 * s.rtt:.1f}" + ("" if s.rtt_jit is None else f" ±{1000 * s.rtt_jit:.1f}")


class Snapshot:
    """What the bus says right now: services alive, their stats, each vehicle's state."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.stats: dict[str, wire.Stats] = {}
        self.states: dict[str, wire.State] = {}
        self.state_time: dict[str, float] = {}
        self._stats = bus.subscribe(keys.STATS_ALL, capacity=512, ring=True)
        self._states = bus.subscribe("arena/*/state", capacity=512, ring=True)
        self.clocks: dict[str, wire.ClockOffset] = {}
        self._clocks = bus.subscribe(keys.CLOCK_ALL, capacity=512, ring=True)

    def refresh(self) -> None:
        for item in self._stats.channel.drain():
            if isinstance(item.payload, wire.Stats):
                self.stats[f"{item.payload.host}/{item.payload.service}"] = item.payload
        for item in self._states.channel.drain():
            if isinstance(item.payload, wire.State):
                name = item.key.split("/")[1]
                self.states[name] = item.payload
                self.state_time[name] = time.monotonic()
        for item in self._clocks.channel.drain():
            if isinstance(item.payload, wire.ClockOffset):
                self.clocks[f"{item.payload.host}/{item.payload.service}"] = item.payload

    def render(self, vehicles_first: bool = False) -> Table:
        """The services, vehicles and clocks tables (vehicles first: what a terminal too short still shows)."""
        alive = self.bus.alive(keys.ALIVE_ALL, 0.5)
        services = Table(title="services", title_justify="left")
        for col in ("host", "service", "in/s", "out/s", "rej", "lost", "cpu %", "MB", "up s"):
            services.add_column(col, justify="right" if col not in ("host", "service") else "left")
        for key in alive:
            host, service = key.split("/")[-2:]
            st = self.stats.get(f"{host}/{service}")
            if st is None:
                services.add_row(host, service, "", "", "", "", "", "", "")
                continue
            rej = sum(int(v) for v in st.rejected.values())
            services.add_row(
                host,
                service,
                f"{st.rates.get('in', 0):.0f}",
                f"{st.rates.get('out', 0):.0f}",
                f"[red]{rej}[/]" if rej else "0",
                _lost(sum(int(v) for v in st.lost.values())),
                f"{st.cpu:.1f}",
                f"{st.rss / 1e6:.0f}",
                f"{st.up:.0f}",
            )
        vehicles = Table(title="vehicles", title_justify="left")
        for col in (
            "vehicle",
            "link",
            "armed",
            "mode",
            "held by",
            "landed",
            "N E D [m]",
            "bat",
            "vision",
            "link rtt ms",
            "stamps",
            "lost",
            "failsafes",
        ):
            vehicles.add_column(col)
        lost = lost_by_vehicle(self.stats.values())
        for name in sorted(self.states):
            s = self.states[name]
            age = time.monotonic() - self.state_time[name]
            p = s.p or (math.nan, math.nan, math.nan)
            link = "[green]ok[/]" if s.link and age < 2 else "[red]lost[/]"
            vis_age = "" if s.vis_age is None else f" {1000 * s.vis_age:.0f}ms"
            vision = f"{s.vis_rate:.0f}Hz{vis_age} " + (
                "[green]fused[/]" if s.vis_fused else "[red]not fused[/]"
            )
            vehicles.add_row(
                name,
                link,
                "[yellow]ARMED[/]" if s.armed else "no",
                s.mode,
                s.auth or "autopilot",
                s.landed,
                f"{p[0]:+.2f} {p[1]:+.2f} {p[2]:+.2f}",
                "" if s.bat is None else f"{100 * s.bat:.0f}%",
                vision,
                _rtt(s),
                s.stamps if s.stamps != "arrival" else "[yellow]arrival[/]",
                _lost(lost.get(name, 0)),
                ", ".join(s.fs),
            )
        grid = Table.grid()
        for table in (vehicles, services) if vehicles_first else (services, vehicles):
            grid.add_row(table)
        grid.add_row(clock_table(self.clocks))
        return grid


def _lost(n: int) -> str:
    return f"[red]{n}[/]" if n else "0"


def lost_by_key(stats: Iterable[wire.Stats]) -> dict[str, int]:
    """Samples the arena's services counted lost on the bus, per key (a key two services take: the larger
    count, as both miss what the bus shed before it reached them)."""
    out: dict[str, int] = {}
    for st in stats:
        for key, n in st.lost.items():
            out[key] = max(out.get(key, 0), int(n))
    return out


def lost_by_vehicle(stats: Iterable[wire.Stats]) -> dict[str, int]:
    """Samples lost on the bus per vehicle: on its own keys (``arena/<vehicle>/…``)."""
    out: dict[str, int] = defaultdict(int)
    for key, n in lost_by_key(stats).items():
        parts = key.split("/")
        if len(parts) > 2 and parts[0] == "arena" and parts[1] != "sys":
            out[parts[1]] += n
    return dict(out)


def clock_table(clocks: dict[str, wire.ClockOffset]) -> Table:
    """One row per host: its clock offset to the mocap host's (the best-measured of its services)."""
    table = Table(title="clocks (offset to the mocap host's clock)", title_justify="left")
    for col in ("host", "state", "offset ms", "± ms", "rtt ms", "reference", "by"):
        table.add_column(col, justify="right" if col.endswith("ms") else "left")
    best: dict[str, wire.ClockOffset] = {}
    for c in clocks.values():
        b = best.get(c.host)
        rank = (c.state != "reference", c.unc is None, c.unc if c.unc is not None else 0.0)
        if b is None or rank < (b.state != "reference", b.unc is None, b.unc if b.unc is not None else 0.0):
            best[c.host] = c
    for host in sorted(best):
        c = best[host]
        colour = {"reference": "green", "ok": "green", "uncertain": "red", "unknown": "red"}.get(
            c.state, "yellow"
        )
        offset = "" if c.off is None else f"{1000 * c.off:+.2f}"
        if c.off is not None and c.state == "ok" and abs(c.off) > 0.01:
            offset = f"[red]{offset}[/] (chrony!)"
        table.add_row(
            host,
            f"[{colour}]{c.state}[/]",
            offset,
            "" if c.unc is None else f"{1000 * c.unc:.2f}",
            "" if c.rtt is None else f"{1000 * c.rtt:.2f}",
            c.ref,
            c.service,
        )
    return table


def status(
    watch: Annotated[bool, typer.Option("--watch", "-w", help="Keep the table live until Ctrl-C.")] = False,
    wait: Annotated[float, typer.Option("--wait", help="Seconds to listen before printing.")] = 1.2,
) -> None:
    """Every service and vehicle alive on the bus, from any machine: host, rates, armed, mode, battery."""
    with _arena() as arena:
        snap = Snapshot(arena.bus)
        time.sleep(wait)
        snap.refresh()
        if not watch:
            console.print(snap.render())
            return
        with Live(snap.render(), console=console, refresh_per_second=2) as live:
            try:
                while True:
                    time.sleep(0.5)
                    snap.refresh()
                    live.update(snap.render())
            except KeyboardInterrupt:
                pass


def top(
    keyexpr: Annotated[str, typer.Argument(help="Keys to watch.")] = "arena/**",
    duration: Annotated[float, typer.Option("--duration", help="Stop after S seconds (0: Ctrl-C).")] = 0.0,
) -> None:
    """Rates, latencies (receive time minus measurement time) and losses per key, live: what this viewer
    missed on the bus (gaps in the publishers' numbers) and what the arena's services counted missed."""
    with _arena() as arena:
        sub = arena.bus.subscribe(keyexpr, capacity=100_000, ring=False)
        counts: dict[str, int] = defaultdict(int)
        lats: dict[str, list[float]] = defaultdict(list)
        clocks: dict[str, wire.ClockOffset] = {}
        stats: dict[str, wire.Stats] = {}
        end = time.monotonic() + duration if duration > 0 else math.inf

        def table(dt: float) -> Table:
            t = Table(title=f"{keyexpr} — last {dt:.1f} s")
            for col in ("key", "Hz", "lat p50 ms", "lat p99 ms", "lat max ms", "lost here", "lost (arena)"):
                t.add_column(col, justify="left" if col == "key" else "right")
            arena_lost = lost_by_key(stats.values())
            for k in sorted(counts):
                ls = sorted(lats[k])
                fig = (
                    [f"{1000 * ls[int(q * (len(ls) - 1))]:.2f}" for q in (0.5, 0.99, 1.0)]
                    if ls
                    else ["", "", ""]
                )
                here = sub.gaps.keys.get(k)
                t.add_row(
                    k,
                    f"{counts[k] / dt:.1f}",
                    *fig,
                    _lost(here.lost if here else 0),
                    _lost(arena_lost.get(k, 0)),
                )
            if not clocks:
                return t
            grid = Table.grid()
            grid.add_row(t)
            grid.add_row(clock_table(clocks))
            return grid

        last = time.monotonic()
        with Live(table(1.0), console=console, refresh_per_second=1) as live:
            try:
                while time.monotonic() < end:
                    item = sub.get(0.1)
                    if item is not None and item.payload is not None:
                        counts[item.key] += 1
                        if isinstance(item.payload, wire.ClockOffset):
                            clocks[f"{item.payload.host}/{item.payload.service}"] = item.payload
                        elif isinstance(item.payload, wire.Stats):
                            stats[f"{item.payload.host}/{item.payload.service}"] = item.payload
                        t = getattr(item.payload, "t", 0)
                        if t:
                            lats[item.key].append((item.t_recv - t) / 1e9)
                    if time.monotonic() - last >= 1.0:
                        live.update(table(time.monotonic() - last))
                        counts.clear()
                        lats.clear()
                        last = time.monotonic()
            except KeyboardInterrupt:
                pass


def _targets(arena: Arena, target: str) -> list[Vehicle]:
    names = arena.vehicles() if target == "all" else [target]
    if not names:
        err_console.print("[red]error:[/] no vehicle is alive on the bus")
        raise typer.Exit(1)
    return [arena.vehicle(n) for n in names]


def _act(target: str, what: str, action: Any) -> None:
    try:
        with _arena() as arena:
            vehicles = _targets(arena, target)
            arena.swarm(v.name for v in vehicles).run(action)
    except ArenaError as exc:
        err_console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(1) from None
    console.print(f"{what}: {', '.join(v.name for v in vehicles)} [green]ok[/]")


def arm(
    target: Target,
    timeout: Timeout = 5.0,
) -> None:
    """Arm the motors."""
    _act(target, "armed", lambda v: v.arm(timeout))


def disarm(
    target: Target,
    timeout: Timeout = 5.0,
) -> None:
    """Disarm the motors (refused in the air; see kill)."""
    _act(target, "disarmed", lambda v: v.disarm(timeout))


def takeoff(
    target: Target,
    height: Annotated[float, typer.Argument(help="Height above the floor (m).")] = 1.0,
    timeout: Timeout = 20.0,
) -> None:
    """Take off to a height and wait until there."""
    _act(target, f"at {height} m", lambda v: v.takeoff(height, timeout))


def land(
    target: Target,
    timeout: Timeout = 30.0,
) -> None:
    """Land and wait until on the ground and disarmed."""
    _act(target, "landed", lambda v: v.land(timeout))


def hold(target: Target) -> None:
    """Hold position."""
    _act(target, "holding", lambda v: v.hold())


def goto(
    target: Target,
    north: float,
    east: float,
    down: float,
    yaw: Annotated[float | None, typer.Option(help="Yaw (degrees).")] = None,
    tolerance: Annotated[
        float, typer.Option(help="Arrival tolerance (m) of the position averaged over the last second.")
    ] = ARRIVAL_TOLERANCE,
    timeout: Timeout = 30.0,
) -> None:
    """Fly to NORTH EAST DOWN (arena frame, metres; down is negative above the floor)."""
    yaw_rad = math.radians(yaw) if yaw is not None else None
    _act(
        target,
        f"at ({north}, {east}, {down})",
        lambda v: v.goto(north, east, down, yaw_rad, tolerance, timeout),
    )


def kill(target: Target) -> None:
    """Cut the motors now, in the air too."""
    _act(target, "killed", lambda v: v.kill())


def estop(
    kill_motors: Annotated[bool, typer.Option("--kill", help="Cut motors instead of landing.")] = False,
    reason: Annotated[str, typer.Option(help="Why (logged by every gateway).")] = "operator",
) -> None:
    """Stop everything: every vehicle lands at once (or cuts its motors with --kill)."""
    try:
        with _arena() as arena:
            arena.estop(kill=kill_motors, reason=reason)
            time.sleep(0.2)  # let the reliable publication leave before the session closes
    except ArenaError as exc:
        err_console.print(f"[red]error:[/] ESTOP NOT SENT: {exc}")
        raise typer.Exit(1) from None
    console.print("[red]ESTOP[/] sent: " + ("kill motors" if kill_motors else "land every vehicle"))


def register(app: typer.Typer) -> None:
    """Add the flight commands to ``app``."""
    app.command("status")(status)
    app.command("top")(top)
    # One command per operation of the table that flies a vehicle, its help the table's words.
    for fn in (arm, disarm, takeoff, land, hold, kill):
        app.command(
            fn.__name__, help=f"{ops.OPS[fn.__name__].doc[:1].upper()}{ops.OPS[fn.__name__].doc[1:]}."
        )(fn)
    # Heights above the floor are negative downs: let "-1.0" be a value, not an unknown option.
    app.command("goto", help=f"{ops.OPS['goto'].doc[:1].upper()}{ops.OPS['goto'].doc[1:]}.",
                context_settings={"ignore_unknown_options": True})(goto)  # fmt: skip
    app.command("estop")(estop)
