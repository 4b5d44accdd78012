"""Shared fixtures: a private Zenoh router per test, peer sessions on it, configs with their own endpoints,
child processes that stop with the test.  The helpers they use are in ``tests/helpers.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import config as config_mod
from arena_common.core.config import ArenaConfig, ZenohSpec
from tests.helpers import (
    PYTHON,
    REPO,
    TESTS,
    Proc,
    free_port,
    open_lab,
    service_argv,
    wait_for,
    write_config,
)

# The helpers, for the test modules that still import them from here.
__all__ = [
    "PYTHON",
    "REPO",
    "TESTS",
    "Proc",
    "free_port",
    "open_lab",
    "service_argv",
    "wait_for",
    "write_config",
]


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Callable[..., Proc]]:
    """Start child processes: ``processes("gateway", argv, env={...})``; logs in ``tmp_path``; every one
    still running is stopped (SIGINT, SIGKILL after 15 s) at the end of the test."""
    started: list[Proc] = []

    def start(name: str, argv: Sequence[str], env: Mapping[str, str] | None = None) -> Proc:
        proc = Proc(name, argv, tmp_path, env)
        started.append(proc)
        return proc

    yield start
    for proc in reversed(started):
        proc.stop()


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A private Zenoh router on a free loopback port, for this test only."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    spec = ZenohSpec(mode="router", connect=(), router_listen=(endpoint,))
    bus = open_bus(spec, BusOptions(settings={"connect/endpoints": []}))
    try:
        yield endpoint
    finally:
        bus.close()


@pytest.fixture
def bus_factory(router_endpoint: str) -> Iterator[Callable[[], Bus]]:
    """Open peer sessions connected to this test's router; all closed at the end."""
    opened: list[Bus] = []

    def make() -> Bus:
        b = open_bus(ZenohSpec(mode="peer", connect=(router_endpoint,)))
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.close()


@pytest.fixture
def arena_config(tmp_path: Path, router_endpoint: str) -> Callable[..., ArenaConfig]:
    """Build a config with private ports: ``arena_config(n_vehicles=3, speed=2.0)``."""

    def make(n_vehicles: int = 1, extra: str = "", spacing: float = 1.0, **sim: Any) -> ArenaConfig:
        return config_mod.load(
            write_config(tmp_path, router_endpoint, n_vehicles, extra, spacing=spacing, **sim)
        )

    return make
