"""``arena demo``: bring up the simulated arena, fly every vehicle in formation, show live status.

What ``make run`` runs.  The arena is started by the supervisor (``arena up``) as a child process whose
logs go to a file, so the terminal shows the live status table.

Stopping: Ctrl-C, SIGTERM and a closed terminal (SIGHUP) all stop the demo the same way
(:class:`~arena_common.runtime.process.StopSignals`): the flight program is abandoned, every vehicle in
the air is told to land and the demo waits until each one is on the ground and disarmed (at most
``--land-timeout`` seconds), then stops the arena (the supervisor stops its services).  A second Ctrl-C
(or SIGTERM) skips the wait and has the supervisor kill its services at once; a second SIGHUP does not
(a closing terminal and its shell each send one).  A demo that fails in flight (a command refused, a goal
not reached) lands what flies the same way before it stops the arena.  No thread of the demo keeps the
process alive once it is done: each vehicle's action runs in a daemon thread, left behind on a stop.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any

import tomlkit
import typer
from rich.console import Console, Group
from rich.live import Live
from rich.text import Text
from tomlkit.items import InlineTable

from arena_common.cli._flight import Snapshot
from arena_common.cli._globals import config_file as global_config_file
from arena_common.client import Arena, Vehicle
from arena_common.client.swarm import WANDER_MARGIN, clear_assignment
from arena_common.client.types import FlightMode, LandedState
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ArenaError
from arena_common.runtime.options import load_config
from arena_common.runtime.process import StopSignals, child_setup
from arena_common.runtime.supervisor import endpoint_address

console = Console()
WATCH_3D = (
    "watch in 3D: `arena view` in another terminal, then Foxglove → Open connection → "
    "ws://127.0.0.1:8765 with the layout deploy/foxglove/arena.json (docs/viewer.md)"
)
# s to wait for the vehicles to land once the demo is asked to stop: PX4 v1.16 takes 8.9-10.3 s from 1 m
# to landed and disarmed (its crawl below 1 m, its land detector, COM_DISARM_LAND; docs/px4.md, parity).
LAND_TIMEOUT = 20.0
STOP_TIMEOUT = 20.0  # s for the supervisor to stop its services before it is killed
RESEND_LAND = 2.0  # s between land orders to a vehicle still flying (not landing) while stopping
FLEET_RADIUS = 0.3  # m: the circle a fleet's grid flies around its spots
HOVER_SWING = 0.4  # m: the simulated PX4 hover's largest swing about its point (docs/px4.md)
# s a formation goal may wait for another vehicle to leave it (one held by the separation guard, one
# displaced by a stalled machine) before the goto is sent anyway, and refused if still blocked.
CLEAR_WAIT = 10.0
MAX_FLEET = 250  # MAVLink system ids 1..250
#: PX4 streams these on its onboard link at 30-100 Hz; the gateway reads none of them for itself, and a
#: program sees raw telemetry at the vehicle's telemetry_rate (10 Hz) at most: a fleet asks for 10 Hz.
FLEET_STREAMS: dict[str, float] = {
    "ATTITUDE": 10.0,
    "HIGHRES_IMU": 10.0,
    "ODOMETRY": 10.0,
    "GLOBAL_POSITION_INT": 10.0,
}


class Stopped(ArenaError):
    """The demo was asked to stop (a signal) while the flight program ran."""


class Say:
    """The demo's messages: kept for the live view (the last few are shown under the table) and printed
    as they come when the output is not a terminal (a log file, a pipe) or once :attr:`echo` is set (the
    stop: on a terminal, above the live view, where no terminal height hides them)."""

    def __init__(self, out: Console) -> None:
        self.out = out
        self.lines: list[str] = []
        self.echo = not out.is_terminal

    def __call__(self, text: str) -> None:
        self.lines.append(text)
        if self.echo:
            with contextlib.suppress(OSError, ValueError):  # the output may be gone
                self.out.print(text)

    def last(self, n: int = 6) -> list[str]:
        """The last ``n`` messages."""
        return self.lines[-n:]


def together(vehicles: Sequence[Vehicle], action: Callable[[Vehicle], object], stop: threading.Event) -> None:
    """Run ``action(vehicle)`` on every vehicle at once and wait for all; raise the first error.

    Each runs in a daemon thread: on ``stop`` this raises :class:`Stopped` within 0.1 s and leaves them
    behind (they end at their own timeouts and never keep the process alive, unlike a
    ``concurrent.futures`` pool, whose workers the interpreter joins at exit).
    """
    errors: list[tuple[str, BaseException]] = []

    def run(v: Vehicle) -> None:
        try:
            action(v)
        except BaseException as exc:  # reported by the caller
            errors.append((v.name, exc))

    threads = [threading.Thread(target=run, args=(v,), name=f"demo:{v.name}", daemon=True) for v in vehicles]
    for t in threads:
        t.start()
    for t in threads:
        while t.is_alive():
            if stop.is_set():
                raise Stopped("stopped")
            t.join(0.1)
    if stop.is_set():
        raise Stopped("stopped")
    if len(errors) == 1:
        raise errors[0][1]
    if errors:
        raise ArenaError("; ".join(f"{name}: {exc}" for name, exc in errors)) from errors[0][1]


def formation_flight(
    vehicles: Sequence[Vehicle],
    say: Callable[[str], None],
    stop: threading.Event,
    height: float = 1.0,
    radius: float = 1.0,
    steps: int = 6,
    spots: Mapping[str, tuple[float, float]] | None = None,
) -> None:
    """Arm, take off, fly a rotating triangle (or circle) formation around the arena centre, land.

    With ``spots`` (each vehicle's place on a grid, north and east, m: a fleet), the grid keeps its shape
    and its whole circles ``radius`` around the spots instead (no two vehicles' paths cross).
    :class:`Stopped` as soon as ``stop`` is set (no further command is sent then).
    """
    names = [v.name for v in vehicles]
    say("arming " + (", ".join(names) if len(names) <= 6 else f"{len(names)} vehicles"))
    together(vehicles, lambda v: v.arm(), stop)
    say(f"taking off to {height} m")
    together(vehicles, lambda v: v.takeoff(height), stop)
    for step in range(steps + 1):
        angle = step * 2 * math.pi / steps
        if spots is not None:
            targets = {
                n: (spots[n][0] + radius * math.cos(angle), spots[n][1] + radius * math.sin(angle))
                for n in names
            }
        else:
            if step == 0:
                order, offset = circle_slots(vehicles, radius)
            targets = {
                n: (
                    radius * math.cos(offset + angle + 2 * math.pi * i / len(order)),
                    radius * math.sin(offset + angle + 2 * math.pi * i / len(order)),
                )
                for i, n in enumerate(order)
            }
        say(f"formation step {step}/{steps}")

        def fly(v: Vehicle, t: dict[str, tuple[float, float]] = targets) -> None:
            goal = (t[v.name][0], t[v.name][1], -height)
            wait_clear(v, goal, stop)
            v.goto(*goal, yaw=0.0)

        together(vehicles, fly, stop)
    say("landing")
    together(vehicles, lambda v: v.land(), stop)
    say("landed: demo complete")


def wait_clear(v: Vehicle, goal: tuple[float, float, float], stop: threading.Event) -> None:
    """Wait, at most :data:`CLEAR_WAIT` s, until no other vehicle of the fleet message (what the gateway
    judges a goto by) is within ``arena.min_separation`` of ``goal``.  The formation's goals are clear of
    each other's places by design; one is not only when a vehicle is off its place (held by the separation
    guard, pushed off by a stall): then the step waits for it to move on instead of failing the demo.
    :class:`Stopped` when ``stop`` is set meanwhile: the goto must not follow the demo's land orders."""
    cfg = v.arena.config
    keep = cfg.arena.min_separation if cfg is not None else 0.0
    deadline = time.monotonic() + CLEAR_WAIT
    while time.monotonic() < deadline:
        if all(math.dist(q, goal) >= keep for n, q in v.arena.positions().items() if n != v.name):
            return
        if stop.wait(0.1):
            raise Stopped("stopped")


def circle_slots(vehicles: Sequence[Vehicle], radius: float) -> tuple[list[str], float]:
    """The order of the vehicles around the formation's circle and its starting angle such that each
    vehicle's way to its place is clear of the others (:func:`~arena_common.client.swarm.clear_assignment`:
    the gateways refuse a goto that is not); the given order at angle 0 when no angle gives one."""
    cfg = vehicles[0].arena.config if vehicles else None
    keep = (cfg.arena.min_separation if cfg is not None else 0.0) + WANDER_MARGIN
    here = {v.name: (v.position or (0.0, 0.0, 0.0)) for v in vehicles}
    n = len(here)
    for k in range(24):
        offset = k * math.pi / 12
        slots = [
            (radius * math.cos(offset + 2 * math.pi * i / n), radius * math.sin(offset + 2 * math.pi * i / n))
            for i in range(n)
        ]
        got = clear_assignment(here, slots, keep)
        if got is not None:
            return sorted(got, key=lambda name: slots.index(got[name])), offset  # type: ignore[arg-type]
    return list(here), 0.0


# -- a fleet: N simulated vehicles on a grid (--vehicles) ------------------------------------------------------


def fleet_spacing(min_separation: float) -> float:
    """How far apart a fleet's vehicles stand: ``arena.min_separation`` plus two hovers' largest swing
    (:data:`HOVER_SWING` each), so that two neighbours swinging toward each other still keep it."""
    return min_separation + 2.0 * HOVER_SWING


def grid(n: int, size: tuple[float, float], keep_off: float, least: float) -> list[tuple[float, float]]:
    """``n`` places (north, east, m, about the room's centre) ``least`` apart on a grid that fits a floor
    of ``size`` (north, east) at ``keep_off`` from its walls, row by row.

    :class:`ArenaError` when no grid of them fits at least ``least`` apart.
    """
    length, width = size[0] - 2 * keep_off, size[1] - 2 * keep_off
    best: tuple[float, int, int] | None = None
    for rows in range(1, n + 1):
        cols = math.ceil(n / rows)
        spacing = min(
            length / (cols - 1) if cols > 1 else math.inf, width / (rows - 1) if rows > 1 else math.inf
        )
        if best is None or spacing > best[0]:
            best = (spacing, rows, cols)
    assert best is not None
    spacing, rows, cols = best
    if spacing < least:
        raise ArenaError(
            f"{n} vehicles do not fit the {size[0]:g} × {size[1]:g} m floor at least {least:g} m apart"
        )
    return [
        (round((i % cols - (cols - 1) / 2) * least, 3), round((i // cols - (rows - 1) / 2) * least, 3))
        for i in range(n)
    ]


def fleet_room(n: int, size: tuple[float, float], keep_off: float, least: float) -> tuple[float, float]:
    """The floor (north, east, m) for ``n`` vehicles ``least`` apart: ``size`` when they fit it, else
    the smallest one as long as wide in the same ratio, grown by half-metre steps of its length."""
    length, width = size
    while True:
        try:
            grid(n, (length, width), keep_off, least)
            return (length, width)
        except ArenaError:
            length, width = length + 0.5, round((length + 0.5) * size[1] / size[0], 2)


def _free_udp_ports(n: int) -> list[int]:
    """``n`` distinct UDP ports free on loopback now (each bound at once, so none repeats)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _inline(values: Mapping[str, Any]) -> InlineTable:
    table = tomlkit.inline_table()
    table.update(values)
    return table


def fleet_config(base: Path, n: int, out: Path) -> tuple[Path, dict[str, tuple[float, float]]]:
    """Write to ``out`` the config of ``base`` with ``n`` simulated vehicles ``d1``…``dN`` instead of its own,
    placed on a grid :func:`fleet_spacing` apart inside its room (grown when they do not fit it: a fleet of
    50 stands 1.4 m apart in a 14 × 8 m room); their places by name.

    Every vehicle gets a free loopback UDP port for its MAVLink link and the system id of its number; the
    base's first host runs them all, the transform decimates (``[pipeline] decimate = "transform"``: no
    downsampler process per vehicle), each gateway is a client of the router (``[zenoh] vehicle_mode =
    "client"``: no peer mesh of N processes) and asks its autopilot to stream the messages it does not use
    itself at no more than users see of them (:data:`FLEET_STREAMS`; docs/performance.md, "Fifty
    vehicles").  Everything else (mocap, the rest of Zenoh, the room) is the base's.
    """
    if not 1 <= n <= MAX_FLEET:
        raise ArenaError(f"--vehicles: 1..{MAX_FLEET} (MAVLink system ids), got {n}")
    with open(base, "rb") as f:
        doc = tomllib.load(f)
    cfg = load_config(base)
    host = next(iter(cfg.hosts), None)
    if host is None:
        raise ArenaError(f"{base} names no host to run")
    size, least = cfg.arena.size, fleet_spacing(cfg.arena.min_separation)
    keep_off = cfg.arena.margin + FLEET_RADIUS + 0.1
    floor = fleet_room(n, (size[0], size[1]), keep_off, least)
    spots = grid(n, floor, keep_off, least)
    if floor != (size[0], size[1]):  # a room grown for them: a simulation has walls where it likes
        doc.setdefault("arena", {})["size"] = [floor[0], floor[1], size[2]]
    names = [f"d{i + 1}" for i in range(n)]
    doc.setdefault("pipeline", {})["decimate"] = "transform"
    doc.setdefault("zenoh", {})["vehicle_mode"] = "client"
    hosts = doc.setdefault("hosts", {})
    for h in hosts.values():
        h["vehicles"] = []
        if "vehicle_services" in h:
            h["vehicle_services"] = [s for s in h["vehicle_services"] if s != "downsampler"] or ["gateway"]
    hosts[host]["vehicles"] = names
    doc["vehicles"] = {
        name: {
            "rigid_body": name,
            "mavlink": f"udpin:127.0.0.1:{port}",
            "system_id": i + 1,
            "stream_rates": _inline(FLEET_STREAMS),
            "sim": _inline({"start": list(spot)}),
        }
        for i, (name, port, spot) in enumerate(zip(names, _free_udp_ports(n), spots, strict=True))
    }
    header = f"# {n} simulated vehicles on a grid, from {base} (written by `arena demo --vehicles {n}`)\n\n"
    out.write_text(header + tomlkit.dumps(doc))
    load_config(out)  # what we wrote is a valid config
    return out, dict(zip(names, spots, strict=True))


def _wait_router(
    cfg: ArenaConfig, up: subprocess.Popen[bytes], stop: threading.Event, deadline: float
) -> str:
    """Wait until an endpoint the demo's session connects to (``zenoh.connect``) accepts a TCP connection:
    the router the supervisor starts first is listening.  ``""`` once one does (or when none can be
    probed: UDP, a Unix socket), or on ``stop``; otherwise why not, naming what was waited for.

    The session is a Zenoh client, which gives up after 10 s without its router; the supervisor's router
    listens 3.6 s after the demo starts it on an idle 2-core machine, 13.4 s on the same machine loaded
    (load average 5: other test tiers and CPU burners; measured): so the session opens only once the router
    listens, within the arena's ``deadline``.
    """
    probes = [(e, a) for e in cfg.zenoh.connect if (a := endpoint_address(e)) is not None]
    if not probes:
        return ""
    what = " or ".join(e for e, _ in probes)
    started = time.monotonic()
    while not stop.is_set():
        if up.poll() is not None:
            return f"the supervisor exited ({up.returncode}) before the router accepted on {what}"
        for _, address in probes:
            with contextlib.suppress(OSError), socket.create_connection(address, timeout=0.5):
                return ""
        if time.monotonic() >= deadline:
            return f"the router did not accept on {what} within {time.monotonic() - started:.0f} s"
        stop.wait(0.1)
    return ""


def _wait_ready(arena: Arena, cfg: ArenaConfig, stop: threading.Event, say: Say, timeout: float) -> bool:
    names = list(cfg.vehicles)
    deadline = time.monotonic() + timeout
    listed = ", ".join(names) if len(names) <= 6 else f"{len(names)} vehicles"
    say(f"waiting for {listed}: gateways alive and vision fused")
    while not stop.is_set() and time.monotonic() < deadline:
        vs = [arena.vehicle(n) for n in names]
        if all(v.state is not None and v.link and v.state.vis_fused and v.state.setup_ok for v in vs):
            say("all vehicles ready")
            return True
        stop.wait(0.3)
    return False


def _on_ground(v: Vehicle) -> bool:
    return v.landed == LandedState.ON_GROUND and not v.armed


def _flies_on(v: Vehicle) -> bool:
    """In the air and not landing (an order of the abandoned flight program came after the land)."""
    return v.landed in (LandedState.IN_AIR, LandedState.TAKEOFF) and v.mode != FlightMode.AUTO_LAND


def land_all(
    arena: Arena,
    vehicles: Sequence[Vehicle],
    say: Say,
    hurry: threading.Event,
    timeout: float,
    refresh: Callable[[], None],
) -> None:
    """Land every vehicle in the air and wait until each is on the ground and disarmed, at most
    ``timeout`` seconds (``hurry``: the order is given, not waited for); says what it does.

    The land order is the arena's estop (every gateway lands its vehicle at once, whatever it was
    doing), sent again every :data:`RESEND_LAND` seconds while a vehicle still flies in another mode than
    AUTO.LAND (an order of the abandoned flight program may have reached its gateway after the first).
    """
    flying = [v for v in vehicles if v.armed]
    if not flying:
        say("no vehicle in the air")
        return
    names = ", ".join(v.name for v in flying)
    say(f"landing {names}: waiting up to {timeout:.0f} s for them to be on the ground")
    deadline = time.monotonic() + timeout
    last_order: float | None = None
    while True:
        left = [v for v in flying if not _on_ground(v)]
        if not left:
            say(f"landed: {names}")
            return
        now = time.monotonic()
        if last_order is None or (now - last_order >= RESEND_LAND and any(map(_flies_on, left))):
            try:  # the first order goes out whatever happens next
                arena.estop(reason="demo stopping: land")
            except ArenaError as exc:
                say(f"[red]cannot order the landing: {exc}[/]")
                return
            last_order = now
        in_air = ", ".join(v.name for v in left)
        if hurry.is_set():
            say(f"[red]stopping at once (signalled again): {in_air} still in the air, landing[/]")
            return
        if now >= deadline:
            say(f"[red]{in_air} still in the air after {timeout:.0f} s: stopping anyway[/]")
            return
        refresh()
        hurry.wait(0.2)


def _why_land(signals: StopSignals, failed: list[BaseException], up: subprocess.Popen[bytes]) -> str | None:
    """Why the demo lands what flies before it stops the arena, in words; ``None``: it has no reason to
    (the flight completed) or no way to (the supervisor, and its gateways, are gone)."""
    if signals.count:
        name = signal.Signals(signals.received[0]).name
        return f"stopping ({name}): every vehicle lands, then the arena stops"
    if failed and up.poll() is None:
        return "the demo failed: every vehicle lands, then the arena stops"
    return None


def _stop(up: subprocess.Popen[bytes], hurry: threading.Event, timeout: float = STOP_TIMEOUT) -> None:
    """Stop the supervisor and everything it started: SIGINT (as Ctrl-C), a second SIGINT on ``hurry``
    (it then kills its services at once), SIGKILL after ``timeout`` s (its services go with it: each one
    dies with its parent)."""
    if up.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(up.pid, signal.SIGINT)
    deadline = time.monotonic() + timeout
    hurried = False
    while up.poll() is None and time.monotonic() < deadline:
        if hurry.is_set() and not hurried:
            hurried = True
            with contextlib.suppress(ProcessLookupError):
                os.killpg(up.pid, signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            up.wait(0.1)
    if up.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(up.pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            up.wait(5)


def demo(
    config_file: Annotated[
        Path | None, typer.Argument(help="Arena config (default deploy/sim.toml).")
    ] = None,
    once: Annotated[
        bool, typer.Option("--once", help="Exit after the demo flight instead of watching.")
    ] = False,
    log: Annotated[Path, typer.Option(help="Where the arena's own logs go.")] = Path("arena-demo.log"),
    ready_timeout: Annotated[
        float | None,
        typer.Option(help="Seconds to wait for the arena to come up (default 90, and 2 s more per vehicle)."),
    ] = None,
    land_timeout: Annotated[
        float,
        typer.Option(help="When stopped (Ctrl-C) or failed: seconds to wait for the vehicles to land."),
    ] = LAND_TIMEOUT,
    vehicles: Annotated[
        int | None,
        typer.Option(
            "--vehicles",
            "-n",
            help="Fly N simulated vehicles on a grid instead of CONFIG's own (their config is written "
            "next to --log, as arena-demo-N.toml: CONFIG's room, mocap and Zenoh, free ports).",
        ),
    ] = None,
) -> None:
    """Run the simulated arena from CONFIG and fly a formation demo with every vehicle, live status shown.

    With --vehicles N, N simulated vehicles d1…dN on a grid inside CONFIG's room fly it instead.
    Ctrl-C (or a closed terminal, or SIGTERM) lands the vehicles, waits for them to be on the ground
    (at most --land-timeout s) and stops the arena; a second Ctrl-C stops everything at once.  A demo
    that fails (a command refused, a goal not reached) lands them the same way, then exits with 1.
    """
    path = global_config_file(config_file)
    spots: dict[str, tuple[float, float]] | None = None
    if vehicles is not None:
        try:
            path, spots = fleet_config(path, vehicles, log.with_name(f"arena-demo-{vehicles}.toml"))
        except (ArenaError, OSError) as exc:
            console.print(f"[red]error:[/] {exc}")
            raise typer.Exit(2) from None
        console.print(
            f"{vehicles} vehicles on a grid: config {path} (watch them: arena view -c {path}; "
            f"fly your own program: arena up {path})",
            soft_wrap=True,
        )
    cfg = load_config(path)
    if ready_timeout is None:
        ready_timeout = 90.0 + 2.0 * len(cfg.vehicles)
    host = next(iter(cfg.hosts), None)
    if host is None:
        console.print(f"[red]error:[/] {path} names no host to run")
        raise typer.Exit(2)
    stop = threading.Event()  # a signal: stop the flight, land, stop the arena
    hurry = threading.Event()  # a second one: at once
    with StopSignals(stop, again=lambda _signum: hurry.set()) as signals:
        _run(cfg, path, host, log, once, ready_timeout, land_timeout, stop, hurry, signals, spots)


def _run(
    cfg: ArenaConfig,
    path: Path,
    host: str,
    log: Path,
    once: bool,
    ready_timeout: float,
    land_timeout: float,
    stop: threading.Event,
    hurry: threading.Event,
    signals: StopSignals,
    spots: dict[str, tuple[float, float]] | None = None,
) -> None:
    logf = open(log, "ab")  # noqa: SIM115 - kept open for the child's lifetime
    # The supervisor runs in its own session (the terminal's signals reach the demo alone, which stops
    # it in order) and is sent SIGTERM by the kernel should the demo die without stopping it.
    up = subprocess.Popen(
        [sys.executable, "-m", "arena_common.cli", "up", str(path), "--host", host],
        stdout=logf,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=child_setup(os.getpid(), signal.SIGTERM),
    )
    say = Say(console)
    say(f"arena starting (pid {up.pid}, logs in {log})")
    failed: list[BaseException] = []
    deadline = time.monotonic() + ready_timeout  # the whole come-up: the router, then every vehicle ready
    problem = _wait_router(cfg, up, stop, deadline)
    if stop.is_set():  # stopped before anything could fly: stop the arena
        say("stopping the arena" + (" at once" if hurry.is_set() else ""))
        _stop(up, hurry)
        logf.close()
        with contextlib.suppress(OSError, ValueError):  # the terminal may be gone (SIGHUP)
            console.print(f"arena stopped (supervisor {up.returncode})")
        return
    try:
        if problem:
            raise ArenaError(problem)
        arena = Arena(cfg, name="arena-demo")
    except ArenaError as exc:
        _stop(up, hurry)
        logf.close()
        console.print(f"[red]error:[/] {exc} (see {log})")
        raise typer.Exit(1) from None
    snap = Snapshot(arena.bus)
    vehicles = [arena.vehicle(n) for n in cfg.vehicles]

    def program() -> None:
        try:
            if not _wait_ready(arena, cfg, stop, say, max(deadline - time.monotonic(), 0.0)):
                if stop.is_set():
                    return
                raise ArenaError(f"the arena did not come up within {ready_timeout:.0f} s (see {log})")
            if spots is None:
                formation_flight(vehicles, say, stop)
            else:
                formation_flight(vehicles, say, stop, radius=FLEET_RADIUS, spots=spots)
        except Stopped:
            pass
        except BaseException as exc:
            failed.append(exc)
            say(f"[red]demo failed: {exc}[/]")

    flight = threading.Thread(target=program, name="demo-flight", daemon=True)
    flight.start()

    def view() -> Group:
        snap.refresh()
        # What the demo is doing first, then the vehicles: a terminal too short for everything crops the
        # services and clocks tables at its bottom, never the progress.
        progress = Text.from_markup("\n".join(say.last()))
        return Group(progress, Text(WATCH_3D, style="dim"), snap.render(vehicles_first=True))

    live = Live(view(), console=console, auto_refresh=False)

    def refresh() -> None:
        with contextlib.suppress(OSError, ValueError):  # the terminal may be gone (SIGHUP)
            live.update(view(), refresh=True)

    try:
        with contextlib.suppress(OSError, ValueError):
            live.start(refresh=True)
        while (flight.is_alive() or not once) and not stop.is_set() and not failed:
            if up.poll() is not None:
                say(f"[red]the supervisor exited ({up.returncode}); see {log}[/]")
                failed.append(ArenaError("supervisor exited"))
                break
            stop.wait(0.5)
            refresh()
        why = _why_land(signals, failed, up)
        if why:
            say.echo = True
            say(why)
            refresh()
            land_all(arena, vehicles, say, hurry, land_timeout, refresh)
    finally:
        stop.set()
        say("stopping the arena" + (" at once" if hurry.is_set() else ""))
        refresh()
        with contextlib.suppress(OSError, ValueError):
            live.stop()
            if not console.is_terminal:
                console.line()  # after the last render
        arena.close()
        _stop(up, hurry)
        logf.close()
        with contextlib.suppress(OSError, ValueError):
            console.print(f"arena stopped (supervisor {up.returncode})")
    if failed:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``demo`` to ``app``."""
    app.command("demo")(demo)
