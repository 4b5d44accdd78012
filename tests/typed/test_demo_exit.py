"""``arena demo`` and ``arena up`` end, whatever ends them, and leave nothing running.

Ctrl-C, SIGTERM and a closed terminal (SIGHUP) while the vehicles fly: every vehicle lands (the demo
waits until each is on the ground), then the arena stops and the demo exits.  A second Ctrl-C: at once.
Each is typed as a user would (:class:`tests.typed.harness.Command`: the real ``arena`` script, its own
session), on a config of free ports; a real terminal that closes is a tmux window.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from arena_common.cli._demo import LAND_TIMEOUT
from tests.helpers import free_port, wait_for
from tests.typed.harness import ARENA, Command, Typed, commands, kill_leftovers, leftovers

pytestmark = [
    pytest.mark.system,
    pytest.mark.timeout(300),
    pytest.mark.skipif(not ARENA.exists(), reason=f"no arena console script at {ARENA}"),
]

FLYING_S = 150.0  # the arena up, the vehicle ready and in the air, on a busy 2-core machine
# `arena demo` says it waits for the vehicles once its router listens (3.6 s on an idle 2-core machine, 13.4 s
# loaded: load average 5) and its session is open; it gives up by itself, saying why, after its own
# --ready-timeout (90 s and 2 s a vehicle): the test's bound is the demo's, plus its error.
READY_S = 90.0 + 2.0 + 15.0
LANDED_S = LAND_TIMEOUT + 25.0  # the landing (at most --land-timeout) and the arena's stop


@pytest.fixture
def typed(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    """``arena`` command lines in ``tmp_path``, killed (with all they started) at the end."""
    with commands(tmp_path) as start:
        yield start


def _config(tmp_path: Path) -> Typed:
    return Typed(tmp_path, f"tcp/127.0.0.1:{free_port()}", router=True, px4=False)


def _nothing_left(tmp_path: Path, cmd: Command) -> None:
    wait_for(
        lambda: not leftovers([str(tmp_path)], cmd.pid),
        timeout=15,
        interval=0.2,
        what="no process of the arena left",
    )


def _index(cmd: Command, pattern: str) -> int:
    at = next((i for i, line in enumerate(cmd.lines) if re.search(pattern, line)), None)
    assert at is not None, f"no line matches {pattern!r}:\n{cmd.output()}"
    return at


@pytest.mark.covers("arena demo")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP, signal.SIGTERM], ids=lambda s: s.name)
def test_a_stopped_demo_lands_every_vehicle_then_stops_the_arena(
    tmp_path: Path, typed: Callable[..., Command], sig: signal.Signals
) -> None:
    cfg = _config(tmp_path)
    cmd = typed("demo", str(cfg.path), "--log", str(tmp_path / "demo.log"))
    cmd.wait_line(r"formation step 1/6", timeout=FLYING_S)
    cmd.signal(sig)
    assert cmd.exits_within(LANDED_S) == 0, cmd.output()
    out = cmd.output()
    assert f"stopping ({sig.name}): every vehicle lands, then the arena stops" in out, out
    assert f"landing x7: waiting up to {LAND_TIMEOUT:.0f} s" in out, out
    assert _index(cmd, r"^landed: x7$") < _index(cmd, r"^stopping the arena$"), out
    assert "formation step 2/6" not in out.split(f"stopping ({sig.name})")[1]  # the flight was abandoned
    _nothing_left(tmp_path, cmd)


def test_a_second_ctrl_c_stops_the_demo_at_once(tmp_path: Path, typed: Callable[..., Command]) -> None:
    cfg = _config(tmp_path)
    cmd = typed("demo", str(cfg.path), "--log", str(tmp_path / "demo.log"))
    cmd.wait_line(r"formation step 1/6", timeout=FLYING_S)
    cmd.signal(signal.SIGINT)
    cmd.wait_line(r"landing x7: waiting up to", timeout=15)
    cmd.signal(signal.SIGINT)
    assert cmd.exits_within(15) == 0, cmd.output()
    assert "stopping at once (signalled again): x7 still in the air, landing" in cmd.output()
    assert "stopping the arena at once" in cmd.output()
    _nothing_left(tmp_path, cmd)


def test_a_demo_that_fails_in_flight_lands_before_the_arena_stops(
    tmp_path: Path, typed: Callable[..., Command]
) -> None:
    """A room of 2.4 m x 2.4 m: the safe box ends 0.9 m from the centre, so the gateway refuses the formation's
    first goal (1 m from it) once x7 is in the air; the demo fails, lands x7, then stops the arena."""
    cfg = _config(tmp_path)
    cfg.path.write_text(
        cfg.path.read_text().replace('name = "typed"\n', 'name = "typed"\nsize = [2.4, 2.4, 2.5]\n')
    )
    cmd = typed("demo", str(cfg.path), "--once", "--log", str(tmp_path / "demo.log"))
    assert cmd.exits_within(FLYING_S + LANDED_S) == 1, cmd.output()
    out = cmd.output()
    assert re.search(r"^demo failed: x7: goto REFUSED: .*safe", out, re.M | re.I), out
    assert (
        _index(cmd, r"^demo failed")
        < _index(cmd, r"^the demo failed: every vehicle lands")
        < _index(cmd, r"^landed: x7$")
        < _index(cmd, r"^stopping the arena$")
    ), out
    assert "formation step 1/6" not in out, out  # nothing more was sent after the refusal
    _nothing_left(tmp_path, cmd)


def test_a_demo_stopped_while_the_arena_starts(tmp_path: Path, typed: Callable[..., Command]) -> None:
    """Ctrl-C twice while nothing flies yet: no landing to wait for, everything stops."""
    cfg = _config(tmp_path)
    cmd = typed("demo", str(cfg.path), "--log", str(tmp_path / "demo.log"))
    cmd.wait_line(r"waiting for x7", timeout=READY_S)
    wait_for(lambda: len(leftovers([str(cfg.path)])) >= 3, timeout=60, what="the arena's services starting")
    cmd.signal(signal.SIGINT)
    cmd.wait_line(r"no vehicle in the air|stopping the arena", timeout=15)
    cmd.signal(signal.SIGINT)
    assert cmd.exits_within(20) == 0, cmd.output()
    _nothing_left(tmp_path, cmd)


@pytest.mark.parametrize("twice", [False, True], ids=["SIGHUP", "SIGINT-twice"])
def test_arena_up_stops_every_service(tmp_path: Path, typed: Callable[..., Command], twice: bool) -> None:
    cfg = _config(tmp_path)
    cmd = typed("up", str(cfg.path), "--host", "typed")
    cmd.wait_line(r"^\[gateway\.x7\] .*gateway for x7", timeout=60)
    assert len(leftovers([str(cfg.path)])) >= 8  # the supervisor and its seven services
    if twice:
        cmd.signal(signal.SIGINT)
        cmd.wait_line(r"^\[arena\] stopping ", timeout=15)
        cmd.signal(signal.SIGINT)
    else:
        cmd.signal(signal.SIGHUP)
    assert cmd.exits_within(20) == 0, cmd.output()
    assert re.search(r"^\[arena\] all stopped$", cmd.output(), re.M), cmd.output()
    _nothing_left(tmp_path, cmd)


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_closing_the_terminal_window_ends_the_demo(tmp_path: Path) -> None:
    """`arena demo` in a tmux window, flying; the window's terminal goes away (tmux kill-server)."""
    cfg = _config(tmp_path)
    socket_name = f"arena-test-{os.getpid()}"
    tmux = ["tmux", "-L", socket_name, "-f", "/dev/null"]
    typing = f"cd {tmp_path} && env -u ARENA_CONFIG {ARENA} demo {cfg.path} --log {tmp_path / 'demo.log'}"
    env = {**os.environ, "SHELL": shutil.which("bash") or "/bin/sh"}  # bash hangs its jobs up too
    subprocess.run([*tmux, "new-session", "-d", "-x", "150", "-y", "60"], check=True, timeout=30, env=env)
    try:

        def screen() -> str:
            res = subprocess.run(  # with the scroll-back: the live view redraws in place
                [*tmux, "capture-pane", "-p", "-S", "-"], capture_output=True, text=True, timeout=10
            )
            return res.stdout

        subprocess.run([*tmux, "send-keys", typing, "Enter"], check=True, timeout=30)  # typed at the prompt
        wait_for(lambda: "formation step 1/6" in screen(), timeout=FLYING_S, interval=0.5, what="x7 flying")
        assert len(leftovers([str(cfg.path)])) >= 8
        subprocess.run([*tmux, "kill-server"], timeout=30)
        wait_for(
            lambda: not leftovers([str(tmp_path)]),
            timeout=LANDED_S,
            interval=0.2,
            what="every process of the arena gone with its terminal",
        )
        log = (tmp_path / "demo.log").read_text(errors="replace")
        assert re.search(r"estop \(demo stopping: land\)", log), log[-3000:]
        landed = re.search(r"\[gateway\.x7\] .*(Landing detected|Disarmed by landing)", log)
        stopping = re.search(r"^\[arena\] stopping ", log, re.M)
        assert landed and stopping and landed.start() < stopping.start(), log[-3000:]  # landed, then stopped
    finally:
        subprocess.run([*tmux, "kill-server"], capture_output=True, timeout=30)
        kill_leftovers([str(tmp_path)])
