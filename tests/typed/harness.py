"""The typed tier's harness: ``arena`` started as a user types it, on a config of free ports.

:class:`Typed` writes a config whose ports are free and whose vehicles are not the default config's
(x7 simulated, x8 a PX4 SITL vehicle); :class:`Command` runs the real console script in a session of
its own, as a terminal runs a job; :func:`leftovers` finds what a command left running.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from arena_common.bus.session import Bus
from arena_common.runtime.process import child_setup
from tests.helpers import as_a_terminal_job, free_port, wait_for

ARENA = Path(sys.executable).parent / "arena"  # the console script, as `make setup` installs it

STOP_S = 15.0  # how long a service may take to stop after Ctrl-C
START_S = 45.0  # how long one may take to start on a busy 2-core machine


# -- the config --------------------------------------------------------------------------------------------


class Typed:
    """A config of free ports whose vehicle is x7 (and, with ``px4``, x8: PX4 SITL instance ``instance``,
    on no host); ``router``: the host runs the router (``arena up``, ``arena demo``); ``services``: more
    services of the host (``recorder``…)."""

    def __init__(
        self,
        directory: Path,
        endpoint: str,
        *,
        connect: str | None = None,
        router: bool = False,
        px4: bool = True,
        services: Sequence[str] = (),
    ) -> None:
        self.dir = directory
        self.endpoint = endpoint
        self.command_port = free_port(socket.SOCK_DGRAM)
        self.data_port = free_port(socket.SOCK_DGRAM)
        self.x7_port = free_port(socket.SOCK_DGRAM)
        self.instance = next((i for i in range(9, -1, -1) if _udp_free(19410 + i)), 9)
        self.truth_port = 19410 + self.instance
        self.rec_dir = directory / "rec"
        services = [*(["router"] if router else []), "sim", "mocap", "transform", *services]
        lines = [
            "[arena]",
            'name = "typed"',
            "[mocap]",
            f"command_port = {self.command_port}",
            f"data_port = {self.data_port}",
            'server = "127.0.0.1"',
            'interface = "127.0.0.1"',
            "multicast = false",
            "[zenoh]",
            'mode = "peer"',
            f'connect = ["{connect or endpoint}"]',
            f'router_listen = ["{endpoint}"]',
            "[hosts.typed]",
            "services = [" + ", ".join(f'"{s}"' for s in services) + "]",
            'vehicles = ["x7"]',
            "[vehicles.x7]",
            'rigid_body = "x7"',
            f'mavlink = "udpin:127.0.0.1:{self.x7_port}"',
            "system_id = 7",
            "sim = { start = [0.0, 0.0] }",
            "[recorder]",
            f'directory = "{self.rec_dir}"',
        ]
        if px4:
            lines += [
                "[vehicles.x8]",
                'autopilot = "px4-sitl"',
                f"px4_instance = {self.instance}",
                'rigid_body = "x8"',
                "sim = { start = [1.0, 1.0] }",
            ]
        self.path = directory / "typed.toml"
        self.path.write_text("\n".join(lines) + "\n")

    def fill(self, text: str) -> str:
        """``text`` with ``{CFG}``, ``{cmd}``, ``{x7}``, ``{truth}``, ``{rec}`` replaced."""
        for k, v in {
            "{CFG}": str(self.path),
            "{cmd}": str(self.command_port),
            "{x7}": str(self.x7_port),
            "{truth}": str(self.truth_port),
            "{rec}": str(self.rec_dir),
        }.items():
            text = text.replace(k, v)
        return text


# -- processes and ports -------------------------------------------------------------------------------------


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def bound(kind: str, port: int) -> bool:
    """True when a socket of this network namespace is bound to ``port`` (``kind``: "udp", or "tcp":
    listening)."""
    for table in (f"/proc/net/{kind}", f"/proc/net/{kind}6"):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            local, state = fields[1], fields[3]
            if int(local.rsplit(":", 1)[1], 16) == port and (kind == "udp" or state == "0A"):
                return True
    return False


def _stat(pid: str) -> tuple[str, int] | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields[0], int(fields[3])  # state, session id


def leftovers(markers: Sequence[str], session: int | None = None) -> list[str]:
    """The processes still running whose command line holds one of ``markers`` or that are in
    ``session``: ``"pid: command line"``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        stat = _stat(entry.name)
        if stat is None or stat[0] in ("Z", "X"):
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        if any(m in cmd for m in markers) or (session is not None and stat[1] == session):
            found.append(f"{entry.name}: {cmd}")
    return found


def kill_leftovers(markers: Sequence[str], session: int | None = None) -> None:
    """SIGKILL whatever :func:`leftovers` finds (a failed test's clean-up)."""
    for line in leftovers(markers, session):
        try:
            os.kill(int(line.split(":", 1)[0]), signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def _as_a_terminal_job(parent: int) -> Callable[[], None]:
    """``preexec_fn``: the signal dispositions a shell gives a foreground job; killed with the test."""
    die_with_test = child_setup(parent, signal.SIGKILL)

    def setup() -> None:
        as_a_terminal_job()
        die_with_test()

    return setup


class Command:
    """``arena ARGS`` started as a user types it: its own session and process group (a terminal's job),
    stdout and stderr kept line by line."""

    def __init__(self, args: Sequence[str], cwd: Path, env: dict[str, str] | None = None) -> None:
        self.args = [str(ARENA), *args]
        environ = {k: v for k, v in os.environ.items() if k not in ("ARENA_CONFIG", "ARENA_HOST")}
        self.popen = subprocess.Popen(
            self.args,
            cwd=cwd,
            env={**environ, "PYTHONUNBUFFERED": "1", "NO_COLOR": "1", **(env or {})},
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=_as_a_terminal_job(os.getpid()),
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for raw in iter(self.popen.stdout.readline, b""):
            self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    @property
    def pid(self) -> int:
        """Its pid, also its session and process group id."""
        return self.popen.pid

    def output(self) -> str:
        """Everything it printed so far."""
        return "\n".join(self.lines)

    def running(self) -> None:
        """Raise (with its output) if it has exited: a ``check`` for :func:`wait_for`."""
        if self.popen.poll() is not None:
            self._reader.join(2.0)
            raise AssertionError(
                f"`{' '.join(self.args[1:])}` exited {self.popen.returncode}:\n{self.output()}"
            )

    def wait_line(self, pattern: str, timeout: float = START_S) -> str:
        """The first line matching ``pattern`` (a regular expression), once printed."""

        def found() -> str | None:
            line = next((line for line in list(self.lines) if re.search(pattern, line)), None)
            if line is None:
                self.running()
            return line

        line: str = wait_for(found, timeout=timeout, interval=0.05, what=f"a line matching {pattern!r}")
        return line

    def signal(self, sig: int) -> None:
        """Send ``sig`` to its process group, as a terminal does (Ctrl-C, closing the window)."""
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            pass

    def exits_within(self, timeout: float) -> int:
        """Its exit status, which must come within ``timeout`` seconds (else the test fails)."""
        try:
            code = self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"still running {timeout:g} s later:\n{self.output()}") from None
        self._reader.join(5.0)
        return code

    def kill(self) -> None:
        """SIGKILL its group (clean-up)."""
        self.signal(signal.SIGKILL)
        try:
            self.popen.wait(5.0)
        except subprocess.TimeoutExpired:
            pass


@contextmanager
def commands(directory: Path) -> Iterator[Callable[..., Command]]:
    """Start ``arena`` command lines in ``directory``; each one, and every process naming ``directory``,
    is killed at the end."""
    started: list[Command] = []

    def start(*args: str, env: dict[str, str] | None = None) -> Command:
        cmd = Command(args, directory, env)
        started.append(cmd)
        return cmd

    try:
        yield start
    finally:
        for cmd in started:
            cmd.kill()
            kill_leftovers([str(directory)], cmd.pid)


def alive_ids(bus: Bus) -> set[str]:
    """The ids of the services whose presence is on ``bus`` (``gateway.x7``…)."""
    return {key.rsplit("/", 1)[1] for key in bus.alive("arena/sys/alive/**", 0.5)}


def stops_cleanly(
    cmd: Command, markers: Sequence[str], sig: int = signal.SIGINT, again_after: str | None = None
) -> int:
    """Send ``sig`` (and again once a line matches ``again_after``: the first was taken), wait for the
    exit, assert that nothing of it is left; its exit status."""
    cmd.signal(sig)
    if again_after is not None:
        cmd.wait_line(again_after, timeout=STOP_S)
        cmd.signal(sig)
    code = cmd.exits_within(STOP_S)
    wait_for(
        lambda: not leftovers(markers, cmd.pid),
        timeout=10,
        interval=0.1,
        what=f"no process left of `{' '.join(cmd.args[1:])}`",
    )
    return code


# -- any command line (make, python …, a unit's ExecStart) ---------------------------------------------------


class Program(Command):
    """Any command line (``make run``, ``python examples/…``, a systemd unit's ``ExecStart``) started as
    :class:`Command` starts ``arena``: its own session, the signal dispositions of a terminal's job, its
    output kept line by line; ``env`` replaces the environment's ``ARENA_CONFIG``/``ARENA_HOST`` (removed
    unless given)."""

    def __init__(self, argv: Sequence[str], cwd: Path, env: dict[str, str] | None = None) -> None:
        self.args = [str(a) for a in argv]
        environ = {k: v for k, v in os.environ.items() if k not in ("ARENA_CONFIG", "ARENA_HOST")}
        self.popen = subprocess.Popen(
            self.args,
            cwd=cwd,
            env={**environ, "PYTHONUNBUFFERED": "1", "NO_COLOR": "1", **(env or {})},
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=_as_a_terminal_job(os.getpid()),
        )
        self.lines = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()


@contextmanager
def programs(directory: Path) -> Iterator[Callable[..., Program]]:
    """Start command lines (``start(argv, cwd=…, env=…)``); each one, and every process naming
    ``directory``, is killed at the end."""
    started: list[Program] = []

    def start(argv: Sequence[str], cwd: Path = directory, env: dict[str, str] | None = None) -> Program:
        cmd = Program(argv, cwd, env)
        started.append(cmd)
        return cmd

    try:
        yield start
    finally:
        for cmd in started:
            cmd.kill()
            kill_leftovers([str(directory)], cmd.pid)
