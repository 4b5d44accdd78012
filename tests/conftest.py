"""Shared fixtures: free ports, a private Zenoh router per test, configs with their own endpoints."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import config as config_mod
from arena_common.core.config import ArenaConfig, ZenohSpec

REPO = Path(__file__).resolve().parent.parent


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port nobody listens on right now (TCP by default, UDP with SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(
    predicate: Callable[[], Any], timeout: float = 5.0, interval: float = 0.01, what: str = "condition"
) -> Any:
    """Poll ``predicate`` until truthy (returned) or fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


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


def write_config(
    tmp_path: Path,
    router_endpoint: str,
    n_vehicles: int = 1,
    extra: str = "",
    services: tuple[str, ...] = ("sim", "mocap", "transform"),
    **sim: Any,
) -> Path:
    """Write an arena config whose every port is free and private to this test."""
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
            f"sim = {{ start = [{i * 1.0 - 1.0}, 0.0] }}",
        ]
    if sim:
        lines.append("[sim]")
        lines += [f"{k} = {v!r}".replace("'", '"') for k, v in sim.items()]
    lines.append(extra)
    path = tmp_path / "arena.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def arena_config(tmp_path: Path, router_endpoint: str) -> Callable[..., ArenaConfig]:
    """Build a config with private ports: ``arena_config(n_vehicles=3, speed=2.0)``."""

    def make(n_vehicles: int = 1, extra: str = "", **sim: Any) -> ArenaConfig:
        return config_mod.load(write_config(tmp_path, router_endpoint, n_vehicles, extra, **sim))

    return make
