"""One child process started, watched and stopped the arena's way; the one bounded wait."""

from __future__ import annotations

import os
import signal
import subprocess
import textwrap
import threading
import time
from pathlib import Path

import pytest

from arena_common.core.errors import WaitTimeout
from arena_common.core.waiting import wait_until
from arena_common.runtime.process import ChildProcess
from tests.helpers import PYTHON

CHILD = textwrap.dedent(
    """
    import os, signal, subprocess, sys, time
    mode = sys.argv[1]
    if mode == "stubborn":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if mode == "parent":  # a child of its own, which prints its pid
        kid = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        print(f"kid {kid.pid}", flush=True)
    print("one", flush=True)
    print("two", file=sys.stderr, flush=True)
    print("three é", flush=True)
    if mode == "exit":
        sys.exit(7)
    time.sleep(60)
    """
)


@pytest.fixture
def child_script(tmp_path: Path) -> Path:
    path = tmp_path / "child.py"
    path.write_text(CHILD)
    return path


def gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True


def test_lines_in_order_and_the_exit_status(child_script: Path) -> None:
    lines: list[str] = []
    child = ChildProcess([PYTHON, str(child_script), "exit"], name="c", on_line=lines.append)
    assert child.wait(30.0) == 7
    child.join_output(5.0)
    assert lines == ["one\n", "two\n", "three é\n"]  # stdout and stderr together, decoded
    assert not child.alive and child.returncode == 7 and child.poll() == 7
    assert child.stop() == 7  # stopping an exited child only reports its status


def test_stop_sigterm_then_sigkill_after_grace(child_script: Path) -> None:
    lines: list[str] = []
    polite = ChildProcess([PYTHON, str(child_script), "run"], on_line=lines.append)
    wait_until(lambda: "three é\n" in lines, 30.0, "the polite child's output")
    assert polite.alive and polite.pid == os.getpgid(polite.pid)  # a process group of its own
    assert polite.stop(grace=10.0) == -signal.SIGTERM

    said: list[str] = []
    stubborn = ChildProcess([PYTHON, str(child_script), "stubborn"], on_line=said.append)
    wait_until(lambda: "three é\n" in said, 30.0, "the stubborn child's output")
    t0 = time.monotonic()
    assert stubborn.stop(grace=0.5) == -signal.SIGKILL
    assert time.monotonic() - t0 >= 0.5  # it had its grace period first


def test_group_signal_reaches_the_childs_own_children(child_script: Path) -> None:
    lines: list[str] = []
    parent = ChildProcess([PYTHON, str(child_script), "parent"], on_line=lines.append)
    said = wait_until(lambda: next((x for x in lines if x.startswith("kid ")), ""), 30.0, "the kid's pid")
    kid = int(said.split()[1])
    assert not gone(kid)
    parent.stop(grace=10.0)
    wait_until(lambda: gone(kid), 10.0, "the grandchild gone with its group")


def test_output_to_a_log_file(child_script: Path, tmp_path: Path) -> None:
    log = tmp_path / "c.log"
    child = ChildProcess([PYTHON, str(child_script), "exit"], log=log)
    assert child.wait(30.0) == 7
    child.join_output(5.0)
    assert log.read_text().splitlines() == ["one", "two", "three é"]
    with pytest.raises(ValueError, match="not both"):
        ChildProcess([PYTHON, "-c", "pass"], log=log, on_line=print)
    with pytest.raises(OSError):
        ChildProcess([str(tmp_path / "no-such-program")])


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs /proc (Linux)")
def test_killed_with_the_thread_that_started_it(child_script: Path) -> None:
    """The death signal: the child goes when the thread that started it ends (here a short-lived one)."""
    started: list[ChildProcess] = []
    lines: list[str] = []

    def start() -> None:
        started.append(ChildProcess([PYTHON, str(child_script), "run"], on_line=lines.append))
        wait_until(lambda: "one\n" in lines, 30.0, "the child's output")

    thread = threading.Thread(target=start)
    thread.start()
    thread.join(40.0)
    child = started[0]
    assert child.wait(10.0) == -signal.SIGKILL


# -- waiting -------------------------------------------------------------------------------------------------


def test_wait_until_returns_the_value_or_names_what_it_waited_for() -> None:
    values = iter([0, "", None, "ready"])
    assert wait_until(lambda: next(values), 5.0, "a value", interval=0.001) == "ready"
    calls = []
    with pytest.raises(WaitTimeout, match=r"timed out after 0\.05 s waiting for the moon") as info:
        wait_until(lambda: calls.append(1), 0.05, "the moon", interval=0.01)
    assert info.value.what == "the moon" and info.value.timeout == 0.05
    assert isinstance(info.value, TimeoutError)
    assert len(calls) >= 2  # polled, and once more at the deadline


def test_wait_until_checks_before_each_poll_and_may_stop_early() -> None:
    checks: list[int] = []

    def check() -> None:
        checks.append(1)
        if len(checks) == 3:
            raise RuntimeError("the child died")

    with pytest.raises(RuntimeError, match="the child died"):
        wait_until(lambda: False, 30.0, "never", interval=0.001, check=check)
    assert len(checks) == 3


def test_a_slow_predicate_that_holds_at_the_deadline_is_not_a_timeout() -> None:
    t0 = time.monotonic()

    def slow() -> bool:
        time.sleep(0.06)  # a poll longer than the whole timeout (a busy machine)
        return time.monotonic() - t0 > 0.1

    assert wait_until(slow, 0.05, "slow") is True


# The main thread blocks the stop signals, so the kernel hands each to another thread, and then waits in C code
# (an Event.wait of 120 s): a stop signalled by a Python-level handler alone would wait for the main thread.
SIGNAL_ON_ANOTHER_THREAD = """
import signal, threading
from arena_common.runtime.process import StopSignals
stop = threading.Event()
with StopSignals(stop) as signals:  # its relay thread, started unblocked, is where the signals land
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
    print("ready", flush=True)
    stop.wait(120)
    print("stopped", *(signal.Signals(s).name for s in signals.received), flush=True)
"""


def test_a_stop_signal_caught_by_another_thread_stops_a_main_thread_waiting_in_c(tmp_path: Path) -> None:
    script = tmp_path / "other_thread.py"
    script.write_text(SIGNAL_ON_ANOTHER_THREAD)
    proc = subprocess.Popen([PYTHON, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        proc.send_signal(signal.SIGTERM)
        # bounded well below the script's 120 s wait: a stop acted on only when the main thread wakes fails it
        assert proc.wait(timeout=60) == 0
        assert proc.stdout.read() == "stopped SIGTERM\n"
    finally:
        proc.kill()
        proc.wait()
