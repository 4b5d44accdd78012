"""Fixtures of the real-PX4 tier: PX4 SITL instances, the arena's services in front of them, the client.

Everything under ``tests/px4`` is marked ``px4`` and runs with ``make test-px4`` (``pytest -m px4
tests/px4``), or when the command line names a path under ``tests/px4``; a plain ``pytest`` (``make
test``) deselects it, and it is skipped, with the reason, when no PX4 SITL build is found
(``$PX4_SITL_DIR``, else ``../shared/px4-sitl``).  Instances are taken from 0..9, never one that is
running on the machine.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO

import pytest

from arena_common import Arena
from arena_common.client import Vehicle
from arena_common.runtime.px4_sitl import Px4Sitl, build_missing_reason, is_true
from tests.conftest import wait_for
from tests.px4.harness import InstancePool, Px4Stack, px4_stack, write_px4_config

HERE = Path(__file__).resolve().parent
TIMEOUT_S = 300


def _asked_for(config: pytest.Config) -> bool:
    """True when this run asks for the PX4 tier: ``-m`` names px4, or an argument lies in tests/px4."""
    if "px4" in (config.option.markexpr or ""):
        return True
    for arg in config.args:
        path = Path(config.invocation_params.dir, arg.split("::", 1)[0]).resolve()
        if path == HERE or HERE in path.parents:
            return True
    return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the tier's tests ``px4`` (with a longer timeout), deselect them unless asked, skip them
    when there is no PX4 build."""
    ours = [item for item in items if HERE in Path(str(item.path)).resolve().parents]
    if not ours:
        return
    if not _asked_for(config):
        config.hook.pytest_deselected(items=ours)
        items[:] = [item for item in items if item not in ours]
        return
    reason = build_missing_reason()
    for item in ours:
        item.add_marker(pytest.mark.px4)
        if item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(TIMEOUT_S))
        if reason is not None:
            item.add_marker(pytest.mark.skip(reason=f"PX4 SITL tier: {reason}"))


@pytest.fixture(scope="session")
def px4_pool() -> InstancePool:
    """The session's PX4 SITL instance numbers (0..9)."""
    return InstancePool()


@pytest.fixture
def px4_instance(px4_pool: InstancePool) -> Iterator[int]:
    """A PX4 SITL instance number no other test and no running px4 uses."""
    n = px4_pool.take()
    try:
        yield n
    finally:
        px4_pool.give_back(n)


@pytest.fixture
def px4_sitl(px4_instance: int, tmp_path: Path) -> Iterator[Callable[..., Px4Sitl]]:
    """Start a bare PX4 SITL instance: ``px4_sitl(params={...})`` → a ready :class:`Px4Sitl`, stopped
    at the end of the test (its output in ``tmp_path/px4.log``)."""
    started: list[Px4Sitl] = []
    logs: list[IO[str]] = []

    def make(params: Mapping[str, float] | None = None) -> Px4Sitl:
        log = open(tmp_path / "px4.log", "a", encoding="utf-8")  # noqa: SIM115 - closed at the end
        logs.append(log)

        def write(line: str) -> None:
            log.write(line + "\n")
            log.flush()

        px4 = Px4Sitl(px4_instance, params=params, output=write)
        started.append(px4)
        px4.start()
        px4.wait_ready()
        return px4

    yield make
    for px4 in started:
        px4.stop()
    for log in logs:
        log.close()


PX4ArenaFactory = Callable[..., tuple[Px4Stack, Arena]]


@pytest.fixture
def px4_arena(px4_pool: InstancePool, tmp_path: Path, router_endpoint: str) -> Iterator[PX4ArenaFactory]:
    """Bring up PX4 SITL vehicles and the arena's services for them, with a client on the bus.

    ``px4_arena(vehicles=("d1",), preset="arena", px4_params=None)`` → ``(stack, arena)`` once every
    vehicle's gateway reports its link and, when ``fused`` (default: with the "arena" preset), vision
    fused, setup verified and PX4's own pre-flight checks passed.  ``require_setup`` false lets the
    gateways arm a PX4 whose parameters differ from the arena's; ``keep_log`` keeps PX4's ULog
    (:meth:`Px4Stack.ulog`); ``simulated`` flies the same config's vehicles on the arena's simulated
    autopilot instead, as the parity tier compares them; ``links`` puts a slow link (delay, jitter: seconds
    each way) between a vehicle's PX4 and its gateway (:class:`~arena_common.sim.linkdelay.LinkDelay`).
    Everything stops at the end of the test; logs stay in ``tmp_path``.
    """
    taken: list[int] = []
    stacks: list[tuple[Px4Stack, Arena]] = []
    closers: list[Callable[[], object]] = []

    def make(
        vehicles: Sequence[str] = ("d1",),
        preset: str = "arena",
        px4_params: Mapping[str, Mapping[str, float]] | None = None,
        ready_timeout: float = 90.0,
        require_setup: bool = True,
        fused: bool | None = None,
        keep_log: bool = False,
        simulated: bool = False,
        links: Mapping[str, tuple[float, float]] | None = None,
    ) -> tuple[Px4Stack, Arena]:
        if fused is None:
            fused = preset == "arena"
        instances = {}
        for name in vehicles:
            instances[name] = -1 if simulated else px4_pool.take()
            if not simulated:
                taken.append(instances[name])
        cfg = write_px4_config(
            tmp_path / f"arena{len(stacks)}.toml",
            router_endpoint,
            instances,
            preset=preset,
            px4_params=px4_params,
            require_setup=require_setup,
            simulated=simulated,
        )
        cm = px4_stack(cfg, tmp_path, keep_log=keep_log, links=links)
        stack = cm.__enter__()
        closers.append(lambda: cm.__exit__(None, None, None))
        arena = Arena(cfg, name="px4-tier")
        closers.append(arena.close)
        stacks.append((stack, arena))
        if not simulated:
            print(
                f"\nPX4 SITL {instances} booted in " + ", ".join(f"{s:.2f} s" for s in stack.boot_s.values())
            )
        print(f"logs: {tmp_path}")
        for name in vehicles:
            v = arena.vehicle(name)

            def ready(v: Vehicle = v) -> bool:
                state = v.state
                return v.link and (not fused or bool(state and state.vis_fused and state.setup_ok))

            wait_for(
                ready,
                timeout=ready_timeout,
                interval=0.2,
                what=f"{name}: link" + (", vision fused and setup verified" if fused else ""),
            )
            # and PX4 itself ready to arm (its checks lag the arena's view by a second or two)
            if fused and not simulated:

                def checks_pass(px4: Px4Sitl = stack.px4[name]) -> bool:
                    return is_true(px4.listener("vehicle_status"), "pre_flight_checks_pass")

                wait_for(
                    checks_pass,
                    timeout=ready_timeout,
                    interval=0.2,
                    what=f"{name}: PX4's pre-flight checks to pass",
                )
        return stack, arena

    yield make
    for close in reversed(closers):
        close()
    for n in taken:
        px4_pool.give_back(n)
