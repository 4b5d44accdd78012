"""Run a host's share of the arena: one OS process per service, restarted when it dies, stopped together.

:func:`plan` turns the config into the process table of one host (``hosts.<h>.services`` and, for each
of ``hosts.<h>.vehicles``, its ``vehicle_services``, preceded for an ``autopilot = "px4-sitl"`` vehicle by
its PX4 SITL autopilot and truth bridge); :class:`Supervisor` runs such a table::

    specs = plan(cfg, "ground")
    sup = Supervisor(specs)
    sup.run(stop)          # until ``stop`` is set; then SIGTERM to each, SIGKILL after a grace period

The router starts first and the others only once its port accepts connections.  Every child's output is
prefixed with its name (``[gateway.d1] …``, coloured on a terminal).  A child that exits is restarted
after an exponential back-off (0.5 s doubling to 10 s, back to 0.5 s once a child has run for a stable
minute).  Children never outlive the supervisor: each one asks the kernel for SIGKILL when its parent
dies (``PR_SET_PDEATHSIG``, Linux), so even a ``kill -9`` of the supervisor stops them (an orderly stop
sends SIGTERM first); each child also runs in its own process group, which is what the supervisor
signals, so a child's own children go too, and a Ctrl-C on the terminal reaches the supervisor alone,
which then stops the children in order (a second Ctrl-C or SIGTERM kills them at once).  Each
child is a :class:`~arena_common.runtime.process.ChildProcess`, the one way the arena starts, watches and
stops a process.

``PR_SET_PDEATHSIG`` fires when the *thread* that forked the child ends, so spawn from a thread that
lives as long as the children (``arena up`` spawns from its main thread).
"""

from __future__ import annotations

import os
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig, HostSpec
from arena_common.core.endpoints import split_endpoint
from arena_common.core.errors import ArenaError
from arena_common.core.services import SERVICES, ServiceInfo, started_by
from arena_common.runtime.process import ChildProcess, StopSignals, describe_exit

ROUTER_MODULE = "arena_common.cli"
SUPERVISOR_SERVICE = "supervisor"
_COLOURS = ("36", "32", "33", "35", "34", "91", "92", "93", "95", "96")


class TextSink(Protocol):
    """Where the prefixed lines go: ``sys.stdout`` or anything with ``write`` and ``flush``."""

    def write(self, text: str, /) -> int: ...

    def flush(self) -> None: ...


class SupervisorError(ArenaError):
    """A process table that cannot be run (no such host, nothing to start, a child that cannot start)."""


@dataclass(frozen=True, slots=True)
class ProcessSpec:
    """One supervised process: its name (the log prefix), command line, and what "ready" means."""

    name: str
    argv: tuple[str, ...]
    ready_port: tuple[str, int] | None = None  # wait until this TCP address accepts before the next ones
    env: Mapping[str, str] = field(default_factory=dict)

    def command_line(self) -> str:
        """The command line, quoted as a shell would need it."""
        return shlex.join(self.argv)


@dataclass(frozen=True, slots=True)
class Backoff:
    """Restart delays: ``initial`` doubling up to ``maximum``; reset once a child ran ``stable_s``."""

    initial: float = 0.5
    maximum: float = 10.0
    stable_s: float = 60.0

    def delay(self, failures: int) -> float:
        """Delay before restart number ``failures`` (1-based) of an unstable child."""
        return min(self.maximum, self.initial * 2.0 ** max(0, failures - 1))


@dataclass(frozen=True, slots=True)
class ChildStatus:
    """A snapshot of one supervised process."""

    name: str
    pid: int | None
    alive: bool
    restarts: int
    uptime: float
    last_exit: int | None


# -- the process table ----------------------------------------------------------------------------------


def _bus_args(options: BusOptions | None, router: bool = False) -> list[str]:
    if options is None:
        return []
    args: list[str] = []
    if not router:
        if options.mode:
            args += ["--mode", options.mode]
        for e in options.connect:
            args += ["--connect", e]
    for e in options.listen:
        args += ["--listen", e]
    if options.zconfig:
        args += ["--zconfig", options.zconfig]
    return args


def endpoint_address(endpoint: str) -> tuple[str, int] | None:
    """The TCP address to probe for a Zenoh endpoint (``tcp/0.0.0.0:7447`` → ``('127.0.0.1', 7447)``).

    ``None`` for endpoints that cannot be probed with a TCP connect (UDP, Unix sockets, port 0).
    """
    proto, host, port = split_endpoint(endpoint)
    if "/" not in endpoint or proto not in ("tcp", "tls", "ws") or not port:
        return None
    return {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(host, host), port


def host_options(cfg: ArenaConfig, host: HostSpec, options: BusOptions | None = None) -> BusOptions | None:
    """The bus options of ``host``'s services: peers listen on the host's address when it has one.

    Zenoh 1.x routers do not relay between two peers that cannot reach each other, and a peer listening
    on loopback (the default) cannot be reached from another computer: so a host with an ``address``
    has its peers listen on ``tcp/<address>:0``, and peers of different computers connect directly
    (learning each other's endpoints by gossip through the router).  An explicit ``--listen`` or
    ``zenoh.listen`` wins; clients and routers are left alone, and so is every session of a secured
    arena (a client of the router: :func:`arena_common.bus.security.secured_options`).
    """
    mode = (options.mode if options else None) or cfg.zenoh.mode
    if cfg.security.enabled:  # every session of a secured arena is a client of its router
        return options
    if not host.address or mode != "peer" or cfg.zenoh.listen or (options and options.listen):
        return options
    address = f"[{host.address}]" if ":" in host.address else host.address
    return replace(options or BusOptions(), listen=(f"tcp/{address}:0",))


def plan(
    cfg: ArenaConfig,
    host: str | None = None,
    *,
    options: BusOptions | None = None,
    python: str = sys.executable,
    log_level: str | None = None,
) -> list[ProcessSpec]:
    """The processes the config assigns to ``host`` (default: this machine's hostname), router first.

    Raises :class:`~arena_common.core.errors.ConfigError` naming the known hosts when ``host`` is not in the
    config.  ``options`` (the command line's ``--mode/--connect/--listen/--zconfig``) are passed on to
    every child.
    """
    h: HostSpec = cfg.host(host)
    config_path = str(Path(cfg.path).resolve())
    common = ["-c", config_path, "--host", h.name]
    level = ["--log-level", log_level] if log_level else []
    specs: list[ProcessSpec] = []
    if "router" in h.services:
        ready = next((a for a in map(endpoint_address, cfg.zenoh.router_listen) if a is not None), None)
        argv = (python, "-m", ROUTER_MODULE, "router", *common, *_bus_args(options, router=True))
        specs.append(ProcessSpec("router", argv, ready_port=ready))
    options = host_options(cfg, h, options)
    for word in h.services:
        for s in _host_processes(cfg, word):
            specs.append(ProcessSpec(s.name, (python, "-m", s.module, *common, *level, *_bus_args(options))))
    for vehicle in h.vehicles:
        # An ``autopilot = "px4-sitl"`` vehicle's autopilot and its ground-truth bridge start on the host
        # that runs its gateway (PX4 SITL talks on loopback only), before the vehicle's own services.
        px4 = [s for s in SERVICES if s.scope == "px4-sitl"] if cfg.vehicle(vehicle).px4_sitl else []
        own = [s for word in h.vehicle_services for s in started_by(word)]
        for s in (px4 if "gateway" in h.vehicle_services else []) + own:
            argv = (python, "-m", s.module, *common, "--vehicle", vehicle, *level)
            specs.append(ProcessSpec(f"{s.name}.{vehicle}", (*argv, *_bus_args(options))))
    return specs


def sim_world_plan(
    cfg: ArenaConfig,
    host: str | None = None,
    *,
    options: BusOptions | None = None,
    python: str = sys.executable,
    log_level: str | None = None,
) -> list[ProcessSpec]:
    """The simulated world alone (simulated vehicles and the Motive emulator), whatever the host runs.

    PX4 SITL vehicles are not part of it: their autopilots start with their gateways (:func:`plan`).
    """
    common = ["-c", str(Path(cfg.path).resolve())]
    if host:
        common += ["--host", host]
    level = ["--log-level", log_level] if log_level else []
    return [
        ProcessSpec(s.name, (python, "-m", s.module, *common, *level, *_bus_args(options)))
        for s in _host_processes(cfg, "sim")
    ]


def _host_processes(cfg: ArenaConfig, word: str) -> tuple[ServiceInfo, ...]:
    """The processes a host's service word starts; "sim" without simulated vehicles is the Motive emulator
    alone (the router is not a service module: :func:`plan` starts it first)."""
    processes = started_by(word)
    if word == "sim" and not any(v.simulated for v in cfg.vehicles.values()):
        processes = tuple(s for s in processes if s.name != "sim-vehicle")
    return processes


# -- supervising ---------------------------------------------------------------------------------------


class _Output:
    """One writer for every child's lines, prefixed (and coloured on a terminal)."""

    def __init__(self, out: TextSink, color: bool) -> None:
        self.out = out
        self.color = color
        self.width = 0
        self._lock = threading.Lock()
        self._colours: dict[str, str] = {}

    def prefix(self, name: str) -> str:
        tag = f"[{name}]"
        if not self.color:
            return tag + " "
        colour = self._colours.setdefault(name, _COLOURS[len(self._colours) % len(_COLOURS)])
        return f"\x1b[{colour}m{tag}\x1b[0m "

    def line(self, name: str, text: str) -> None:
        text = text.rstrip("\r\n")
        with self._lock:
            try:
                self.out.write(self.prefix(name) + text + "\n")
                self.out.flush()
            except (OSError, ValueError):  # the terminal went away: keep supervising
                pass


class _Child:
    def __init__(self, spec: ProcessSpec) -> None:
        self.spec = spec
        self.proc: ChildProcess | None = None
        self.started = 0.0
        self.restarts = 0
        self.failures = 0
        self.next_start: float | None = None
        self.last_exit: int | None = None

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.alive


class Supervisor:
    """Starts a process table, restarts what dies, stops everything on :meth:`shutdown`.

    ``out`` receives every child's output, prefixed, and the supervisor's own lines (prefix
    ``[arena]``); ``color`` defaults to "``out`` is a terminal and ``NO_COLOR`` is unset".  ``grace``
    is how long stopping children get after SIGTERM before SIGKILL; ``ready_timeout`` bounds the wait
    for the router's port.  ``on_event(kind, name, detail)`` is called on ``started``/``exited``/
    ``restarting`` (from the supervising thread).
    """

    def __init__(
        self,
        specs: Sequence[ProcessSpec],
        *,
        out: TextSink | None = None,
        color: bool | None = None,
        backoff: Backoff | None = None,
        grace: float = 5.0,
        ready_timeout: float = 15.0,
        death_signal: int = signal.SIGKILL,
        env: Mapping[str, str] | None = None,
        on_event: Callable[[str, str, str], None] | None = None,
    ) -> None:
        if not specs:
            raise SupervisorError("nothing to start: the process table is empty")
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise SupervisorError(f"duplicate process names in {names}")
        out = out or sys.stdout
        if color is None:
            color = bool(getattr(out, "isatty", lambda: False)()) and "NO_COLOR" not in os.environ
        self.output = _Output(out, color)
        self.backoff = backoff or Backoff()
        self.grace = grace
        self.ready_timeout = ready_timeout
        self.death_signal = int(death_signal)
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.on_event = on_event
        self.children = [_Child(s) for s in specs]
        self.stopping = False
        self.killing = False  # set by kill_all: nothing starts again
        self._started = False

    # -- reporting ------------------------------------------------------------------------------------
    def say(self, text: str) -> None:
        """Print one supervisor line."""
        self.output.line("arena", text)

    def _event(self, kind: str, name: str, detail: str = "") -> None:
        if self.on_event is not None:
            try:
                self.on_event(kind, name, detail)
            except Exception as exc:  # an observer's bug must not stop supervision
                self.say(f"event callback failed: {exc}")

    def status(self) -> list[ChildStatus]:
        """One :class:`ChildStatus` per process, in start order."""
        now = time.monotonic()
        return [
            ChildStatus(
                c.spec.name,
                c.proc.pid if c.proc is not None else None,
                c.alive,
                c.restarts,
                now - c.started if c.alive else 0.0,
                c.last_exit,
            )
            for c in self.children
        ]

    @property
    def alive_count(self) -> int:
        """How many children run right now."""
        return sum(1 for c in self.children if c.alive)

    @property
    def restart_count(self) -> int:
        """Restarts of all children since start."""
        return sum(c.restarts for c in self.children)

    def pids(self) -> dict[str, int]:
        """Name → pid of every running child."""
        return {c.spec.name: c.proc.pid for c in self.children if c.alive and c.proc is not None}

    # -- starting -------------------------------------------------------------------------------------
    def _spawn(self, child: _Child) -> bool:
        spec = child.spec
        if self.killing:
            return False
        try:
            proc = ChildProcess(
                spec.argv,
                name=spec.name,
                env={**self.env, **spec.env},
                on_line=lambda text: self.output.line(spec.name, text),
                death_signal=self.death_signal,
            )
        except OSError as exc:
            self.say(f"{spec.name}: cannot start {spec.argv[0]}: {exc.strerror or exc}")
            child.last_exit = 127
            self._schedule_restart(child, time.monotonic())
            return False
        child.proc = proc
        child.started = time.monotonic()
        child.next_start = None
        self._event("started", spec.name, str(proc.pid))
        return True

    def _wait_ready(self, child: _Child, stop: threading.Event | None) -> None:
        address = child.spec.ready_port
        if address is None:
            return
        deadline = time.monotonic() + self.ready_timeout
        while time.monotonic() < deadline:
            if stop is not None and stop.is_set():
                return
            if not child.alive:
                return  # it died: supervision restarts it; the others start anyway
            try:
                with socket.create_connection(address, timeout=0.5):
                    return
            except OSError:
                time.sleep(0.05)
        self.say(
            f"{child.spec.name} is not accepting on {address[0]}:{address[1]} after "
            f"{self.ready_timeout:.0f} s; starting the others anyway"
        )

    def start(self, stop: threading.Event | None = None) -> None:
        """Start every child in order, waiting for each ``ready_port`` before the next ones."""
        if self._started:
            return
        self._started = True
        for child in self.children:
            if stop is not None and stop.is_set():
                return
            if self._spawn(child):
                assert child.proc is not None
                self.say(f"started {child.spec.name} (pid {child.proc.pid})")
                self._wait_ready(child, stop)

    # -- supervising ------------------------------------------------------------------------------------
    def _schedule_restart(self, child: _Child, now: float) -> None:
        ran = now - child.started if child.started else 0.0
        child.failures = 1 if ran >= self.backoff.stable_s else child.failures + 1
        delay = self.backoff.delay(child.failures)
        child.next_start = now + delay
        self._event("restarting", child.spec.name, f"{delay:.1f}")

    def poll(self) -> None:
        """One supervision step: notice exits, schedule restarts, start what is due."""
        if self.stopping or self.killing:
            return
        now = time.monotonic()
        for child in self.children:
            proc = child.proc
            if proc is not None and child.next_start is None:
                code = proc.poll()
                if code is None:
                    continue
                child.last_exit = code
                ran = now - child.started
                self._schedule_restart(child, now)
                assert child.next_start is not None
                self.say(
                    f"{child.spec.name} (pid {proc.pid}) {describe_exit(code)} after {ran:.1f} s; "
                    f"restarting in {child.next_start - now:.1f} s"
                )
                self._event("exited", child.spec.name, describe_exit(code))
            elif child.next_start is not None and now >= child.next_start:
                child.restarts += 1
                if self._spawn(child):
                    assert child.proc is not None
                    self.say(f"restarted {child.spec.name} (pid {child.proc.pid}, restart {child.restarts})")

    def run(self, stop: threading.Event, interval: float = 0.1) -> None:
        """Start (if not yet), supervise until ``stop`` is set, then :meth:`shutdown`."""
        try:
            self.start(stop)
            while not stop.wait(interval):
                self.poll()
        finally:
            self.shutdown()

    # -- stopping -------------------------------------------------------------------------------------
    def _signal(self, child: _Child, sig: int) -> None:
        if child.proc is not None:
            child.proc.send_signal(sig)

    def _stop_group(self, group: Iterable[_Child]) -> None:
        group = [c for c in group if c.alive]
        for child in group:
            self._signal(child, signal.SIGKILL if self.killing else signal.SIGTERM)
        deadline = time.monotonic() + self.grace
        for child in group:
            assert child.proc is not None
            try:
                child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.say(f"{child.spec.name} did not stop within {self.grace:.1f} s: SIGKILL")
                self._signal(child, signal.SIGKILL)
                try:
                    child.proc.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    self.say(f"{child.spec.name} (pid {child.proc.pid}) survived SIGKILL")

    def kill_all(self, why: str = "") -> None:
        """SIGKILL every child's process group now and start none again (a second Ctrl-C: hurry).
        Thread-safe; :meth:`shutdown` still reaps them."""
        self.killing = True
        alive = [c for c in self.children if c.alive]
        if alive:
            self.say(f"{why + ': ' if why else ''}SIGKILL to " + ", ".join(c.spec.name for c in alive))
        for child in alive:
            self._signal(child, signal.SIGKILL)

    def shutdown(self) -> None:
        """Stop every child: SIGTERM, then SIGKILL after ``grace``; the router last.  Idempotent."""
        if self.stopping:
            return
        self.stopping = True
        routers = [c for c in self.children if c.spec.ready_port is not None]
        others = [c for c in self.children if c.spec.ready_port is None]
        if any(c.alive for c in self.children):
            self.say("stopping " + ", ".join(c.spec.name for c in self.children if c.alive))
        self._stop_group(reversed(others))
        self._stop_group(routers)
        for child in self.children:
            if child.proc is not None:
                child.proc.join_output(timeout=2.0)
        self.say("all stopped")


def supervise(
    specs: Sequence[ProcessSpec],
    stop: threading.Event | None = None,
    *,
    tick: Callable[[Supervisor], None] | None = None,
    **kwargs: Any,
) -> Supervisor:
    """Run ``specs`` in the foreground until SIGINT/SIGTERM/SIGHUP (or ``stop``); returns when all stopped.

    Signal handlers are installed only when called from the main thread
    (:class:`~arena_common.runtime.process.StopSignals`); a second SIGINT or SIGTERM kills every child at once
    (:meth:`Supervisor.kill_all`) instead of waiting for their grace period.  ``tick`` is called about
    every 0.1 s with the supervisor (stats, status displays).
    """
    stop = stop or threading.Event()
    sup = Supervisor(specs, **kwargs)
    with StopSignals(stop, again=lambda signum: sup.kill_all(signal.Signals(signum).name)):
        try:
            sup.start(stop)
            while not stop.wait(0.1):
                sup.poll()
                if tick is not None:
                    tick(sup)
        finally:
            sup.shutdown()
    return sup
