"""``arena demo``: bring up the simulated arena, fly every vehicle in formation, show live status.

What ``make run`` runs.  The arena is started by the supervisor (``arena up``) as a child process whose
logs go to a file, so the terminal shows the live status table; Ctrl-C lands the vehicles and stops
everything.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console, Group
from rich.live import Live
from rich.text import Text

from arena_common.cli._flight import Snapshot
from arena_common.cli._globals import config_file as global_config_file
from arena_common.client import Arena, Swarm, Vehicle
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ArenaError
from arena_common.runtime.options import load_config
from arena_common.runtime.process import child_setup

console = Console()
WATCH_3D = (
    "watch in 3D: `arena view` in another terminal, then Foxglove → Open connection → "
    "ws://127.0.0.1:8765 with the layout deploy/foxglove/arena.json (docs/viewer.md)"
)


def formation_flight(
    swarm: Swarm, say: list[str], height: float = 1.0, radius: float = 1.0, steps: int = 6
) -> None:
    """Arm, take off, fly a rotating triangle (or circle) formation around the arena centre, land."""
    names = [v.name for v in swarm]
    say.append("arming " + ", ".join(names))
    swarm.arm()
    say.append(f"taking off to {height} m")
    swarm.takeoff(height)
    for step in range(steps + 1):
        angle = step * 2 * math.pi / steps
        targets = {
            n: (
                radius * math.cos(angle + 2 * math.pi * i / len(names)),
                radius * math.sin(angle + 2 * math.pi * i / len(names)),
            )
            for i, n in enumerate(names)
        }
        say.append(f"formation step {step}/{steps}")

        def fly(v: Vehicle, t: dict[str, tuple[float, float]] = targets) -> None:
            v.goto(t[v.name][0], t[v.name][1], -height, yaw=0.0, tolerance=0.2)

        swarm.run(fly)
    say.append("landing")
    swarm.land()
    say.append("landed: demo complete")


def _wait_ready(
    arena: Arena, cfg: ArenaConfig, stop: threading.Event, say: list[str], timeout: float
) -> bool:
    names = list(cfg.vehicles)
    deadline = time.monotonic() + timeout
    say.append(f"waiting for {', '.join(names)}: gateways alive and vision fused")
    while not stop.is_set() and time.monotonic() < deadline:
        vs = [arena.vehicle(n) for n in names]
        if all(v.state is not None and v.link and v.state.vis_fused and v.state.setup_ok for v in vs):
            say.append("all vehicles ready")
            return True
        time.sleep(0.3)
    return False


def _stop(up: subprocess.Popen[bytes]) -> None:
    """Stop the supervisor and everything it started (Ctrl-C first, then SIGKILL)."""
    if up.poll() is None:
        os.killpg(up.pid, signal.SIGINT)
        try:
            up.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait(5)


def demo(
    config_file: Annotated[
        Path | None, typer.Argument(help="Arena config (default deploy/sim.toml).")
    ] = None,
    once: Annotated[
        bool, typer.Option("--once", help="Exit after the demo flight instead of watching.")
    ] = False,
    log: Annotated[Path, typer.Option(help="Where the arena's own logs go.")] = Path("arena-demo.log"),
    ready_timeout: Annotated[float, typer.Option(help="Seconds to wait for the arena to come up.")] = 90.0,
) -> None:
    """Run the simulated arena from CONFIG and fly a formation demo with every vehicle, live status shown."""
    path = global_config_file(config_file)
    cfg = load_config(path)
    host = next(iter(cfg.hosts), None)
    if host is None:
        console.print(f"[red]error:[/] {path} names no host to run")
        raise typer.Exit(2)
    logf = open(log, "ab")  # noqa: SIM115 - kept open for the child's lifetime
    # A closed terminal (SIGHUP) or a kill (SIGTERM) ends the demo as Ctrl-C does: land, stop the arena.
    # The supervisor runs in its own session (the terminal's signals reach the demo alone) and is told
    # to stop (SIGTERM) should the demo die without stopping it.
    for sig in (signal.SIGHUP, signal.SIGTERM):
        signal.signal(sig, signal.default_int_handler)
    up = subprocess.Popen(
        [sys.executable, "-m", "arena_common.cli", "up", str(path), "--host", host],
        stdout=logf,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=child_setup(os.getpid(), signal.SIGTERM),
    )
    say: list[str] = [f"arena starting (pid {up.pid}, logs in {log})"]
    stop = threading.Event()
    failed: list[BaseException] = []
    try:
        arena = Arena(cfg, name="arena-demo")
    except ArenaError as exc:
        _stop(up)
        logf.close()
        console.print(f"[red]error:[/] {exc} (see {log})")
        raise typer.Exit(1) from None
    snap = Snapshot(arena.bus)

    def program() -> None:
        try:
            if not _wait_ready(arena, cfg, stop, say, ready_timeout):
                raise ArenaError(f"the arena did not come up within {ready_timeout:.0f} s (see {log})")
            formation_flight(arena.swarm(list(cfg.vehicles)), say)
        except BaseException as exc:
            failed.append(exc)
            say.append(f"[red]demo failed: {exc}[/]")

    flight = threading.Thread(target=program, name="demo-flight", daemon=True)
    flight.start()

    def view() -> Group:
        snap.refresh()
        return Group(snap.render(), Text.from_markup("\n".join(say[-6:])), Text(WATCH_3D, style="dim"))

    try:
        with Live(view(), console=console, refresh_per_second=2) as live:
            while flight.is_alive() or not once:
                if up.poll() is not None:
                    say.append(f"[red]the supervisor exited ({up.returncode}); see {log}[/]")
                    failed.append(ArenaError("supervisor exited"))
                    break
                time.sleep(0.5)
                live.update(view())
            live.update(view())
    except KeyboardInterrupt:
        with contextlib.suppress(OSError):  # the terminal may be gone
            console.print("stopping: landing every vehicle")
        stop.set()
        try:
            arena.estop(reason="demo interrupted")
            time.sleep(0.3)
        except ArenaError:
            pass
    finally:
        stop.set()
        arena.close()
        _stop(up)
        logf.close()
    if failed:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``demo`` to ``app``."""
    app.command("demo")(demo)
