"""The supervisor: process table from the config, restarts with back-off, clean stops, no orphans.

Mechanics run on small stand-in processes (a worker script below); the end-to-end test runs the real
services with ``arena up`` on a private config and kills its children.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from arena_common.bus.session import BusOptions, open_bus
from arena_common.cli import app
from arena_common.core import config as config_mod
from arena_common.core import keys
from arena_common.core.config import ZenohSpec
from arena_common.core.errors import ConfigError, WaitTimeout
from arena_common.runtime.supervisor import (
    Backoff,
    ProcessSpec,
    Supervisor,
    SupervisorError,
    describe_exit,
    endpoint_address,
    plan,
    sim_world_plan,
)
from tests.helpers import PYTHON, REPO, Proc, as_a_terminal_job, free_port, open_lab, wait_for, write_config

runner = CliRunner()

WORKER = textwrap.dedent(
    """
    import os, signal, socket, sys, time
    mode = sys.argv[1]
    print(f"hello {os.getpid()}", flush=True)
    if mode == "crash":
        sys.exit(3)
    if mode == "stubborn":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if mode == "listen":
        time.sleep(float(sys.argv[3]))
        s = socket.socket()
        s.bind(("127.0.0.1", int(sys.argv[2])))
        s.listen()
        print("listening", flush=True)
    if mode == "probe":
        try:
            socket.create_connection(("127.0.0.1", int(sys.argv[2])), timeout=1).close()
            print("probe ok", flush=True)
        except OSError as exc:
            print(f"probe refused {exc}", flush=True)
    if mode == "brief":
        time.sleep(float(sys.argv[2]))
        sys.exit(1)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        time.sleep(0.05)
    """
)


class Lines:
    """A thread-safe text sink that keeps every line written."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._buf = ""
        self._lock = threading.Lock()

    def write(self, text: str) -> int:
        with self._lock:
            self._buf += text
            *done, self._buf = self._buf.split("\n")
            self.lines += done
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def grep(self, pattern: str) -> list[str]:
        with self._lock:
            return [line for line in self.lines if re.search(pattern, line)]


def gone(pid: int) -> bool:
    """True once ``pid`` no longer runs (absent, or a zombie nobody reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return True


@pytest.fixture
def worker(tmp_path: Path) -> Path:
    path = tmp_path / "worker.py"
    path.write_text(WORKER)
    return path


def spec(worker: Path, name: str, *args: str, ready: tuple[str, int] | None = None) -> ProcessSpec:
    return ProcessSpec(name, (sys.executable, str(worker), *args), ready_port=ready)


@pytest.fixture
def running_supervisor() -> Iterator[list[tuple[Supervisor, threading.Event, threading.Thread]]]:
    """Supervisors started by a test in a thread; all stopped at the end."""
    started: list[tuple[Supervisor, threading.Event, threading.Thread]] = []
    yield started
    for sup, stop, thread in started:
        stop.set()
        thread.join(timeout=20)
        for pid in sup.pids().values():
            os.kill(pid, signal.SIGKILL)


def start(
    started: list[tuple[Supervisor, threading.Event, threading.Thread]], sup: Supervisor
) -> tuple[threading.Event, threading.Thread]:
    stop = threading.Event()
    thread = threading.Thread(target=sup.run, args=(stop,), daemon=True)
    thread.start()
    started.append((sup, stop, thread))
    return stop, thread


# -- the process table ----------------------------------------------------------------------------------


def test_plan_from_the_config(tmp_path: Path) -> None:
    cfg = config_mod.load(REPO / "deploy/sim.toml")
    specs = plan(cfg, "sim", python="/py")
    names = [s.name for s in specs]
    assert names == [
        "router",
        "sim-vehicle",
        "sim-motive",
        "mocap",
        "transform",
        *[f"{svc}.{v}" for v in ("d1", "d2", "d3") for svc in ("downsampler", "gateway")],
    ]
    cfg_path = str((REPO / "deploy/sim.toml").resolve())
    assert specs[0].argv == ("/py", "-m", "arena_common.cli", "router", "-c", cfg_path, "--host", "sim")
    assert specs[0].ready_port == ("127.0.0.1", 7447)
    assert all(s.ready_port is None for s in specs[1:])
    gw = specs[names.index("gateway.d2")].argv
    assert gw[:3] == ("/py", "-m", "services.mavlink_gateway") and gw[gw.index("--vehicle") + 1] == "d2"
    assert specs[names.index("mocap")].argv[2] == "services.mocap_ingest"

    # The shipped lab recipe is locked down: every session a client of the router, nothing listens.
    secured = config_mod.load(REPO / "deploy/lab.example.toml")
    assert [s.name for s in plan(secured, "cc1")] == ["gateway.c1"]
    assert not [s for h in secured.hosts for s in plan(secured, h) if "--listen" in s.argv]
    lab = config_mod.load(open_lab(tmp_path))
    cc1 = plan(lab, "cc1")
    assert [s.name for s in cc1] == ["downsampler.c1", "gateway.c1"]
    # Peers of a computer with an address listen there, so that other computers' peers reach them.
    assert cc1[0].argv[-2:] == ("--listen", "tcp/192.168.1.31:0")
    assert "--listen" not in plan(lab, "cc1", options=BusOptions(mode="client"))[0].argv
    ground = plan(lab, "ground", options=BusOptions(connect=("tcp/10.0.0.1:7447",), zconfig="z.json5"))
    assert [s.name for s in ground] == [
        "router",
        "mocap",
        "transform",
        "recorder",
        "downsampler.c3",
        "gateway.c3",
    ]
    assert ground[0].ready_port == ("127.0.0.1", 7447)  # tcp/0.0.0.0:7447 is probed on loopback
    assert "--connect" not in ground[0].argv and ground[0].argv[-2:] == ("--zconfig", "z.json5")
    assert ground[1].argv[-6:] == (
        "--connect",
        "tcp/10.0.0.1:7447",
        "--listen",
        "tcp/192.168.1.20:0",
        "--zconfig",
        "z.json5",
    )

    with pytest.raises(
        ConfigError, match=r"host 'nope' is not in the config \(known hosts: ground, cc1, cc2\)"
    ):
        plan(lab, "nope")
    assert [s.name for s in sim_world_plan(cfg, "sim")] == ["sim-vehicle", "sim-motive"]


def test_endpoint_address() -> None:
    assert endpoint_address("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert endpoint_address("tcp/[::]:7447") == ("::1", 7447)
    assert endpoint_address("tls/ground.lab:7447#iface=wlan0") == ("ground.lab", 7447)
    assert endpoint_address("udp/127.0.0.1:7447") is None
    assert endpoint_address("tcp/127.0.0.1:0") is None


def test_cli_dry_run_and_unknown_host() -> None:
    res = runner.invoke(app, ["up", str(REPO / "deploy/lab.example.toml"), "--host", "ground", "--dry-run"])
    assert res.exit_code == 0, res.output
    assert re.search(
        r"^router: .* -m arena_common.cli router -c \S+lab.example.toml --host ground", res.output, re.M
    )
    assert re.search(r"^gateway.c3: .* -m services.mavlink_gateway .* --vehicle c3", res.output, re.M)
    res = runner.invoke(app, ["up", str(REPO / "deploy/lab.example.toml"), "--host", "nope", "--dry-run"])
    assert res.exit_code == 2
    assert "known hosts: ground, cc1, cc2" in res.output
    # A one-host config (the simulation) runs on any machine without --host.
    res = runner.invoke(app, ["up", str(REPO / "deploy/sim.toml"), "--dry-run"], env={"ARENA_HOST": ""})
    assert res.exit_code == 0 and "gateway.d3:" in res.output


def test_backoff_doubles_to_the_maximum() -> None:
    b = Backoff(0.5, 10.0, 60.0)
    assert [b.delay(n) for n in range(1, 8)] == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert describe_exit(-9) == "killed by SIGKILL" and describe_exit(3) == "exited with status 3"
    with pytest.raises(SupervisorError, match="empty"):
        Supervisor([])


# -- mechanics on stand-ins -------------------------------------------------------------------------------


def test_restart_after_kill_with_prefixed_logs(worker: Path, running_supervisor: list) -> None:
    out = Lines()
    sup = Supervisor([spec(worker, "a", "run"), spec(worker, "b.d1", "run")], out=out, grace=3.0)
    start(running_supervisor, sup)
    pids = wait_for(lambda: len(sup.pids()) == 2 and sup.pids(), timeout=20, what="both workers")
    wait_for(lambda: out.grep(rf"^\[b\.d1\] hello {pids['b.d1']}$"), timeout=20, what="b.d1's prefixed line")
    os.kill(pids["b.d1"], signal.SIGKILL)
    wait_for(lambda: sup.pids().get("b.d1", pids["b.d1"]) != pids["b.d1"], timeout=20, what="b.d1 restarted")
    assert out.grep(
        rf"^\[arena\] b\.d1 \(pid {pids['b.d1']}\) killed by SIGKILL after .*restarting in 0\.5 s"
    )
    # The new pid is known a moment before the supervisor says so.
    wait_for(lambda: out.grep(r"^\[arena\] restarted b\.d1 \(pid \d+, restart 1\)"), 5, what="restart line")
    assert sup.pids()["a"] == pids["a"]  # the others are left alone
    assert sup.restart_count == 1


def test_backoff_grows_then_resets_after_a_stable_run(worker: Path, running_supervisor: list) -> None:
    events: list[tuple[float, str, str, str]] = []
    out = Lines()
    sup = Supervisor(
        [spec(worker, "crashy", "crash")],
        out=out,
        backoff=Backoff(initial=0.1, maximum=0.4, stable_s=60.0),
        on_event=lambda kind, name, detail: events.append((time.monotonic(), kind, name, detail)),
    )
    start(running_supervisor, sup)
    wait_for(lambda: sum(e[1] == "restarting" for e in events) >= 5, timeout=40, what="five restarts")
    delays = [float(e[3]) for e in events if e[1] == "restarting"][:5]
    assert delays == [0.1, 0.2, 0.4, 0.4, 0.4]
    assert out.grep(r"crashy \(pid \d+\) exited with status 3")

    events2: list[str] = []
    sup2 = Supervisor(
        [spec(worker, "brief", "brief", "0.4")],
        out=Lines(),
        backoff=Backoff(initial=0.1, maximum=5.0, stable_s=0.2),
        on_event=lambda kind, name, detail: events2.append(detail) if kind == "restarting" else None,
    )
    start(running_supervisor, sup2)
    wait_for(lambda: len(events2) >= 3, timeout=40, what="three restarts of a child that ran long enough")
    assert events2[:3] == ["0.1", "0.1", "0.1"]


def test_router_first_then_the_others(worker: Path, running_supervisor: list) -> None:
    port = free_port()
    out = Lines()
    sup = Supervisor(
        [
            spec(worker, "router", "listen", str(port), "0.5", ready=("127.0.0.1", port)),
            spec(worker, "svc", "probe", str(port)),
        ],
        out=out,
    )
    start(running_supervisor, sup)
    wait_for(lambda: out.grep(r"^\[svc\] probe"), timeout=30, what="the service's probe")
    assert out.grep(r"^\[svc\] probe ok$"), out.lines


def test_sigterm_then_sigkill_after_grace(worker: Path) -> None:
    out = Lines()
    sup = Supervisor(
        [spec(worker, "polite", "run"), spec(worker, "stubborn", "stubborn")], out=out, grace=1.0
    )
    stop = threading.Event()
    thread = threading.Thread(target=sup.run, args=(stop,), daemon=True)
    thread.start()
    try:
        pids = wait_for(lambda: len(sup.pids()) == 2 and sup.pids(), timeout=20, what="both workers")
        wait_for(lambda: out.grep(r"^\[stubborn\] hello"), timeout=20, what="stubborn ignoring SIGTERM")
        t0 = time.monotonic()
        stop.set()
        thread.join(timeout=20)
        assert not thread.is_alive()
        assert 0.9 <= time.monotonic() - t0 < 10
        assert all(gone(p) for p in pids.values())
        assert out.grep(r"stubborn did not stop within 1\.0 s: SIGKILL")
        assert not out.grep(r"polite did not stop")
        assert out.grep(r"^\[arena\] all stopped$")
    finally:
        for pid in sup.pids().values():
            os.kill(pid, signal.SIGKILL)


DRIVER = textwrap.dedent(
    """
    import sys
    from arena_common.runtime.supervisor import ProcessSpec, supervise
    worker = sys.argv[1]
    specs = [ProcessSpec(f"w{i}", (sys.executable, worker, "stubborn" if i else "run")) for i in range(2)]
    supervise(specs, grace=1.0)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux only")
def test_children_die_with_a_killed_supervisor(
    worker: Path, tmp_path: Path, processes: Callable[..., Proc]
) -> None:
    """SIGKILL of the supervisor: the kernel kills each child, even one that ignores SIGTERM."""
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    proc = processes("driver", [PYTHON, str(driver), str(worker)])
    pids: dict[str, int] = {}
    try:

        def both_started() -> bool:
            for line in list(proc.lines):
                m = re.match(r"\[arena\] started (\w+) \(pid (\d+)\)", line)
                if m:
                    pids[m[1]] = int(m[2])
            return len(pids) == 2

        wait_for(both_started, timeout=30, what="the driver's two children")
        proc.signal(signal.SIGKILL)
        proc.wait(timeout=10)
        wait_for(lambda: all(gone(p) for p in pids.values()), timeout=10, what="children to die with it")
    finally:
        proc.signal(signal.SIGKILL)
        for pid in pids.values():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


# -- the real arena -----------------------------------------------------------------------------------------


@pytest.mark.system
def test_arena_up_runs_restarts_and_stops_the_real_services(
    tmp_path: Path, processes: Callable[..., Proc]
) -> None:
    """`arena up` on a private config: the chain flows, kill -9 of each child is repaired, Ctrl-C ends all."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    path = write_config(tmp_path, endpoint, n_vehicles=1)
    text = path.read_text().replace(
        'services = ["sim", "mocap", "transform"]', 'services = ["router", "sim", "mocap", "transform"]'
    )
    path.write_text(text)
    expected = {"router", "sim-vehicle", "sim-motive", "mocap", "transform", "downsampler.d1", "gateway.d1"}
    proc = processes("arena-up", [PYTHON, "-m", "arena_common.cli", "up", str(path), "--host", "test"])

    def grep(pattern: str) -> list[str]:
        return [line for line in (x.rstrip("\n") for x in list(proc.lines)) if re.search(pattern, line)]

    bus = open_bus(ZenohSpec(mode="peer", connect=(endpoint,)))
    every_pid: set[int] = set()

    def pids() -> dict[str, int]:
        found: dict[str, int] = {}
        for line in grep(r"^\[arena\] (re)?started "):
            m = re.match(r"\[arena\] (?:re)?started (\S+) \(pid (\d+)", line)
            if m:
                found[m[1]] = int(m[2])
        every_pid.update(found.values())
        return found

    try:
        vision = bus.subscribe(keys.vision("d1"), capacity=1)
        state = bus.subscribe(keys.state("d1"), capacity=1)
        stats = bus.subscribe(keys.stats("test", "supervisor"), capacity=1)

        def flowing(after: int) -> bool:
            v, s = vision.get(0.05), state.get(0.05)
            return bool(v and s and v.t_recv > after and s.t_recv > after)

        first = wait_for(lambda: set(pids()) == expected and pids(), timeout=60, what="every child started")
        wait_for(
            lambda: flowing(0), timeout=90, interval=0.05, what="vision and state of d1 (the whole chain)"
        )
        # The supervisor's own session started before the router: it joins at its next connect retry.
        alive = wait_for(
            lambda: (
                (a := bus.alive("arena/sys/alive/test/**")) and "arena/sys/alive/test/supervisor" in a and a
            ),
            timeout=15,
            what="the supervisor's presence",
        )
        assert len(alive) >= len(expected) + 1, alive

        t_kill = time.time_ns()
        for pid in first.values():
            os.kill(pid, signal.SIGKILL)
        wait_for(
            lambda: all(pids().get(n) not in (None, first[n]) for n in expected),
            timeout=60,
            what="every child restarted with a new pid",
        )
        for name in expected:
            assert grep(rf"^\[arena\] {re.escape(name)} \(pid {first[name]}\) killed by SIGKILL"), name
        wait_for(lambda: flowing(t_kill), timeout=90, interval=0.05, what="the chain flowing again")

        def restarts_published() -> bool:
            item = stats.get(0.2)
            return bool(item and item.payload and item.payload.counts.get("restarts", 0) >= len(expected))

        wait_for(restarts_published, timeout=10, what="the supervisor's stats counting the restarts")

        assert proc.stop(40.0) == 0, proc.tail()  # SIGINT, as Ctrl-C
        survivors = [p for p in every_pid if not gone(p)]
        assert not survivors, f"children left behind: {survivors}"
        assert grep(r"^\[arena\] all stopped$")
    finally:
        bus.close()
        for pid in every_pid:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_sim_world_runs_both_parts_and_stops(
    tmp_path: Path, router_endpoint: str, processes: Callable[..., Proc]
) -> None:
    """`arena sim world CONFIG`: simulated vehicles and Motive emulator, supervised; Ctrl-C ends both."""
    path = write_config(tmp_path, router_endpoint, n_vehicles=1)
    argv = [PYTHON, "-m", "arena_common.cli", "sim", "world", str(path), "--host", "test"]
    proc = processes("sim-world", argv)
    bus = open_bus(ZenohSpec(mode="peer", connect=(router_endpoint,)))
    pids: list[int] = []
    try:
        truth = bus.subscribe(keys.truth("d1"), capacity=1)
        wait_for(
            lambda: truth.get(0.1) is not None, timeout=60, what="d1's true pose from the simulated world"
        )
        wait_for(
            lambda: (
                {"sim-vehicle", "sim-motive"}
                <= {k.rsplit("/", 1)[1] for k in bus.alive("arena/sys/alive/test/**")}
            ),
            timeout=30,
            what="both parts' presence",
        )
        pids = [int(p) for p in re.findall(r"^\[arena\] started \S+ \(pid (\d+)\)", proc.output(), re.M)]
        assert len(pids) == 2
        assert proc.stop(30.0) == 0, proc.tail()  # SIGINT, as Ctrl-C
        assert all(gone(p) for p in pids)
    finally:
        bus.close()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _processes_of(config: Path) -> list[str]:
    """Command lines of the processes that name ``config``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(config) in cmd:
            found.append(f"{entry.name}: {cmd.strip()}")
    return found


@pytest.mark.system
def test_closing_the_terminal_stops_the_demo_and_every_process(tmp_path: Path, router_endpoint: str) -> None:
    """`make run` in a terminal that is then closed (SIGHUP): nothing of the arena is left running."""
    import pty

    cfg = write_config(tmp_path, router_endpoint, n_vehicles=1)
    arena = Path(sys.executable).parent / "arena"
    pid, fd = pty.fork()
    if pid == 0:  # the child: the demo on a terminal of its own, as its shell starts it
        as_a_terminal_job()  # a test run under nohup would leave SIGHUP ignored, and the demo outlive it
        os.chdir(tmp_path)
        os.execv(str(arena), [str(arena), "demo", str(cfg), "--log", str(tmp_path / "demo.log")])
    try:
        out = bytearray()

        def started() -> bool:
            import select

            while select.select([fd], [], [], 0.05)[0]:
                try:
                    out.extend(os.read(fd, 65536))
                except OSError:
                    break
            return b"arena starting" in out and len(_processes_of(cfg)) >= 4

        wait_for(started, timeout=60, interval=0.1, what="the demo and its services running")
        os.close(fd)  # the terminal window closes
        try:
            wait_for(lambda: not _processes_of(cfg), timeout=60, interval=0.2, what="every process gone")
        except WaitTimeout:
            raise AssertionError(f"60 s after the terminal closed: {_processes_of(cfg)}") from None
        _, status = os.waitpid(pid, 0)
        assert os.WIFEXITED(status) or os.WIFSIGNALED(status)
    finally:
        for line in _processes_of(cfg):
            os.kill(int(line.split(":", 1)[0]), signal.SIGKILL)
        try:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
