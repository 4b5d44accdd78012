"""``arena`` as a user types it: the real console script, in a session of its own as a terminal runs a
job, on a config of free ports whose vehicles are not the default config's.

The shared options (``-c/--config``, ``--connect``, ``--listen``…), before or after the sub-command,
reach every ``arena run`` and ``arena sim`` service: each serves the named config's ports and vehicles
(seen from its presence on this test's private router, the ports it binds and its log).  A named config
that cannot be read is an error naming it, for every command.  Ctrl-C, a closed terminal (SIGHUP),
SIGTERM and a double Ctrl-C end each command with nothing of it left running.
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

import pytest

from arena_common.bus.session import Bus
from arena_common.core.waiting import wait_until
from arena_common.runtime.process import child_setup
from tests.conftest import REPO, free_port, wait_for

ARENA = Path(sys.executable).parent / "arena"  # the console script, as `make setup` installs it
pytestmark = pytest.mark.skipif(not ARENA.exists(), reason=f"no arena console script at {ARENA}")

STOP_S = 15.0  # how long a service may take to stop after Ctrl-C
START_S = 45.0  # how long one may take to start on a busy 2-core machine


# -- the config --------------------------------------------------------------------------------------------


class Typed:
    """A config of free ports whose vehicle is x7 (and, with ``px4``, x8: PX4 SITL instance ``instance``,
    on no host); ``router``: the host runs the router (``arena up``, ``arena demo``)."""

    def __init__(
        self,
        directory: Path,
        endpoint: str,
        *,
        connect: str | None = None,
        router: bool = False,
        px4: bool = True,
    ) -> None:
        self.dir = directory
        self.endpoint = endpoint
        self.command_port = free_port(socket.SOCK_DGRAM)
        self.data_port = free_port(socket.SOCK_DGRAM)
        self.x7_port = free_port(socket.SOCK_DGRAM)
        self.instance = next((i for i in range(9, -1, -1) if _udp_free(19410 + i)), 9)
        self.truth_port = 19410 + self.instance
        self.rec_dir = directory / "rec"
        services = ["router", "sim", "mocap", "transform"] if router else ["sim", "mocap", "transform"]
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
        for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGTERM, signal.SIGQUIT):
            signal.signal(sig, signal.SIG_DFL)
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


@pytest.fixture
def typed(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    """:func:`commands` in ``tmp_path`` (no ``deploy/`` there: a default config cannot be read)."""
    with commands(tmp_path) as start:
        yield start


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


# -- every service serves the config named on the command line -----------------------------------------------

# (id, command line, presence ids, a log line, ports it binds); {CFG}, {cmd}… are the config's.
SERVICES: list[tuple[str, list[str], set[str], str, list[tuple[str, str]]]] = [
    (
        "sim-vehicle",
        ["sim", "vehicle", "-c", "{CFG}"],
        {"sim_vehicle"},
        r"simulating x7 \(sysid 7, udpout:127\.0\.0\.1:{x7}\)",
        [],
    ),
    (
        "sim-mocap",
        ["sim", "mocap", "-c", "{CFG}"],
        {"sim_mocap"},
        r"server on 127\.0\.0\.1:{cmd}",
        [("udp", "{cmd}")],
    ),
    (
        "sim-mocap-config-first",
        ["-c", "{CFG}", "sim", "mocap"],
        {"sim_mocap"},
        r"streaming x7 \(id",
        [("udp", "{cmd}")],
    ),
    (
        "sim-mocap-long-option",
        ["sim", "mocap", "--config", "{CFG}"],
        {"sim_mocap"},
        r"server on 127\.0\.0\.1:{cmd}",
        [("udp", "{cmd}")],
    ),
    (
        "sim-world",
        ["sim", "world", "-c", "{CFG}", "--host", "typed"],
        {"sim_vehicle", "sim_mocap"},
        r"\[sim_mocap\] .*streaming x7",
        [("udp", "{cmd}")],
    ),
    (
        "run-mocap",
        ["run", "mocap", "-c", "{CFG}"],
        {"mocap"},
        r"source natnet \(server 127\.0\.0\.1:{cmd},",
        [],
    ),
    (
        "run-transform",
        ["--config", "{CFG}", "run", "transform"],
        {"transform"},
        r"arena\.transform: started",
        [],
    ),
    (
        "run-downsampler",
        ["run", "downsampler", "--vehicle", "x7", "--config={CFG}"],
        {"downsampler.x7"},
        r"arena/x7/pose → arena/x7/vision",
        [],
    ),
    (
        "run-gateway",
        ["run", "gateway", "-c", "{CFG}", "--vehicle", "x7"],
        {"gateway.x7"},
        r"gateway for x7: udpin:127\.0\.0\.1:{x7}, system 7",
        [("udp", "{x7}")],
    ),
    ("run-recorder", ["run", "recorder", "-c", "{CFG}"], {"recorder"}, r"recording to {rec}/", []),
    (
        "run-px4-truth",
        ["run", "px4-truth", "-c", "{CFG}", "--vehicle", "x8"],
        {"px4_truth.x8"},
        r"udp 127\.0\.0\.1:{truth} \(PX4 SITL instance",
        [("udp", "{truth}")],
    ),
]


@pytest.mark.parametrize(
    ("args", "ids", "line", "ports"), [s[1:] for s in SERVICES], ids=[s[0] for s in SERVICES]
)
def test_each_service_serves_the_named_config_and_stops_on_ctrl_c(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    typed: Callable[..., Command],
    args: list[str],
    ids: set[str],
    line: str,
    ports: list[tuple[str, str]],
) -> None:
    cfg = Typed(tmp_path, router_endpoint)
    if "px4-truth" in args and not _udp_free(cfg.truth_port):
        pytest.skip(f"udp port {cfg.truth_port} of PX4 SITL instance {cfg.instance} is in use")
    bus = bus_factory()
    cmd = typed(*(cfg.fill(a) for a in args))
    cmd.wait_line(cfg.fill(line))
    wait_until(lambda: ids <= alive_ids(bus), START_S, f"presence of {ids}", interval=0.2, check=cmd.running)
    for kind, port in ports:
        assert bound(kind, int(cfg.fill(port))), f"{kind} port {cfg.fill(port)} not bound:\n{cmd.output()}"
    assert stops_cleanly(cmd, [str(tmp_path)]) == 0, cmd.output()


def test_px4_sitl_flies_the_named_configs_vehicle(tmp_path: Path, typed: Callable[..., Command]) -> None:
    """x8 is only in the named config: the service reaches the build it was given (none here)."""
    cfg = Typed(tmp_path, f"tcp/127.0.0.1:{free_port()}")
    nowhere = tmp_path / "no-px4-build"
    cmd = typed("run", "px4-sitl", "--vehicle", "x8", "-c", str(cfg.path), "--build", str(nowhere))
    assert cmd.exits_within(30) == 2, cmd.output()
    assert f"no PX4 SITL build (bin/px4 and etc/) found: looked at {nowhere}" in cmd.output()


def test_the_bus_options_reach_the_service_too(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], typed: Callable[..., Command]
) -> None:
    """--connect (before the sub-command) and --listen (after it) replace the config's endpoints."""
    dead = f"tcp/127.0.0.1:{free_port()}"  # the config's router: nobody listens there
    cfg = Typed(tmp_path, dead, connect=dead)
    port = free_port()
    bus = bus_factory()
    cmd = typed("-e", router_endpoint, "run", "transform", "-c", str(cfg.path), "-l", f"tcp/127.0.0.1:{port}")
    cmd.wait_line(r"arena\.transform: started")
    wait_for(
        lambda: "transform" in alive_ids(bus), timeout=START_S, interval=0.2, what="presence via --connect"
    )
    wait_for(lambda: bound("tcp", port), timeout=10, what=f"a listener on tcp {port} (--listen)")
    assert stops_cleanly(cmd, [str(tmp_path)]) == 0, cmd.output()


# -- a named config that cannot be read --------------------------------------------------------------------

RUN = ["mocap", "transform", "downsampler", "gateway", "recorder", "px4-sitl", "px4-truth"]
SIM = ["vehicle", "mocap", "world"]
MISSING: list[list[str]] = [
    *(["run", name, "--vehicle", "x7", "-c", "{MISSING}"] for name in RUN),
    *(["sim", name, "-c", "{MISSING}"] for name in SIM),
    ["-c", "{MISSING}", "sim", "mocap"],
    ["run", "gateway", "--vehicle", "x7", "--config={MISSING}"],
    ["up", "-c", "{MISSING}"],
    ["-c", "{MISSING}", "up"],
    ["demo", "-c", "{MISSING}"],
    ["view", "-c", "{MISSING}"],
    ["status", "--config", "{MISSING}"],
    ["echo", "arena/**", "-c", "{MISSING}"],
    ["keys", "-c", "{MISSING}"],
]


@pytest.mark.parametrize("args", MISSING, ids=[" ".join(a).replace("{MISSING}", "M") for a in MISSING])
def test_a_named_config_that_cannot_be_read_is_an_error_naming_it(tmp_path: Path, args: list[str]) -> None:
    missing = tmp_path / "missing.toml"
    environ = {k: v for k, v in os.environ.items() if k != "ARENA_CONFIG"}
    res = subprocess.run(
        [str(ARENA), *(a.replace("{MISSING}", str(missing)) for a in args)],
        cwd=REPO,  # where deploy/sim.toml is: it must not be used instead
        env=environ,
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert res.returncode == 2, res
    assert f"error: {missing}: cannot read: No such file or directory" in res.stderr, res
    assert "deploy/sim.toml" not in res.stderr + res.stdout


@pytest.mark.parametrize("args", [["up", "{A}", "-c", "{B}"], ["sim", "world", "{A}", "--config", "{B}"]])
def test_two_different_configs_named_are_an_error(tmp_path: Path, args: list[str]) -> None:
    a, b = Typed(tmp_path, "tcp/127.0.0.1:1").path, tmp_path / "other.toml"
    b.write_text(a.read_text())
    res = subprocess.run(
        [str(ARENA), *(x.replace("{A}", str(a)).replace("{B}", str(b)) for x in args)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2, res
    assert f"two config files named: {a} (argument) and {b} (--config)" in res.stderr


# -- signals: nothing outlives its terminal ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("sig", "twice"),
    [(signal.SIGHUP, False), (signal.SIGTERM, False), (signal.SIGINT, True)],
    ids=["SIGHUP", "SIGTERM", "SIGINT-twice"],
)
def test_sim_world_and_its_children_end_on_any_stop_signal(
    tmp_path: Path, router_endpoint: str, typed: Callable[..., Command], sig: int, twice: bool
) -> None:
    cfg = Typed(tmp_path, router_endpoint)
    cmd = typed("sim", "world", "-c", str(cfg.path), "--host", "typed")
    cmd.wait_line(r"\[sim_mocap\] .*streaming x7")
    cmd.wait_line(r"\[sim_vehicle\] .*simulating x7")
    assert len(leftovers([str(cfg.path)])) >= 3  # the supervisor and its two children
    code = stops_cleanly(cmd, [str(tmp_path)], sig, r"^\[arena\] stopping " if twice else None)
    assert code == 0, cmd.output()


@pytest.mark.parametrize("args", [["run", "gateway", "--vehicle", "x7"], ["view", "--port", "0"]])
def test_a_closed_terminal_stops_a_service_in_order(
    tmp_path: Path, router_endpoint: str, typed: Callable[..., Command], args: list[str]
) -> None:
    """SIGHUP is an orderly stop, as Ctrl-C: the service says it stopped."""
    cfg = Typed(tmp_path, router_endpoint)
    cmd = typed(*args, "-c", str(cfg.path), "--log-level", "INFO")
    cmd.wait_line(r": started \(host")
    assert stops_cleanly(cmd, [str(tmp_path)], signal.SIGHUP) == 0, cmd.output()
    assert re.search(r"arena\.\S+: stopped$", cmd.output(), re.M), cmd.output()


STOP_SIGNALS_SCRIPT = """
import signal, sys, threading, time
from arena_common.runtime.process import StopSignals
stop, again = threading.Event(), []
with StopSignals(stop, again=again.append) as signals:
    print("ready", flush=True)
    stop.wait(30)
    print("stopped", signal.Signals(signals.received[0]).name, flush=True)
    deadline = time.monotonic() + 30
    while not again and time.monotonic() < deadline:
        time.sleep(0.01)
    print("received", *(signal.Signals(s).name for s in signals.received), flush=True)
    print("again", *(signal.Signals(s).name for s in again), flush=True)
"""


@pytest.mark.parametrize("nohup", [False, True], ids=["terminal", "nohup-background"])
def test_stop_signals_first_stops_a_further_one_hurries(tmp_path: Path, nohup: bool) -> None:
    """The first stop signal stops, a further SIGINT/SIGTERM hurries, a further SIGHUP does not; a
    SIGINT ignored from the start (a shell script's background job) is handled, an ignored SIGHUP
    (``nohup``) stays ignored."""
    script = tmp_path / "signals.py"
    script.write_text(STOP_SIGNALS_SCRIPT)

    def setup() -> None:
        for sig in (signal.SIGINT, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN if nohup else signal.SIG_DFL)

    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=setup,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        first = signal.SIGINT if nohup else signal.SIGHUP
        if nohup:
            proc.send_signal(signal.SIGHUP)  # ignored: SIGINT below is the first one taken
        proc.send_signal(first)
        assert proc.stdout.readline() == f"stopped {first.name}\n"
        proc.send_signal(signal.SIGHUP)  # nohup: ignored; else taken, but no hurry
        proc.send_signal(signal.SIGTERM)
        received = [first.name] + ([] if nohup else ["SIGHUP"]) + ["SIGTERM"]
        assert sorted(proc.stdout.readline().split()[1:]) == sorted(received)
        assert proc.stdout.readline() == "again SIGTERM\n"
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait(5)
