"""What every tier's tests share: free ports, configs with their own endpoints, child processes started the
arena's way (:class:`Proc`), bounded waits.  The fixtures built on them are in ``tests/conftest.py``.

Tests may run in parallel (``pytest -n``, pytest-xdist): every port comes from :func:`free_port`, which
hands each worker its own range below the kernel's ephemeral ports, so no two workers of a run (and no
port the kernel picks for an outgoing connection) get the same one.
"""

from __future__ import annotations

import itertools
import os
import random
import signal
import socket
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from signal import SIGINT
from typing import IO, Any

from arena_common.core.waiting import wait_until
from arena_common.runtime.process import ChildProcess

REPO = Path(__file__).resolve().parent.parent
TESTS = REPO / "tests"
PYTHON = sys.executable

# -- ports ---------------------------------------------------------------------------------------------------

#: Ports handed out to tests: below Linux's default ephemeral range (32768–60999), above most services.
PORT_LOW, PORT_HIGH = 12000, 32000


def _worker_range() -> range:
    """This process's share of the test ports: the xdist worker's slice of ``PORT_LOW..PORT_HIGH``."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    count = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))
    index = int(worker[2:]) % count if worker[2:].isdigit() else 0
    span = (PORT_HIGH - PORT_LOW) // count
    return range(PORT_LOW + index * span, PORT_LOW + (index + 1) * span)


_range = _worker_range()
# From a random point: another test run may share the machine (its workers have the same slices).
_ports = itertools.cycle(itertools.chain(_range[(start := random.randrange(len(_range))) :], _range[:start]))
_ports_lock = threading.Lock()


def _bindable(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port nobody uses right now for TCP or UDP (``kind`` names the one the caller means to
    use), from this xdist worker's own range: not handed out again before the worker has gone through the
    whole range, and never one another worker of this run can get."""
    other = socket.SOCK_DGRAM if kind == socket.SOCK_STREAM else socket.SOCK_STREAM
    with _ports_lock:
        for port in itertools.islice(_ports, len(_range)):
            if _bindable(port, kind) and _bindable(port, other):
                return port
    raise AssertionError(f"no free port in {_range.start}..{_range.stop - 1} (every one is in use)")


def wait_for(
    predicate: Callable[[], Any], timeout: float = 5.0, interval: float = 0.01, what: str = "condition"
) -> Any:
    """:func:`~arena_common.core.waiting.wait_until` with ``interval`` as its third argument."""
    return wait_until(predicate, timeout, what, interval=interval)


# -- processes -----------------------------------------------------------------------------------------------


def service_argv(module: str, cfg_path: Path | str, *extra: str, host: str | None = "test") -> list[str]:
    """The command line of one service (``services.<module>``) on ``cfg_path``, as ``host`` by default."""
    argv = [PYTHON, "-m", f"services.{module}", "-c", str(cfg_path)]
    return argv + (["--host", host] if host else []) + list(extra)


class Proc:
    """One child process of a test, a :class:`~arena_common.runtime.process.ChildProcess` (own process
    group; killed by the kernel if the test process dies), its output kept in :attr:`lines` and written to
    ``<log_dir>/<name>.log``.

    Start it from a thread that outlives it (the test's own): the kernel kills it when that thread ends.
    """

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        log_dir: Path,
        env: Mapping[str, str] | None = None,
        cwd: Path = REPO,
    ) -> None:
        self.name = name
        self.argv = list(argv)
        self.log_path = log_dir / f"{name}.log"
        self.lines: list[str] = []
        self._log: IO[str] = self.log_path.open("a")
        self.child = ChildProcess(
            self.argv,
            name=name,
            cwd=cwd,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            on_line=self._line,
        )

    def _line(self, line: str) -> None:
        self.lines.append(line)
        self.on_line(line)
        try:
            self._log.write(line)
            self._log.flush()
        except ValueError:  # the log was closed by stop() while the last lines arrived
            pass

    def on_line(self, line: str) -> None:
        """Called for every line of output (subclasses parse them)."""

    @property
    def pid(self) -> int:
        """The child's pid."""
        return self.child.pid

    @property
    def running(self) -> bool:
        """True until the child has exited."""
        return self.child.alive

    @property
    def returncode(self) -> int | None:
        """The exit status, ``None`` while it runs."""
        return self.child.returncode

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process itself (not its group)."""
        self.child.send_signal(sig, group=False)

    def wait(self, timeout: float) -> int:
        """Wait for it to exit (``subprocess.TimeoutExpired`` after ``timeout``); its status."""
        return self.child.wait(timeout)

    def stop(self, timeout: float = 15.0, sig: int = SIGINT) -> int | None:
        """``sig`` (SIGINT by default), then SIGKILL after ``timeout``; the exit status."""
        code = self.child.stop(timeout, sig)
        self._log.close()
        return code

    def output(self) -> str:
        """Everything it printed so far."""
        return "".join(self.lines)

    def tail(self, n: int = 30) -> str:
        """Its last ``n`` lines of output."""
        return "".join(self.lines[-n:])


# -- the bus and configs -------------------------------------------------------------------------------------


def write_config(
    tmp_path: Path,
    router_endpoint: str,
    n_vehicles: int = 1,
    extra: str = "",
    services: tuple[str, ...] = ("sim", "mocap", "transform"),
    spacing: float = 1.0,
    **sim: Any,
) -> Path:
    """Write an arena config whose every port is free and private to this test; the vehicles start in
    a line along north from -1 m, ``spacing`` apart."""
    cmd_port, data_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    lines = [
        "[arena]",
        'name = "test"',
        "[mocap]",
        f"command_port = {cmd_port}",
        f"data_port = {data_port}",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["{router_endpoint}"]',
        f'router_listen = ["{router_endpoint}"]',
        "[hosts.test]",
        "services = [" + ", ".join(f'"{x}"' for x in services) + "]",
        "vehicles = [" + ", ".join(f'"d{i + 1}"' for i in range(n_vehicles)) + "]",
    ]
    for i in range(n_vehicles):
        port = free_port(socket.SOCK_DGRAM)
        lines += [
            f"[vehicles.d{i + 1}]",
            f'rigid_body = "d{i + 1}"',
            f'mavlink = "udpin:127.0.0.1:{port}"',
            f"system_id = {i + 1}",
            f"sim = {{ start = [{i * spacing - 1.0}, 0.0] }}",
        ]
    if sim:
        lines.append("[sim]")
        lines += [f"{k} = {v!r}".replace("'", '"') for k, v in sim.items()]
    lines.append(extra)
    path = tmp_path / "arena.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def open_lab(tmp_path: Path) -> Path:
    """``deploy/lab.example.toml`` as an open lab of peers: no ``[security]`` (``insecure = true``), plain
    TCP, a downsampler per vehicle on its companion computer — the topology the locked-down recipe avoids."""
    import re as _re

    text = (REPO / "deploy" / "lab.example.toml").read_text()
    text = _re.sub(r"\n\[security\]\n(?:[^\[\n][^\n]*\n)*", "\n[security]\ninsecure = true\n\n", text)
    text = text.replace('mode = "client"', 'mode = "peer"').replace('"tls/', '"tcp/')
    text = text.replace('router_listen = ["tcp/192.168.1.20:7447"]', 'router_listen = ["tcp/0.0.0.0:7447"]')
    text = text.replace('decimate = "transform"', 'decimate = "downsampler"')
    path = tmp_path / "open-lab.toml"
    path.write_text(text)
    return path


#: What a shell resets in the job it starts: a test run under ``nohup`` (SIGHUP ignored, inherited through
#: exec) must still show a typed command what a terminal gives it.
TERMINAL_JOB_SIGNALS = (signal.SIGINT, signal.SIGHUP, signal.SIGTERM, signal.SIGQUIT)


def as_a_terminal_job() -> None:
    """In a child before exec: the signal dispositions a shell gives a foreground job (each its default)."""
    for sig in TERMINAL_JOB_SIGNALS:
        signal.signal(sig, signal.SIG_DFL)
