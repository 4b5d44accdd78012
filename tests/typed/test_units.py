"""The systemd units, run as systemd runs them: ``arena deploy systemd CONFIG --host NAME --prefix DIR``
(typed) renders them for a config of free ports; each unit's ``ExecStart`` is filled in as systemd fills
it (``${ARENA_CONFIG}`` and ``${ARENA_HOST}`` from the generated ``etc/arena/arena.env``, ``%i`` the
vehicle), started in its working directory with the unit's environment, in a session of its own; it must
declare its presence (``arena/sys/alive/<host>/<service>``) on the config's router (the router unit,
started first) and log what it serves; SIGTERM (what ``systemctl stop`` sends) must end it with status 0
within the unit's ``TimeoutStopSec``, nothing of it left running.

``systemd-analyze verify`` of the same units is tests/unit/cli/test_systemd.py's.
"""

from __future__ import annotations

import re
import shlex
import signal
import socket
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from arena_common.bus.session import Bus, open_bus
from arena_common.core.config import ZenohSpec
from arena_common.core.waiting import wait_until
from tests.helpers import REPO, free_port, wait_for
from tests.typed.harness import START_S, Command, Program, leftovers, programs

HOST = "ground"
VEHICLE = "x7"
UNIT_DIR = "etc/systemd/system"

#: Every unit of deploy/systemd that starts something (what tools/typed.py lists as ``unit NAME``).
UNITS_WITH_EXEC = sorted(
    p.name for p in (REPO / "deploy" / "systemd").glob("*.service") if "ExecStart=" in p.read_text()
)


@dataclass(frozen=True)
class Ground:
    """A config whose host ``ground`` runs every service, and vehicle x7's downsampler and gateway."""

    path: Path
    endpoint: str
    command_port: int
    x7_port: int
    rec_dir: Path

    @classmethod
    def write(cls, directory: Path) -> Ground:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        command_port = free_port(socket.SOCK_DGRAM)
        data_port = free_port(socket.SOCK_DGRAM)
        x7_port = free_port(socket.SOCK_DGRAM)
        rec_dir = directory / "rec"
        path = directory / "ground.toml"
        path.write_text(
            "\n".join(
                [
                    "[arena]",
                    'name = "units"',
                    "[mocap]",
                    f"command_port = {command_port}",
                    f"data_port = {data_port}",
                    'server = "127.0.0.1"',
                    'interface = "127.0.0.1"',
                    "multicast = false",
                    "[zenoh]",
                    'mode = "peer"',
                    f'connect = ["{endpoint}"]',
                    f'router_listen = ["{endpoint}"]',
                    f"[hosts.{HOST}]",
                    'services = ["router", "sim", "mocap", "transform", "recorder", "ros2"]',
                    f'vehicles = ["{VEHICLE}"]',
                    'vehicle_services = ["downsampler", "gateway"]',
                    f"[vehicles.{VEHICLE}]",
                    f'rigid_body = "{VEHICLE}"',
                    f'mavlink = "udpin:127.0.0.1:{x7_port}"',
                    "system_id = 7",
                    "sim = { start = [0.0, 0.0] }",
                    "[recorder]",
                    f'directory = "{rec_dir}"',
                ]
            )
            + "\n"
        )
        return cls(path, endpoint, command_port, x7_port, rec_dir)


# unit → (presence id, a line its log must show); {cmd}, {x7}, {rec}, {endpoint} are the config's.
EXPECTED: dict[str, tuple[str, str]] = {
    "arena-router.service": ("router", r"arena\.router: routing on {endpoint}$"),
    "arena-sim-vehicle.service": ("sim-vehicle", r"simulating x7 \(sysid 7, udpout:127\.0\.0\.1:{x7}\)"),
    "arena-sim-motive.service": ("sim-motive", r"server on 127\.0\.0\.1:{cmd}"),
    "arena-mocap.service": ("mocap", r"source natnet \(server 127\.0\.0\.1:{cmd},"),
    "arena-transform.service": ("transform", r"arena\.transform: started \(host ground"),
    "arena-recorder.service": ("recorder", r"arena\.recorder: recording to {rec}/"),
    "arena-ros2.service": ("ros2", r"arena\.ros2: ROS 2 domain \d+, node /arena_bridge .*1 vehicle"),
    "arena-downsampler@.service": ("downsampler.x7", r"arena/x7/pose → arena/x7/vision"),
    "arena-gateway@.service": ("gateway.x7", r"gateway for x7: udpin:127\.0\.0\.1:{x7}, system 7"),
}


@dataclass(frozen=True)
class Unit:
    """One rendered unit: what systemd would run, where, with what environment, and its stop bound."""

    name: str
    argv: list[str]
    workdir: Path
    env: dict[str, str]
    stop_s: float
    pre: list[list[str]]


def _directives(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.lstrip().startswith(("#", ";", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def _env_file(path: Path) -> dict[str, str]:
    env = {}
    for line in path.read_text().splitlines():
        if "=" in line and not line.startswith("#"):
            key, value = line.split("=", 1)
            env[key.strip()] = value.strip()
    return env


def systemd_unit(root: Path, name: str, instance: str = VEHICLE) -> Unit:
    """Unit ``name`` as written under ``root``, its ``ExecStart`` filled in as systemd fills it."""
    directives = _directives((root / UNIT_DIR / name).read_text())
    env = _env_file(root / "etc" / "arena" / "arena.env")  # EnvironmentFile=/etc/arena/arena.env
    for assignment in directives.get("Environment", []):
        for word in shlex.split(assignment):
            key, value = word.split("=", 1)
            env[key] = value
    (start,) = directives["ExecStart"]
    line = start.replace("%i", instance) if "@" in name else start
    line = re.sub(r"\$\{(\w+)\}", lambda m: env[m[1]], line)
    assert "%" not in line and "$" not in line and "@" not in line, f"{name}: left unfilled: {line}"
    (stop,) = directives["TimeoutStopSec"]
    (workdir,) = directives["WorkingDirectory"]
    # ExecStartPre: a leading "+" (privileged), "-" (failure ignored) or "@" is systemd's, not the command's.
    pre = [shlex.split(p.lstrip("+-@!")) for p in directives.get("ExecStartPre", [])]
    return Unit(name, shlex.split(line), Path(workdir), env, float(stop), pre)


@pytest.fixture
def ground(tmp_path: Path) -> Ground:
    return Ground.write(tmp_path)


@pytest.fixture
def rendered(tmp_path: Path, ground: Ground) -> Path:
    """``arena deploy systemd CONFIG --host ground --prefix DIR``, typed: the install root it wrote."""
    root = tmp_path / "root"
    cmd = Command(["deploy", "systemd", str(ground.path), "--host", HOST, "--prefix", str(root)], tmp_path)
    try:
        code = cmd.exits_within(60)
    finally:
        cmd.kill()
    assert code == 0, cmd.output()
    written = {p.name for p in (root / UNIT_DIR).glob("*.service")}
    assert written == set(UNITS_WITH_EXEC), cmd.output()  # the ground host gets every unit
    assert f"wrote {root / 'etc/arena/arena.env'}" in cmd.output()
    env = _env_file(root / "etc/arena/arena.env")
    assert env == {"ARENA_CONFIG": str(ground.path.resolve()), "ARENA_HOST": HOST}
    return root


@pytest.fixture
def start(tmp_path: Path) -> Iterator[Callable[..., Program]]:
    with programs(tmp_path) as run:
        yield run


@pytest.fixture
def bus(ground: Ground) -> Iterator[Callable[[], Bus]]:
    """A peer session on the config's router (opened once the router unit runs)."""
    opened: list[Bus] = []

    def make() -> Bus:
        if not opened:
            opened.append(open_bus(ZenohSpec(mode="peer", connect=(ground.endpoint,))))
        return opened[0]

    yield make
    for b in opened:
        b.close()


def _alive(bus: Bus) -> set[str]:
    return set(bus.alive(f"arena/sys/alive/{HOST}/*", 0.5))


def _runs(
    unit: Unit, ground: Ground, start: Callable[..., Program], bus: Callable[[], Bus], tmp_path: Path
) -> Program:
    """Start ``unit`` as systemd does; wait for its log line and its presence on the router."""
    service, line = EXPECTED[unit.name]
    for argv in unit.pre:  # ExecStartPre, in order: each must succeed (the recorder's directory)
        res = subprocess.run(argv, cwd=unit.workdir, capture_output=True, text=True, timeout=30)
        assert res.returncode == 0, f"{unit.name}: ExecStartPre {argv} failed: {res}"
    proc = start(unit.argv, cwd=unit.workdir, env=unit.env)
    pattern = line.format(
        endpoint=re.escape(ground.endpoint),
        cmd=ground.command_port,
        x7=ground.x7_port,
        rec=re.escape(str(ground.rec_dir)),
    )
    proc.wait_line(pattern, timeout=START_S)
    key = f"arena/sys/alive/{HOST}/{service}"
    wait_until(lambda: key in _alive(bus()), START_S, f"presence {key}", interval=0.2, check=proc.running)
    return proc


def _stops_on_sigterm(unit: Unit, proc: Program, tmp_path: Path) -> None:
    """SIGTERM (systemctl stop): status 0 within TimeoutStopSec, nothing of it left."""
    proc.signal(signal.SIGTERM)
    code = proc.exits_within(unit.stop_s)
    assert code == 0, f"{unit.name} exited {code} on SIGTERM:\n{proc.output()}"
    wait_for(
        lambda: not leftovers([], proc.pid),
        timeout=10,
        interval=0.1,
        what=f"no process of {unit.name} left",
    )


@pytest.mark.covers(
    "arena deploy systemd",
    "unit arena-router.service",
    "unit arena-mocap.service",
    "unit arena-transform.service",
    "unit arena-recorder.service",
    "unit arena-downsampler@.service",
    "unit arena-gateway@.service",
    "unit arena-sim-vehicle.service",
    "unit arena-sim-motive.service",
    "unit arena-ros2.service",
)
@pytest.mark.timeout(180)
@pytest.mark.parametrize("name", UNITS_WITH_EXEC)
def test_each_unit_starts_as_systemd_runs_it_and_stops_on_sigterm(
    tmp_path: Path,
    ground: Ground,
    rendered: Path,
    start: Callable[..., Program],
    bus: Callable[[], Bus],
    name: str,
) -> None:
    assert name in EXPECTED, f"{name}: a new unit; say what it serves in EXPECTED"
    router = systemd_unit(rendered, "arena-router.service")
    router_proc = _runs(router, ground, start, bus, tmp_path)
    if name != router.name:
        unit = systemd_unit(rendered, name)
        if "@" in name:
            assert unit.argv[unit.argv.index("--vehicle") + 1] == VEHICLE
        assert unit.argv[unit.argv.index("--config") + 1] == str(ground.path.resolve())
        assert unit.argv[unit.argv.index("--host") + 1] == HOST
        proc = _runs(unit, ground, start, bus, tmp_path)
        _stops_on_sigterm(unit, proc, tmp_path)
        service = EXPECTED[name][0]
        wait_for(
            lambda: f"arena/sys/alive/{HOST}/{service}" not in _alive(bus()),
            timeout=START_S,
            interval=0.2,
            what=f"{service}'s presence gone",
        )
    _stops_on_sigterm(router, router_proc, tmp_path)
    assert not leftovers([str(tmp_path)]), "a process of the units is still running"


def test_every_unit_with_a_command_is_covered() -> None:
    """A new unit in deploy/systemd needs its line in EXPECTED (what it serves, what it logs)."""
    assert set(UNITS_WITH_EXEC) == set(EXPECTED)
