"""``arena demo`` opens its Zenoh client only once the router it starts listens (``_wait_router``).

The client gives up after 10 s without its router, and the supervisor's router listened 3.6 s after the
demo started it on an idle 2-core machine, 13.4 s on the same machine loaded (load average 5): the demo
waits for the router's port (within its come-up deadline, Ctrl-C and the supervisor's exit heard), and
says what it waited for when it does not come.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from arena_common.cli._demo import _wait_router
from arena_common.core.config import ArenaConfig, load
from tests.helpers import free_port


def _config(tmp_path: Path, port: int) -> ArenaConfig:
    path = tmp_path / "arena.toml"
    path.write_text(
        "\n".join(
            [
                "[zenoh]",
                f'connect = ["tcp/127.0.0.1:{port}"]',
                f'router_listen = ["tcp/127.0.0.1:{port}"]',
                "[hosts.h]",
                'services = ["router"]',
            ]
        )
        + "\n"
    )
    return load(path)


@pytest.fixture
def supervisor() -> Iterator[subprocess.Popen[bytes]]:
    """A stand-in for ``arena up``: a process that runs until killed."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc
    proc.kill()
    proc.wait(5)


def test_the_client_opens_only_once_the_router_listens(
    tmp_path: Path, supervisor: subprocess.Popen[bytes]
) -> None:
    port = free_port()
    cfg = _config(tmp_path, port)
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)

    def listen_later() -> None:
        time.sleep(0.5)  # the router's port opens while the demo already waits (a late router, scaled down)
        listener.bind(("127.0.0.1", port))
        listener.listen()

    later = threading.Thread(target=listen_later)
    later.start()
    try:
        start = time.monotonic()
        assert _wait_router(cfg, supervisor, threading.Event(), time.monotonic() + 30) == ""
        assert 0.4 < time.monotonic() - start < 10
    finally:
        later.join()
        listener.close()


def test_a_router_that_never_listens_is_named_at_the_deadline(
    tmp_path: Path, supervisor: subprocess.Popen[bytes]
) -> None:
    port = free_port()
    why = _wait_router(_config(tmp_path, port), supervisor, threading.Event(), time.monotonic() + 0.5)
    assert why.startswith(f"the router did not accept on tcp/127.0.0.1:{port} within "), why


def test_a_supervisor_that_exits_ends_the_wait(tmp_path: Path) -> None:
    port = free_port()
    gone = subprocess.Popen([sys.executable, "-c", "raise SystemExit(2)"])
    gone.wait(30)
    why = _wait_router(_config(tmp_path, port), gone, threading.Event(), time.monotonic() + 30)
    assert why == f"the supervisor exited (2) before the router accepted on tcp/127.0.0.1:{port}", why


def test_a_stop_ends_the_wait_at_once(tmp_path: Path, supervisor: subprocess.Popen[bytes]) -> None:
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    start = time.monotonic()
    assert _wait_router(_config(tmp_path, free_port()), supervisor, stop, time.monotonic() + 30) == ""
    assert time.monotonic() - start < 2
