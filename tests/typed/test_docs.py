"""The commands of README.md and docs/*.md, typed as a reader types them, on configs of free ports.

Each doc config (``deploy/sim.toml``, ``deploy/px4-sitl.toml``) is copied with its ports replaced by free
ones (:func:`free_ports_config`: the router endpoint, the NatNet ports, each vehicle's MAVLink port or PX4
instance), the vehicles' names kept; a command that names the doc's config names the copy instead, one
that relies on ``$ARENA_CONFIG`` gets the copy there.  What each test asserts is what the docs promise:
``make run`` flies the vehicles live in a real terminal and Ctrl-C lands them before the arena stops;
an example flies against ``arena up``; ``arena status``/``echo``/``arm`` answer from the running arena;
``arena view`` serves Foxglove's WebSocket protocol; the bench lines run (shortened) and write their
results where they are told, never into the checkout; and nothing is left running afterwards.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import termios
import threading
import tomllib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from arena_common import Arena
from arena_common.bus.session import Bus
from arena_common.core.config import load
from arena_common.core.waiting import wait_until
from arena_common.runtime.px4_sitl import (
    Px4SitlError,
    build_missing_reason,
    instance_busy,
    is_true,
    listener,
)
from arena_common.runtime.supervisor import endpoint_address
from tests.helpers import REPO, free_port, wait_for
from tests.typed.harness import (
    START_S,
    Command,
    Program,
    Typed,
    _as_a_terminal_job,
    alive_ids,
    bound,
    commands,
    kill_leftovers,
    leftovers,
    programs,
    stops_cleanly,
)

PYTHON = Path(sys.executable)  # .venv/bin/python, as the docs write it
READY_S = 150.0  # `arena up` until every vehicle has vision fused, on a busy 2-core machine
FLYING_S = 200.0  # `make run` until the formation flies (three vehicles)
LANDED_S = 60.0  # Ctrl-C until make returns: the landing (at most 10 s) and the arena's stop
SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")


# -- configs of the docs, on free ports ------------------------------------------------------------------------


def free_ports_config(source: Path, dest: Path, *, px4_instances: Sequence[int] = ()) -> Path:
    """``source`` (a doc's config) written to ``dest`` with every port it takes replaced by a free one:
    the Zenoh endpoints, NatNet's command and data ports, each vehicle's ``udpin`` port, and each PX4
    SITL vehicle's instance (by ``px4_instances``, in order); the recorder's directory moved beside it.
    Comments and everything else are kept; the result is parsed again and checked."""
    text = source.read_text()
    doc = tomllib.loads(text)
    endpoints = {
        e: f"tcp/127.0.0.1:{free_port()}" for e in [*doc["zenoh"]["connect"], *doc["zenoh"]["router_listen"]]
    }
    for old, moved in endpoints.items():
        text = text.replace(f'"{old}"', f'"{moved}"')
    ports = {key: free_port(socket.SOCK_DGRAM) for key in ("command_port", "data_port")}
    for key, port in ports.items():
        text, n = re.subn(rf"^({key}\s*=\s*){doc['mocap'][key]}\b", rf"\g<1>{port}", text, flags=re.M)
        assert n == 1, f"{source}: [mocap] {key} not found once"
    links: dict[str, str] = {}
    instances = iter(px4_instances)
    for name, vehicle in doc["vehicles"].items():
        if "mavlink" in vehicle:
            m = re.fullmatch(r"(udpin:127\.0\.0\.1:)(\d+)", vehicle["mavlink"])
            assert m is not None, f"{source}: {name}: a mavlink this helper cannot move: {vehicle['mavlink']}"
            links[name] = f"{m[1]}{free_port(socket.SOCK_DGRAM)}"
            text = text.replace(f'mavlink = "{vehicle["mavlink"]}"', f'mavlink = "{links[name]}"', 1)
        if "px4_instance" in vehicle:
            section = f"[vehicles.{name}]"
            head, rest = text.split(section, 1)
            rest = re.sub(
                r"^px4_instance\s*=\s*\d+", f"px4_instance = {next(instances)}", rest, count=1, flags=re.M
            )
            text = head + section + rest
    recordings = dest.parent / "recordings"
    if "recorder" in doc:
        text = re.sub(r'^(directory\s*=\s*)"[^"]*"', rf'\g<1>"{recordings}"', text, count=1, flags=re.M)
    dest.write_text(text)
    new = tomllib.loads(text)  # what the copy says: every port moved, nothing else
    assert new["zenoh"]["connect"] == [endpoints[e] for e in doc["zenoh"]["connect"]]
    assert new["zenoh"]["router_listen"] == [endpoints[e] for e in doc["zenoh"]["router_listen"]]
    assert {k: new["mocap"][k] for k in ports} == ports
    assert {n: v["mavlink"] for n, v in new["vehicles"].items() if "mavlink" in v} == links
    assert [v["px4_instance"] for v in new["vehicles"].values() if "px4_instance" in v] == list(px4_instances)
    assert list(new["vehicles"]) == list(doc["vehicles"]) and new["hosts"] == doc["hosts"]
    return dest


def lab_config(directory: Path) -> Path:
    """docs/lab.md's arena in small: one host running everything, the simulated vehicle c1."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    path = directory / "lab.toml"
    lines = [
        "[arena]",
        'name = "lab"',
        "[mocap]",
        f"command_port = {free_port(socket.SOCK_DGRAM)}",
        f"data_port = {free_port(socket.SOCK_DGRAM)}",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        "multicast = false",
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["{endpoint}"]',
        f'router_listen = ["{endpoint}"]',
        "[hosts.ground]",
        'services = ["router", "sim", "mocap", "transform"]',
        'vehicles = ["c1"]',
        "[vehicles.c1]",
        'rigid_body = "c1"',
        f'mavlink = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"',
        "system_id = 1",
        "sim = { start = [0.0, 0.0] }",
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def wait_ready(config: Path, names: Sequence[str], up: Command, timeout: float = READY_S) -> None:
    """Until every vehicle of ``names`` has its link, its setup and vision fused (what a reader sees in
    ``arena status`` before typing the next command); ``up`` must keep running.

    The session is a Zenoh client, which gives up after 10 s without its router, and ``arena up`` starts its
    router only after its own presence (3.6 s after it starts on an idle 2-core machine, 13.4 s loaded: load
    average 5): it opens once the router listens."""
    ports = [a[1] for e in load(config).zenoh.connect if (a := endpoint_address(e)) is not None]
    wait_until(
        lambda: any(bound("tcp", port) for port in ports),
        timeout,
        f"the router listening on tcp {ports}",
        interval=0.1,
        check=up.running,
    )
    with Arena(config, name="typed-docs") as arena:
        vehicles = [arena.vehicle(n) for n in names]
        wait_until(
            lambda: all(v.state and v.link and v.state.vis_fused and v.state.setup_ok for v in vehicles),
            timeout,
            f"{', '.join(names)} ready (link, setup, vision fused)",
            interval=0.5,
            check=up.running,
        )


@pytest.fixture
def typed(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    with commands(tmp_path) as start:
        yield start


@pytest.fixture
def program(tmp_path: Path) -> Iterator[Callable[..., Program]]:
    with programs(tmp_path) as start:
        yield start


def _all_stopped(up: Command, tmp_path: Path) -> None:
    """Ctrl-C ends ``arena up`` with status 0, every service stopped, nothing left."""
    assert stops_cleanly(up, [str(tmp_path)]) == 0, up.output()
    assert re.search(r"^\[arena\] all stopped$", up.output(), re.M), up.output()


# -- README: make run, in a real terminal ----------------------------------------------------------------------

ANSI = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b[()][0-9A-Za-z]|\x1b[=>78]|\r")


class Terminal:
    """``argv`` in a real pseudo-terminal: its own session with the terminal as its controlling one (a
    shell's foreground job); what it shows is kept; :meth:`type` is the keyboard."""

    def __init__(self, argv: Sequence[str], cwd: Path, env: dict[str, str], rows: int = 60, cols: int = 200):
        master, slave = os.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
        job = _as_a_terminal_job(os.getpid())

        def setup() -> None:
            job()
            fcntl.ioctl(0, termios.TIOCSCTTY, 0)  # the pty is this session's terminal: ^C reaches the job

        self.popen = subprocess.Popen(
            list(argv),
            cwd=cwd,
            env=env,
            stdin=slave,
            stdout=slave,
            stderr=slave,
            start_new_session=True,
            preexec_fn=setup,
        )
        os.close(slave)
        self.master = master
        self.raw = bytearray()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                chunk = os.read(self.master, 65536)
            except OSError as exc:  # EIO: every process holding the terminal has gone
                if exc.errno != errno.EIO:
                    raise
                return
            if not chunk:
                return
            self.raw += chunk

    def text(self) -> str:
        """What it showed, escape sequences removed."""
        return ANSI.sub("", bytes(self.raw).decode(errors="replace"))

    def type(self, keys: bytes) -> None:
        os.write(self.master, keys)

    def close(self) -> None:
        if self.popen.poll() is None:
            try:
                os.killpg(self.popen.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.popen.wait(10)
        self._reader.join(5)
        os.close(self.master)


def checkout_for_make(tmp_path: Path) -> Path:
    """A directory where ``make`` finds this checkout's Makefile and .venv, so that what ``make run``
    writes (``arena-demo.log``) lands beside the test's config and never in the checkout."""
    here = tmp_path / "checkout"
    here.mkdir()
    for name in ("Makefile", "pyproject.toml", ".venv"):
        (here / name).symlink_to(REPO / name)
    return here


def _make_env() -> dict[str, str]:
    drop = ("ARENA_CONFIG", "ARENA_HOST", "MAKEFLAGS", "MFLAGS", "MAKELEVEL", "NO_COLOR")
    return {**{k: v for k, v in os.environ.items() if k not in drop}, "TERM": "xterm-256color"}


@pytest.mark.system
@pytest.mark.timeout(400)
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
@pytest.mark.covers("make run")
def test_make_run_flies_in_a_terminal_and_ctrl_c_lands_before_the_arena_stops(tmp_path: Path) -> None:
    cfg = free_ports_config(REPO / "deploy/sim.toml", tmp_path / "sim.toml")
    here = checkout_for_make(tmp_path)
    dry = subprocess.run(
        ["make", "-n", "run", f"CONFIG={cfg}"],
        cwd=here,
        env=_make_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert dry.returncode == 0, dry
    if dry.stdout.strip() != f".venv/bin/arena demo {cfg}":
        pytest.skip(f"make run would first set up .venv (run `make setup`):\n{dry.stdout}")
    term = Terminal(["make", "run", f"CONFIG={cfg}"], here, _make_env())
    try:
        # The live status table, with the vehicles in the air.
        try:
            wait_for(
                lambda: "formation step 1/6" in term.text() or term.popen.poll() is not None,
                timeout=FLYING_S,
                interval=0.5,
                what="the formation flying on the terminal",
            )
        except TimeoutError as exc:
            log = here / "arena-demo.log"
            tail = log.read_text(errors="replace")[-6000:] if log.exists() else "(no arena-demo.log)"
            raise AssertionError(
                f"{exc}\n--- terminal\n{term.text()[-4000:]}\n--- arena-demo.log\n{tail}"
            ) from None
        assert term.popen.poll() is None, term.text()[-5000:]
        shown = term.text()
        for name in ("d1", "d2", "d3"):
            assert re.search(rf"│ {name}\s+│ ok", shown), f"{name} not live in the table:\n{shown[-5000:]}"
        term.type(b"\x03")  # Ctrl-C: the terminal sends SIGINT to make and the demo (its foreground job)
        try:
            status = term.popen.wait(LANDED_S)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"make still running {LANDED_S:g} s after Ctrl-C:\n{term.text()[-5000:]}"
            ) from None
        term._reader.join(10)
        out = term.text()
        # make waits for the demo (which exits 0 after landing), then ends itself by the SIGINT it got (a
        # shell's status 130, make's "Interrupt").
        assert status == -signal.SIGINT, f"make ended with {status}:\n{out[-5000:]}"
        assert "stopping (SIGINT): every vehicle lands, then the arena stops" in out, out[-5000:]
        landed = out.find("landed: d1, d2, d3")
        stopping = out.find("stopping the arena", landed)
        assert 0 <= landed < stopping, f"not landed before the arena stopped:\n{out[-5000:]}"
        assert "arena stopped (supervisor 0)" in out, out[-5000:]
        wait_for(
            lambda: not leftovers([str(tmp_path)]), timeout=15, interval=0.2, what="nothing of make run left"
        )
    finally:
        term.close()
        kill_leftovers([str(tmp_path)])


# -- README: arena up, then a program against it ----------------------------------------------------------------


@pytest.mark.system
@pytest.mark.timeout(420)
@pytest.mark.covers(
    "arena up deploy/sim.toml --host sim", "python examples/formation.py --config deploy/sim.toml"
)
def test_arena_up_then_the_formation_example(
    tmp_path: Path, typed: Callable[..., Command], program: Callable[..., Program]
) -> None:
    cfg = free_ports_config(REPO / "deploy/sim.toml", tmp_path / "sim.toml")
    up = typed("up", str(cfg), "--host", "sim")
    up.wait_line(r"^\[arena\] host sim: starting ")
    wait_ready(cfg, ["d1", "d2", "d3"], up)
    example = program([str(PYTHON), "examples/formation.py", "--config", str(cfg)], cwd=REPO)
    code = example.exits_within(240)
    assert code == 0, example.output()
    steps = [line for line in example.lines if line.startswith("formation step ")]
    assert [s.split(":")[0] for s in steps] == [f"formation step {i}" for i in range(4)], example.output()
    assert all(name in steps[-1] for name in ("d1", "d2", "d3")), example.output()
    up.running()
    _all_stopped(up, tmp_path)


def _px4_instances(n: int) -> list[int]:
    """``n`` free PX4 SITL instances from the top (tests/px4's pool hands them out from 0 up; the typed
    harness's x8 takes 9 down)."""
    free = [i for i in range(8, -1, -1) if not instance_busy(i)]
    if len(free) < n:
        pytest.skip(f"fewer than {n} free PX4 SITL instances on this machine")
    return free[:n]


def _checks_pass(instance: int) -> bool:
    try:
        return is_true(listener(instance, "vehicle_status"), "pre_flight_checks_pass")
    except Px4SitlError:  # not answering yet
        return False


@pytest.mark.px4
@pytest.mark.system
@pytest.mark.timeout(600)
@pytest.mark.skipif(build_missing_reason() is not None, reason=f"PX4 SITL: {build_missing_reason()}")
@pytest.mark.covers(
    "arena up deploy/px4-sitl.toml", "python examples/hover_land.py --config deploy/px4-sitl.toml"
)
def test_arena_up_px4_sitl_then_hover_and_land(
    tmp_path: Path, typed: Callable[..., Command], program: Callable[..., Program]
) -> None:
    instances = _px4_instances(2)
    cfg = free_ports_config(
        REPO / "deploy/px4-sitl.toml", tmp_path / "px4-sitl.toml", px4_instances=instances
    )
    env = {k: os.environ[k] for k in ("PX4_SITL_DIR",) if k in os.environ}
    up = typed("up", str(cfg), env=env)  # one host in the config: no --host needed
    up.wait_line(r"^\[arena\] host sitl: starting ")
    wait_ready(cfg, ["d1", "d2"], up, timeout=300)
    # And PX4's own pre-flight checks passed (they lag the arena's view by a second or two; tests/px4 waits
    # for them the same way): what a reader sees as "Ready for takeoff" before typing the example.
    wait_until(
        lambda: _checks_pass(instances[0]),
        120,
        "d1: PX4's pre-flight checks to pass",
        interval=0.5,
        check=up.running,
    )
    example = program([str(PYTHON), "examples/hover_land.py", "--config", str(cfg)], cwd=REPO, env=env)
    code = example.exits_within(240)
    assert code == 0, example.output()
    assert re.search(r"^d1 hovering at ", example.output(), re.M), example.output()
    up.running()
    _all_stopped(up, tmp_path)


# -- docs/lab.md: checking a lab -------------------------------------------------------------------------------

# How a command names the config: as docs/lab.md types it ($ARENA_CONFIG set), -c after the sub-command,
# -c before it.
FORMS = ["ARENA_CONFIG", "-c after", "-c before"]


def _lab_args(form: str, cfg: Path, *args: str) -> tuple[list[str], dict[str, str]]:
    if form == "ARENA_CONFIG":
        return list(args), {"ARENA_CONFIG": str(cfg)}
    if form == "-c after":
        return [args[0], "-c", str(cfg), *args[1:]], {}
    return ["-c", str(cfg), *args], {}


@pytest.mark.system
@pytest.mark.timeout(360)
@pytest.mark.covers("arena status", "arena echo 'arena/sys/clock/**' -n 5", "arena arm c1")
def test_checking_a_lab(tmp_path: Path, typed: Callable[..., Command]) -> None:
    cfg = lab_config(tmp_path)
    up = typed("up", str(cfg), "--host", "ground")
    up.wait_line(r"^\[arena\] host ground: starting ")
    wait_ready(cfg, ["c1"], up)
    wide = {"COLUMNS": "200"}
    for form in FORMS:
        args, env = _lab_args(form, cfg, "status")
        status = typed(*args, env={**env, **wide})
        assert status.exits_within(60) == 0, f"{form}: {status.output()}"
        out = status.output()
        for service in (
            "router",
            "mocap",
            "transform",
            "sim-motive",
            "sim-vehicle",
            "gateway.c1",
            "downsampler.c1",
        ):
            assert re.search(rf"│ ground\s+│ {re.escape(service)}\s", out), f"{form}: no {service}:\n{out}"
        assert re.search(r"│ c1\s+│ ok", out), f"{form}: c1 not listed with its link:\n{out}"
        assert "clocks" in out, f"{form}: no clocks table:\n{out}"

        args, env = _lab_args(form, cfg, "echo", "arena/sys/clock/**", "-n", "5")
        echo = typed(*args, env=env)
        assert echo.exits_within(60) == 0, f"{form}: {echo.output()}"
        lines = [line for line in echo.lines if line.strip()]
        assert len(lines) == 5, f"{form}: {echo.output()}"
        assert all(re.match(r"arena/sys/clock/\S+ \[ClockOffset\] ", line) for line in lines), echo.output()

        args, env = _lab_args(form, cfg, "arm", "c1")
        arm = typed(*args, env=env)
        code = arm.exits_within(60)
        # Armed, or refused because c1's clock cannot be trusted (docs/lab.md: refused with "clock: …").
        assert (code == 0 and "armed: c1 ok" in arm.output()) or "clock: " in arm.output(), (
            f"{form}: exit {code}:\n{arm.output()}"
        )
    up.running()
    _all_stopped(up, tmp_path)


# -- docs/viewer.md: arena view ----------------------------------------------------------------------------------


def _foxglove_client(port: int) -> dict[str, Any]:
    """Open the view as Foxglove does (loopback only); its first message, the server's info."""
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=20) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        first = ws.recv(timeout=20)
    info: dict[str, Any] = json.loads(first)
    return info


VIEWS = [
    pytest.param(["view"], True, id="arena view ($ARENA_CONFIG)"),
    pytest.param(["view", "--config", "{CFG}"], False, id="arena view --config"),
    pytest.param(
        ["view", "--address", "0.0.0.0", "--public"], True, id="arena view --address 0.0.0.0 --public"
    ),
]


@pytest.mark.covers(
    "arena view",
    "arena view --config deploy/sim.toml",
    "arena view --address 0.0.0.0 --port 8765 --public",
)
@pytest.mark.parametrize(("args", "by_env"), VIEWS)
def test_arena_view_serves_foxglove_and_stops_on_ctrl_c(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    typed: Callable[..., Command],
    args: list[str],
    by_env: bool,
) -> None:
    cfg = Typed(tmp_path, router_endpoint, px4=False)
    port = free_port()  # the docs' 8765 (the default) may be taken on a shared machine
    line = [a.replace("{CFG}", str(cfg.path)) for a in args] + ["--port", str(port)]
    view = typed(*line, env={"ARENA_CONFIG": str(cfg.path)} if by_env else None)
    address = "0.0.0.0" if "--public" in args else "127.0.0.1"
    view.wait_line(rf"^live 3D view on ws://{re.escape(address)}:{port} ")
    if "--public" in args:
        assert "warning: public view on 0.0.0.0: no login" in view.output(), view.output()
    assert bound("tcp", port), view.output()
    info = _foxglove_client(port)
    assert info.get("op") == "serverInfo", info
    bus = bus_factory()
    wait_for(lambda: "viewer" in alive_ids(bus), timeout=START_S, interval=0.2, what="the viewer's presence")
    assert stops_cleanly(view, [str(tmp_path)]) == 0, view.output()
    assert not bound("tcp", port)


@pytest.mark.covers("arena view --address 0.0.0.0 --port 8765 --public")
def test_arena_view_beyond_loopback_needs_public(tmp_path: Path, typed: Callable[..., Command]) -> None:
    cfg = Typed(tmp_path, f"tcp/127.0.0.1:{free_port()}", px4=False)
    port = free_port()
    view = typed("view", "--address", "0.0.0.0", "--port", str(port), "-c", str(cfg.path))
    assert view.exits_within(60) == 2, view.output()
    assert "error: --address 0.0.0.0:" in view.output() and "add --public" in view.output(), view.output()
    assert not bound("tcp", port)


# -- docs/performance.md: the bench -------------------------------------------------------------------------------
#
# `python -m bench` runs from the checkout (the bench package is not installed); here it runs in the test's
# directory with the checkout on PYTHONPATH, so that what it writes by default (bench-results/,
# docs/performance.md) lands in the test's directory: the command line is the documented one, the checkout
# is never written.  Each runs as documented plus the options that shorten it (fewer seconds per point, no
# CPU hogs), named where they are appended.

SHORT = ["--duration", "1", "--warmup", "0.5", "--overload", "0"]  # the documented command, shorter


def _bench_dir(tmp_path: Path) -> Path:
    work = tmp_path / "bench"
    (work / "docs").mkdir(parents=True)
    shutil.copy(REPO / "docs/performance.md", work / "docs/performance.md")
    return work


def _bench_env() -> dict[str, str]:
    return {
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
        "COLUMNS": "200",
    }


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else ""


@pytest.fixture
def checkout_untouched() -> Iterator[None]:
    """The checkout's docs/performance.md and bench-results/ are as they were."""
    docs = _digest(REPO / "docs/performance.md")
    results = (
        sorted(p.name for p in (REPO / "bench-results").glob("*"))
        if (REPO / "bench-results").exists()
        else []
    )
    latest = _digest(REPO / "bench-results/latest.json")
    yield
    assert _digest(REPO / "docs/performance.md") == docs, (
        "the bench wrote docs/performance.md of the checkout"
    )
    after = (
        sorted(p.name for p in (REPO / "bench-results").glob("*"))
        if (REPO / "bench-results").exists()
        else []
    )
    assert after == results and _digest(REPO / "bench-results/latest.json") == latest, (
        "the bench wrote bench-results/"
    )


def _bench(program: Callable[..., Program], work: Path, *args: str, timeout: float = 300) -> Program:
    run = program([str(PYTHON), "-m", "bench", *args], cwd=work, env=_bench_env())
    code = run.exits_within(timeout)
    assert code == 0, run.output()
    return run


@pytest.mark.system
@pytest.mark.timeout(600)
@pytest.mark.usefixtures("checkout_untouched")
@pytest.mark.covers("python -m bench --quick", "python -m bench --from bench-results/latest.json")
def test_bench_quick_then_rerendered_from_its_result(tmp_path: Path, program: Callable[..., Program]) -> None:
    work = _bench_dir(tmp_path)
    docs_before = (work / "docs/performance.md").read_text()
    # --quick, with one vehicle count (of 1 and 10) and shorter points.
    quick = _bench(program, work, "--quick", "--vehicles", "1", *SHORT, "--peer-duration", "0.5")
    assert re.search(r"^result: bench-results/bench-\S+\.json \(\d+ s\)$", quick.output(), re.M), (
        quick.output()
    )
    stored = json.loads((work / "bench-results/latest.json").read_text())
    assert stored["options"]["quick"] is True
    chains = {p["chain"] for p in stored["points"]}
    assert {"arena", "arena-td", "floor-zenoh", "floor-udp"} <= chains, chains
    assert all(p["delivered"] > 0 for p in stored["points"]), stored["points"]
    assert stored["peer"]["gateway"]["forwarded"] > 0 and stored["micro"]
    assert (work / "docs/performance.md").read_text() == docs_before  # --quick leaves the page alone

    # As documented, verbatim: the tables again, from the stored result, and into the page.
    rerendered = _bench(program, work, "--from", "bench-results/latest.json", timeout=120)
    assert "End-to-end latency" in rerendered.output() and "Targets" in rerendered.output(), (
        rerendered.output()
    )
    page = (work / "docs/performance.md").read_text()
    assert page != docs_before and page.count("<!-- bench:begin") == 1, page[-3000:]


@pytest.mark.system
@pytest.mark.timeout(400)
@pytest.mark.usefixtures("checkout_untouched")
@pytest.mark.covers("python -m bench -p pipeline -n 1 -r 180 --hops")
def test_bench_pipeline_with_hops(tmp_path: Path, program: Callable[..., Program]) -> None:
    work = _bench_dir(tmp_path)
    run = _bench(program, work, "-p", "pipeline", "-n", "1", "-r", "180", "--hops", *SHORT)
    out = run.output()
    assert "Per stage, first vehicle" in out, out
    assert "tables written into docs/performance.md" in out, out  # the test's copy (its working directory)
    stored = json.loads((work / "bench-results/latest.json").read_text())
    assert {p["vehicles"] for p in stored["points"]} == {1} and {p["rate"] for p in stored["points"]} == {
        180.0
    }
    assert any(p.get("hops") for p in stored["points"]), stored["points"]


def _pyspy() -> str | None:
    local = PYTHON.parent / "py-spy"
    return str(local) if local.exists() else shutil.which("py-spy")


@pytest.mark.system
@pytest.mark.timeout(600)
@pytest.mark.usefixtures("checkout_untouched")
@pytest.mark.covers("python -m bench -p pipeline -n 20 -r 180 --profile")
def test_bench_profile(tmp_path: Path, program: Callable[..., Program]) -> None:
    """Without py-spy (the bench extra, which make bench installs) the documented line says so and exits
    2 before starting anything; with it, it runs (one vehicle instead of 20, shorter) and writes the
    profiles."""
    work = _bench_dir(tmp_path)
    argv = ["-p", "pipeline", "-n", "20", "-r", "180", "--profile"]
    if _pyspy() is None:
        run = program([str(PYTHON), "-m", "bench", *argv], cwd=work, env=_bench_env())
        assert run.exits_within(120) == 2, run.output()
        assert "error: --profile needs py-spy (pip install py-spy)" in run.output(), run.output()
        assert not leftovers([str(work)])
        return
    _bench(program, work, *argv, "-n", "1", *SHORT, "--decimate", "transform")  # -n 1: the later -n wins
    assert list((work / "bench-results").glob("profile-*/*.txt")), "no py-spy profile written"


@pytest.mark.system
@pytest.mark.timeout(600)
@pytest.mark.usefixtures("checkout_untouched")
@pytest.mark.covers("python -m bench -p peer --peer-repeats 5")
def test_bench_peer(tmp_path: Path, program: Callable[..., Program]) -> None:
    work = _bench_dir(tmp_path)
    run = _bench(program, work, "-p", "peer", "--peer-repeats", "5", "--peer-duration", "0.5")  # shorter runs
    assert "Gateway vs its floors and MAVProxy" in run.output(), run.output()
    peer = json.loads((work / "bench-results/latest.json").read_text())["peer"]
    for name in ("gateway", "floor-zenoh", "floor-udp"):
        assert peer[name]["repeats"] == 5 and peer[name]["forwarded"] > 0, peer[name]
    assert "forwarded" in peer["mavproxy"] or "unavailable" in peer["mavproxy"], peer["mavproxy"]


@pytest.mark.covers("python -m bench.flames docs/profiles/before docs/profiles/after --seconds 10")
def test_bench_flames_of_the_stored_profiles(program: Callable[..., Program]) -> None:
    """It only reads the profiles: run in the checkout, verbatim."""
    run = program(
        [str(PYTHON), "-m", "bench.flames", "docs/profiles/before", "docs/profiles/after", "--seconds", "10"],
        cwd=REPO,
    )
    assert run.exits_within(60) == 0, run.output()
    for service in ("ingest", "transform", "gateway.d1"):
        for label in ("before", "after"):
            assert re.search(rf"^\|\s*{re.escape(service)}\s*\|\s*{label}\s*\|", run.output(), re.M), (
                run.output()
            )


@pytest.mark.system
@pytest.mark.covers("make bench")
def test_make_bench(tmp_path: Path) -> None:
    """What ``make bench`` runs: the bench extra installed into .venv, then the whole bench.  Neither is
    done by a test: the install changes the shared .venv (and needs the network), and a full run takes
    minutes and rewrites docs/performance.md and bench-results/ of the checkout; the recipe is checked and
    the run is left to `python -m bench` above."""
    here = checkout_for_make(tmp_path)
    dry = subprocess.run(
        ["make", "-n", "bench"], cwd=here, env=_make_env(), capture_output=True, text=True, timeout=60
    )
    assert dry.returncode == 0, dry
    assert dry.stdout.strip().splitlines()[-2:] == [
        ".venv/bin/python -m pip install -q -e '.[bench]'",
        ".venv/bin/python -m bench",
    ], dry.stdout
    missing = [tool for tool in ("py-spy", "mavproxy.py") if not (PYTHON.parent / tool).exists()]
    pytest.skip(
        "make bench is not run here: it pip-installs the bench extra into the shared .venv"
        + (f" ({', '.join(missing)} missing)" if missing else "")
        + " and a full run rewrites the checkout's docs/performance.md and bench-results/"
    )
