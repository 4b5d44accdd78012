"""Starting, watching and stopping one OS process: the one way the arena, its tools and its tests do it.

:class:`ChildProcess` starts a program in a process group of its own, has the kernel kill it when the
thread that started it dies (``PR_SET_PDEATHSIG``, Linux), hands each line of its output to a callback,
and stops it with a signal and then SIGKILL after a grace period.  The :mod:`supervisor
<arena_common.runtime.supervisor>` behind ``arena up`` runs each of its children as one;
:func:`child_setup` is the ``preexec_fn`` for a ``subprocess.Popen`` that needs other plumbing (a log
file for stdout, a terminal).

``PR_SET_PDEATHSIG`` fires when the *thread* that forked the child ends, so start children from a thread
that lives as long as they do.

:class:`StopSignals` is the other half: how an arena process itself is asked to stop.  SIGINT (Ctrl-C),
SIGTERM (a kill, systemd, a supervisor) and SIGHUP (its terminal closed) all set one stop event, so that
every command stops the same orderly way whatever ended it; a second signal hurries the stop.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, ClassVar

_PR_SET_PDEATHSIG = 1


def _load_prctl() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        prctl: Callable[..., int] = libc.prctl
    except (OSError, AttributeError):
        return None
    return prctl


# Resolved once, before any fork: the child side must not load libraries.
_prctl = _load_prctl()


def child_setup(parent_pid: int, death_signal: int) -> Callable[[], None]:
    """A ``preexec_fn`` that has the child sent ``death_signal`` when ``parent_pid`` (this thread) dies."""

    def setup() -> None:
        # Runs in the child between fork and exec: ask for ``death_signal`` when the parent dies, and
        # handle the race where it died before this line ran.
        if _prctl is not None:
            _prctl(_PR_SET_PDEATHSIG, death_signal, 0, 0, 0)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), death_signal)

    return setup


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(-code).name
    except ValueError:
        return f"signal {-code}"


def describe_exit(code: int) -> str:
    """``exited with status 1`` or ``killed by SIGKILL``."""
    return f"killed by {_signal_name(code)}" if code < 0 else f"exited with status {code}"


class ChildProcess:
    """One OS process started the arena's way; the :class:`Supervisor` runs each of its children as one.

    The child runs in a process group of its own (a terminal's Ctrl-C reaches the parent alone, and a
    signal to the group reaches the child's own children), is sent ``death_signal`` by the kernel when
    the thread that started it dies (``None``: not), and has its output (stdout and stderr together)
    read line by line by a thread that hands each decoded line, newline included, to ``on_line`` — or,
    with ``log``, appended by the child itself to that file (no thread in this process: what a
    measurement wants)::

        child = ChildProcess(["python", "-m", "services.downsampler", ...], on_line=print)
        ...
        code = child.stop(grace=5.0)   # SIGTERM to its group, SIGKILL after the grace period

    Raises :class:`OSError` when the program cannot be started.
    """

    def __init__(
        self,
        argv: Sequence[str],
        *,
        name: str = "",
        env: Mapping[str, str] | None = None,
        cwd: str | Path | None = None,
        on_line: Callable[[str], None] | None = None,
        log: str | Path | None = None,
        death_signal: int | None = signal.SIGKILL,
    ) -> None:
        if log is not None and on_line is not None:
            raise ValueError("a child's output goes to on_line or to a log file, not both")
        self.name = name or Path(argv[0]).name
        self.argv = tuple(argv)
        self._on_line = on_line
        out = open(log, "ab") if log is not None else None  # noqa: SIM115 - the child's, closed below
        try:
            self.popen: subprocess.Popen[bytes] = subprocess.Popen(
                self.argv,
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=out if out is not None else subprocess.PIPE,
                stderr=subprocess.STDOUT,
                env=dict(os.environ if env is None else env),
                start_new_session=True,
                preexec_fn=None if death_signal is None else child_setup(os.getpid(), death_signal),
                close_fds=True,
            )
        finally:
            if out is not None:
                out.close()
        self._reader = threading.Thread(target=self._pump, name=f"log:{self.name}", daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        stream = self.popen.stdout
        if stream is None:
            return
        with stream:
            for raw in iter(stream.readline, b""):
                if self._on_line is not None:
                    self._on_line(raw.decode("utf-8", errors="replace"))

    @property
    def pid(self) -> int:
        """The child's process id (also its process group id)."""
        return self.popen.pid

    @property
    def alive(self) -> bool:
        """True until the child has exited (and was reaped)."""
        return self.popen.poll() is None

    @property
    def returncode(self) -> int | None:
        """The exit status (negative: killed by that signal), ``None`` while it runs."""
        return self.popen.poll()

    def poll(self) -> int | None:
        """Reap the child if it exited: its exit status, else ``None``."""
        return self.popen.poll()

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the child to exit; its status.  :class:`subprocess.TimeoutExpired` after ``timeout``."""
        return self.popen.wait(timeout)

    def send_signal(self, sig: int, *, group: bool = True) -> None:
        """Send ``sig`` to the child's process group (``group=False``: to the child alone); a no-op once
        it has exited."""
        if self.popen.poll() is not None:
            return
        try:
            if group:
                os.killpg(self.popen.pid, sig)
            else:
                os.kill(self.popen.pid, sig)
        except ProcessLookupError:
            pass
        except PermissionError:
            self.popen.send_signal(sig)

    def stop(self, grace: float = 5.0, sig: int = signal.SIGTERM) -> int | None:
        """Send ``sig`` (to the group), SIGKILL after ``grace`` seconds; the exit status (``None`` if even
        SIGKILL did not end it within 5 s).  Waits for the last of its output to be handed on."""
        if self.alive:
            self.send_signal(sig)
            try:
                self.popen.wait(grace)
            except subprocess.TimeoutExpired:
                self.send_signal(signal.SIGKILL)
                try:
                    self.popen.wait(5.0)
                except subprocess.TimeoutExpired:
                    return None
        self.join_output(5.0)
        return self.popen.returncode

    def join_output(self, timeout: float | None = None) -> None:
        """Wait (at most ``timeout``) until every line the child wrote has been handed to ``on_line``."""
        self._reader.join(timeout)


#: The signals that ask an arena process to stop: Ctrl-C, a kill (or systemd, or a supervisor), and the
#: terminal closing.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class StopSignals:
    """SIGINT, SIGTERM and SIGHUP turned into an orderly stop: the first sets ``stop``, each further one
    calls ``again(signum)`` (hurry: SIGKILL what is left, skip a wait…) — but a further SIGHUP does not:
    a closing terminal sends one and its shell another, and neither is a user insisting.

    Use as a context manager in the main thread (elsewhere it installs nothing: Python delivers signals
    to the main thread only)::

        stop = threading.Event()
        with StopSignals(stop, again=lambda sig: sup.kill_all()):
            while not stop.wait(0.1):
                ...

    The signal number reaches a pipe through Python's wakeup fd (:func:`signal.set_wakeup_fd`): the C-level
    handler writes it in whichever thread the kernel chose, and a thread of this object reads it and acts.  So
    a stop is acted on at once even while the main thread waits in C code (a lock, a socket) and the signal
    landed on another thread — a Python-level handler runs only once the main thread is back in Python, and a
    30 s ``Event.wait`` then delayed it 30 s — and nothing done on a signal can deadlock with the code it
    interrupted (``Event.set`` from a handler can: the main thread may hold the event's lock).  SIGINT is
    handled even when this process was started with it ignored (a background job of a shell script: the
    arena must still stop on Ctrl-C of its group); SIGHUP is left ignored when it was (``nohup``: the user
    asked the process to outlive its terminal).  On exit the previous handlers come back, unless a stop
    signal reached this process: then it is on its way out, and a further signal still hurries it instead of
    raising :class:`KeyboardInterrupt` in its clean-up.
    """

    #: True once any stop signal reached this process: handlers are no longer restored.
    stopping: ClassVar[bool] = False

    def __init__(
        self,
        stop: threading.Event,
        *,
        again: Callable[[int], None] | None = None,
        signals: Sequence[int] = STOP_SIGNALS,
    ) -> None:
        self.stop = stop
        self.again = again
        self.signals = tuple(signals)
        #: The signals received so far, in order.
        self.received: list[int] = []
        self._previous: dict[int, Any] = {}
        self._pipe: tuple[int, int] | None = None
        self._wakeup = -1  # the wakeup fd before this one, put back by restore()
        self._thread: threading.Thread | None = None

    @property
    def count(self) -> int:
        """How many stop signals arrived."""
        return len(self.received)

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        """The Python-level handler: nothing to do, the wakeup fd carried the signal to the relay."""

    def _act(self, signum: int) -> None:
        StopSignals.stopping = True
        self.received.append(signum)
        if len(self.received) == 1:
            self.stop.set()
        elif self.again is not None and signum != signal.SIGHUP:
            try:
                self.again(signum)
            except Exception:  # a hurry that fails must not end the relay
                pass
        self.stop.set()

    def _relay(self, read_fd: int) -> None:
        while True:
            try:
                data = os.read(read_fd, 64)
            except InterruptedError:
                continue
            except OSError:
                return
            if not data:
                return
            for signum in data:
                if signum in self._previous:  # the wakeup fd carries every signal with a Python handler
                    self._act(signum)

    def install(self) -> StopSignals:
        """Install the handlers (from the main thread; elsewhere: nothing).  Returns ``self``."""
        if threading.current_thread() is not threading.main_thread() or self._pipe is not None:
            return self
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        self._wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        self._pipe = (read_fd, write_fd)
        self._thread = threading.Thread(target=self._relay, args=(read_fd,), name="stop-signals", daemon=True)
        self._thread.start()
        for sig in self.signals:
            current = signal.getsignal(sig)
            if sig == signal.SIGHUP and current == signal.SIG_IGN:
                continue  # nohup
            self._previous[sig] = current
            signal.signal(sig, self._handler)
        return self

    def restore(self) -> None:
        """Put the previous handlers back (kept while a stop is under way, see the class)."""
        if self._pipe is None or self.received or StopSignals.stopping:
            return
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()
        signal.set_wakeup_fd(self._wakeup)
        read_fd, write_fd = self._pipe
        self._pipe = None
        os.close(write_fd)  # the relay reads the end of the pipe and returns
        if self._thread is not None:
            self._thread.join(1.0)
        os.close(read_fd)

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()


def lead_own_session(death_signal: int = signal.SIGKILL) -> None:
    """Make this command the leader of a session of its own: unless it already is one (Linux only), run it
    again — the same interpreter and command line — as the leader of a new session, pass it every stop
    signal, and exit with its status.  For a command's entry point, before it does anything.

    Linux's autogroup scheduling (on by default in most distributions) shares the CPU between sessions first
    and weighs a niceness only among the processes of one session, so a process that yields the CPU must
    lower its session's group (:func:`~arena_common.runtime.service.yield_cpu`).  A command typed in a
    terminal shares its shell's session: lowering that group would lower the terminal's every other job too,
    so the command moves to a session of its own first.  Every process ``arena up`` starts already leads one.

    The new leader keeps this process's input and output; SIGINT, SIGTERM and SIGHUP (unless ignored:
    ``nohup``) go on to it, and the kernel sends it ``death_signal`` should this process die.
    """
    if not sys.platform.startswith("linux") or os.getsid(0) == os.getpid():
        return
    child = subprocess.Popen(
        [sys.executable, *sys.orig_argv[1:]],
        start_new_session=True,
        preexec_fn=child_setup(os.getpid(), death_signal),
    )

    def relay(signum: int, frame: FrameType | None) -> None:
        child.send_signal(signum)  # a no-op once it has exited

    for sig in STOP_SIGNALS:
        if sig == signal.SIGHUP and signal.getsignal(sig) == signal.SIG_IGN:
            continue  # nohup: the user asked it to outlive its terminal
        signal.signal(sig, relay)
    code = child.wait()
    raise SystemExit(128 - code if code < 0 else code)
