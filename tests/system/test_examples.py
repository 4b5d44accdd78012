"""The user's side against a whole simulated arena brought up by ``arena up`` (private ports).

Every example flies and ends where it should; a user program killed with SIGKILL mid-flight leaves its
vehicle to land by itself; ``arena status`` from a second process shows the whole running system.
"""

from __future__ import annotations

import asyncio
import importlib.util
import math
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from arena_common import Arena
from tests.helpers import REPO, free_port, wait_for, write_config

pytestmark = [pytest.mark.system, pytest.mark.timeout(300)]
VEHICLES = ("d1", "d2", "d3")


def _example(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"example_{name}", REPO / "examples" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def sim_arena(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Arena]]:
    tmp = tmp_path_factory.mktemp("arena")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # The examples' figures are judged on exact vehicles (PX4's wander: tests/unit/sim/test_sim_px4_parity.py).
    path = write_config(
        tmp, endpoint, n_vehicles=3, services=("router", "sim", "mocap", "transform"), fidelity="ideal"
    )
    log = open(tmp / "arena.log", "wb")  # noqa: SIM115 - closed in the finally below
    up = subprocess.Popen(
        [sys.executable, "-m", "arena_common.cli", "up", str(path), "--host", "test"],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=REPO,
    )
    arena: Arena | None = None
    try:
        arena = Arena(path, name="test-examples")
        vs = [arena.vehicle(n) for n in VEHICLES]
        wait_for(
            lambda: all(v.state and v.link and v.state.vis_fused and v.state.setup_ok for v in vs),
            timeout=90,
            interval=0.2,
            what="three vehicles with vision fused",
        )
        yield path, arena
    finally:
        if arena is not None:
            arena.close()
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGINT)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait(5)
        log.close()


def _on_ground(arena: Arena, name: str) -> None:
    v = arena.vehicle(name)
    v.wait_until(lambda x: x.landed == "on_ground" and not x.armed, timeout=30, what="on the ground")


def test_hover_and_land(sim_arena: tuple[Path, Arena]) -> None:
    _, arena = sim_arena
    d1 = arena.vehicle("d1")
    start = d1.position
    assert start is not None
    _example("hover_land").main(arena, "d1", height=1.0, hover_s=1.0)
    _on_ground(arena, "d1")
    end = d1.position
    assert end is not None and math.dist(start[:2], end[:2]) < 0.15 and abs(end[2]) < 0.05


def test_square(sim_arena: tuple[Path, Arena]) -> None:
    _, arena = sim_arena
    d2 = arena.vehicle("d2")
    start = d2.position
    assert start is not None
    _example("square").main(arena, "d2", side=1.0)
    _on_ground(arena, "d2")
    end = d2.position
    assert end is not None and math.dist(start[:2], end[:2]) < 0.2


def test_velocity_controller(sim_arena: tuple[Path, Arena]) -> None:
    _, arena = sim_arena
    final = _example("velocity_controller").main(arena, "d3", target=(1.5, 0.8, -1.0), timeout=25)
    assert final < 0.2
    _on_ground(arena, "d3")
    p = arena.vehicle("d3").position
    assert p is not None and math.dist(p[:2], (1.5, 0.8)) < 0.25


def test_formation(sim_arena: tuple[Path, Arena]) -> None:
    _, arena = sim_arena
    mod = _example("formation")
    mod.main(arena, list(VEHICLES), radius=1.0, height=1.0, turns=3)
    final = mod.slots((0.0, 0.0), 1.0, 2 * math.pi / 3, 3)
    taken: set[int] = set()
    for name in VEHICLES:  # each in a slot of its own (which one: the clear assignment's choice)
        _on_ground(arena, name)
        p = arena.vehicle(name).position
        assert p is not None
        here = p[:2]
        k = min(range(3), key=lambda i: math.dist(here, final[i]))
        assert math.dist(p[:2], final[k]) < 0.25 and k not in taken, (name, p, final)
        taken.add(k)


def test_async_example(sim_arena: tuple[Path, Arena]) -> None:
    path, arena = sim_arena
    _on_ground(arena, "d1")
    modes = asyncio.run(
        _example("async_monitor").main(path, "d1", height=0.8, hover_s=1.0, name="test-async")
    )
    _on_ground(arena, "d1")
    # In order (it may start in AUTO.LAND, where the last landing left it): take off, offboard, land.
    assert modes[-1] == "AUTO.LAND" and "AUTO.TAKEOFF" in modes, modes
    assert modes.index("AUTO.TAKEOFF") < modes.index("OFFBOARD") < len(modes) - 1, modes


def test_status_from_a_second_process(sim_arena: tuple[Path, Arena]) -> None:
    path, _ = sim_arena
    out = subprocess.run(
        [sys.executable, "-m", "arena_common.cli", "status", "-c", str(path), "--wait", "1.5"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert out.returncode == 0, out.stderr
    for service in (
        "router",
        "sim-vehicle",
        "sim-motive",
        "mocap",
        "transform",
        "supervisor",
        *(f"gateway.{v}" for v in VEHICLES),
        *(f"downsampler.{v}" for v in VEHICLES),
    ):
        assert f" {service} " in out.stdout, service
    for v in VEHICLES:
        assert f" {v} " in out.stdout and "fused" in out.stdout


def test_user_program_killed_mid_flight_lands_by_itself(sim_arena: tuple[Path, Arena]) -> None:
    path, arena = sim_arena
    program = textwrap.dedent(f"""
        import sys, time
        from arena_common import Arena
        with Arena({str(path)!r}) as arena:
            d1 = arena.vehicle("d1")
            d1.wait_until(lambda v: v.position is not None, timeout=10)
            d1.arm()
            d1.takeoff(1.0)
            with d1.offboard() as ctl:
                ctl.position(0.0, 0.0, -1.2, yaw=0.0)
                print("flying", flush=True)
                time.sleep(120)
    """)
    user = subprocess.Popen([sys.executable, "-c", program], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert user.stdout is not None
        assert user.stdout.readline().strip() == "flying"
        d1 = arena.vehicle("d1")
        d1.wait_until(
            lambda v: v.mode == "OFFBOARD" and v.position is not None and v.position[2] < -1.0,
            timeout=20,
            what="hovering in offboard",
        )
        user.send_signal(signal.SIGKILL)
        user.wait(5)
        d1.wait_until(lambda v: v.mode != "OFFBOARD", timeout=5, what="offboard-loss failsafe")
        _on_ground(arena, "d1")
    finally:
        if user.poll() is None:
            user.kill()
            user.wait(5)


def test_readme_programs(sim_arena: tuple[Path, Arena]) -> None:
    """Every Python program in the README runs as written (config path aside) and flies."""
    path, arena = sim_arena
    text = (REPO / "README.md").read_text()
    blocks = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    assert len(blocks) >= 3
    for block in blocks:
        program = block.replace('"deploy/sim.toml"', repr(str(path)))
        run = subprocess.run(
            [sys.executable, "-c", program], capture_output=True, text=True, timeout=180, cwd=REPO
        )
        assert run.returncode == 0, (block, run.stderr)
    for name in VEHICLES:
        _on_ground(arena, name)
    p = arena.vehicle("d1").position
    assert p is not None and p[0] > 1.2  # the quick start flew north from the goto point at (1.0, -1.0)


def _arena_cli(path: Path, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arena_common.cli", *args, "-c", str(path)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
        env={**os.environ, "COLUMNS": "200"},
    )


def test_flight_commands_from_the_shell(sim_arena: tuple[Path, Arena]) -> None:
    path, arena = sim_arena
    for name in VEHICLES:
        _on_ground(arena, name)
    assert _arena_cli(path, "arm", "all").returncode == 0
    res = _arena_cli(path, "takeoff", "all", "0.8")
    assert res.returncode == 0, res.stderr
    assert "d1, d2, d3" in res.stdout
    res = _arena_cli(path, "goto", "d2", "0.5", "-0.5", "-1.0", "--yaw", "90")
    assert res.returncode == 0, res.stderr
    p = arena.vehicle("d2").position
    assert p is not None and math.dist(p, (0.5, -0.5, -1.0)) <= 0.15
    refused = _arena_cli(path, "goto", "d2", "9.0", "0.0", "-1.0")  # outside the 7 m room
    assert refused.returncode == 1 and "REFUSED" in refused.stderr
    top = _arena_cli(path, "top", "arena/*/vision", "--duration", "2.5")
    assert top.returncode == 0 and "arena/d1/vision" in top.stdout
    assert _arena_cli(path, "estop", "--reason", "test").returncode == 0
    for name in VEHICLES:
        _on_ground(arena, name)
    assert any(
        e.kind in ("failsafe", "safety", "command", "info") and "estop" in e.text.lower()
        for e in arena.vehicle("d1").events()
    ), [e.text for e in arena.vehicle("d1").events()]


def test_shell_errors_exit_non_zero(sim_arena: tuple[Path, Arena]) -> None:
    path, _ = sim_arena
    absent = _arena_cli(path, "arm", "d9", timeout=60)
    assert absent.returncode == 1 and "unknown vehicle 'd9': the config lists d1, d2, d3" in absent.stderr
    bad = _arena_cli(path, "goto", "d1", "north", "0", "0")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
