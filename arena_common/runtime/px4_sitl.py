"""A real PX4 SITL autopilot (v1.16, built-in SIH simulator) as a child process: find, start, wait, stop.

The build (``px4_sitl_default`` with ``bin/px4``, ``bin/px4-*`` and ``etc/``) is found from
``$PX4_SITL_DIR``, else ``<repo>/../shared/px4-sitl`` (:func:`find_build`).  One :class:`Px4Sitl` runs
instance *N* the way the build's ``run.sh`` does::

    with Px4Sitl(0, params={"EKF2_EV_CTRL": 15, "EKF2_HGT_REF": 3}) as px4:   # started, ready
        flags = px4.listener("estimator_status_flags")                       # PX4's own view
        print(flags["cs_ev_pos"], px4.boot_s)

Every instance runs in a fresh temporary working directory (parameters, dataman), removed on
:meth:`Px4Sitl.stop`; ``PX4_PARAM_<NAME>`` boot parameters are applied at every boot (PX4's ``rcS``), so
they win over values saved before a reboot.  The build's ``bin/px4-*`` helpers are symbolic links to
``px4`` (PX4 dispatches on its own program name); a copy may have them flattened into small text files,
which makes ``run.sh`` fail with "px4-param: Permission denied" — so each instance gets its own private
directory of links, to the real file when it is one and to ``bin/px4`` otherwise.

The ports and system id of instance *i* (:func:`~arena_common.runtime.px4_sitl_rules.ports`) and the
config rules of a ``"px4-sitl"`` vehicle are in :mod:`arena_common.runtime.px4_sitl_rules`; SIH's ground
truth comes at 25 Hz unless asked otherwise.  PX4 latches the first peer address of each link.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import math
import os
import re
import shutil
import signal
import struct
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from arena_common.core.config import ArenaConfig, VehicleSpec
from arena_common.core.errors import ConfigError
from arena_common.mavlink import px4
from arena_common.mavlink.metadata import MetadataError, load_parameters_json
from arena_common.runtime.process import child_setup
from arena_common.runtime.px4_sitl_rules import MAX_INSTANCE as MAX_INSTANCE  # the launcher's names too
from arena_common.runtime.px4_sitl_rules import Ports as Ports
from arena_common.runtime.px4_sitl_rules import Px4SitlError as Px4SitlError
from arena_common.runtime.px4_sitl_rules import check_instance, ports

ENV_DIR = "PX4_SITL_DIR"
REPO = Path(__file__).resolve().parents[2]
DEFAULT_DIR = REPO.parent / "shared" / "px4-sitl"
DEFAULT_MODEL = "sihsim_quadx"
READY_LINES = ("Startup script returned successfully", "Ready for takeoff")
LOCK_FILE = "/tmp/px4_lock-{n}"  # PX4 holds a POSIX record lock on it while instance n runs
#: SIH's home when no parameter moves it (this build's parameters.json defaults).
SIH_HOME_DEFAULT = (47.397742, 8.545594, 489.4)

ListenerValue = bool | int | float | str | list[float]


# -- the build ----------------------------------------------------------------------------------------


def find_build(explicit: str | Path | None = None) -> Path:
    """The PX4 SITL build: ``explicit``, else ``$PX4_SITL_DIR``, else ``<repo>/../shared/px4-sitl``.

    :class:`Px4SitlError` naming the places looked at when none holds ``bin/px4`` and ``etc/``.
    """
    if explicit is not None:
        candidates = [(str(explicit), Path(explicit))]
    else:
        env = os.environ.get(ENV_DIR)
        candidates = [(f"${ENV_DIR}={env}", Path(env))] if env else []
        candidates.append((str(DEFAULT_DIR), DEFAULT_DIR))
    for _, path in candidates:
        if (path / "bin" / "px4").is_file() and (path / "etc").is_dir():
            return path.resolve()
    looked = "; ".join(label for label, _ in candidates)
    hint = "" if explicit is not None or os.environ.get(ENV_DIR) else f" (${ENV_DIR} is not set)"
    raise Px4SitlError(f"no PX4 SITL build (bin/px4 and etc/) found: looked at {looked}{hint}")


def build_missing_reason(explicit: str | Path | None = None) -> str | None:
    """None when a build is found, else why not (for a test skip)."""
    try:
        find_build(explicit)
    except Px4SitlError as exc:
        return str(exc)
    return None


def link_tools(build: Path, dest: Path) -> Path:
    """Fill ``dest`` with links to the build's ``bin/px4*``: real files kept, flattened helpers → ``px4``."""
    dest.mkdir(parents=True, exist_ok=True)
    px4_exe = build / "bin" / "px4"
    for f in sorted((build / "bin").glob("px4*")):
        real = f.name == "px4-alias.sh" or f.is_symlink() or (os.access(f, os.X_OK) and f.is_file())
        link = dest / f.name
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(f if real else px4_exe)
    return dest


def parameter_defaults(build: Path) -> dict[str, float]:
    """Default value of every parameter of the build (its ``parameters.json``); empty when absent."""
    try:
        meta = load_parameters_json(build / "parameters.json")
    except MetadataError:
        return {}
    return {name: float(m["default"]) for name, m in meta.items() if m["default"] is not None}


def sih_home(
    params: Mapping[str, float | int | str] | None = None,
    env: Mapping[str, str] | None = None,
    build: Path | None = None,
) -> tuple[float, float, float]:
    """Where SIH puts the vehicle at boot: (latitude °, longitude °, ground altitude m AMSL).

    ``SIH_LOC_LAT0/LON0/H0`` from the boot ``params``, else ``PX4_HOME_LAT/LON/ALT`` from ``env`` (as
    ``run.sh`` takes them), else the build's defaults.  Each is rounded to float32, as PX4 stores it:
    the ground truth then reads exactly (0, 0, 0) on the ground at home.
    """
    defaults = parameter_defaults(build) if build is not None else {}
    env = env or {}
    out = []
    for name, env_name, fallback in zip(
        ("SIH_LOC_LAT0", "SIH_LOC_LON0", "SIH_LOC_H0"),
        ("PX4_HOME_LAT", "PX4_HOME_LON", "PX4_HOME_ALT"),
        SIH_HOME_DEFAULT,
        strict=True,
    ):
        value = (params or {}).get(name, env.get(env_name, defaults.get(name, fallback)))
        out.append(float(np.float32(float(value))))
    return out[0], out[1], out[2]


def arena_boot_params(
    preset: str = "arena", extra: Mapping[str, float | int] | None = None
) -> dict[str, float]:
    """Boot parameters of a PX4 SITL vehicle: ``preset`` "arena" starts it as ``arena px4 setup`` leaves
    a lab's vehicle (:data:`~arena_common.mavlink.px4.ARENA_REQUIRED_PARAMS`), "px4" with PX4's defaults; then
    ``extra`` (a vehicle's ``px4_params``) on top."""
    if preset not in ("arena", "px4"):
        raise Px4SitlError(f'PX4 parameter preset must be "arena" or "px4", got {preset!r}')
    out: dict[str, float] = {}
    if preset == "arena":
        out = {name: float(value) for name, (value, _) in px4.ARENA_REQUIRED_PARAMS.items()}
    out.update({name: float(value) for name, value in (extra or {}).items()})
    return out


def instance_busy(instance: int) -> bool:
    """True while some px4 process runs instance ``instance`` on this machine (its lock file is held)."""
    path = LOCK_FILE.format(n=instance)
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        # F_GETLK: would a write lock conflict?  Asks without taking anything.
        lock = fcntl.fcntl(fd, fcntl.F_GETLK, _flock_struct(fcntl.F_WRLCK))
        return _flock_type(lock) != fcntl.F_UNLCK
    except OSError:
        return False
    finally:
        os.close(fd)


def _flock_struct(kind: int) -> bytes:
    # struct flock on Linux x86-64/aarch64: short l_type, short l_whence, off_t l_start, off_t l_len, pid_t.
    return struct.pack("hhqqi4x", kind, os.SEEK_SET, 0, 0, 0)


def _flock_type(raw: bytes) -> int:
    return int(struct.unpack("hhqqi4x", raw)[0])


# -- listener ----------------------------------------------------------------------------------------

_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _value(text: str) -> ListenerValue:
    text = text.strip()
    if text in ("True", "true"):
        return True
    if text in ("False", "false"):
        return False
    if text.startswith("[") and text.endswith("]"):
        items = [x for x in text[1:-1].replace(",", " ").split() if x]
        try:
            return [float(x) for x in items]
        except ValueError:
            return text
    head = text.split(" (", 1)[0].strip()  # "4048000 (0.68 seconds ago)"
    if re.fullmatch(r"[-+]?\d+", head):
        return int(head)
    if _NUMBER.match(head) or head.lower() in ("nan", "-nan", "inf", "-inf", "+inf"):
        return float(head.replace("-nan", "nan"))
    return text


def parse_listener(text: str) -> list[dict[str, ListenerValue]]:
    """The messages in ``px4-listener`` output, one dict per printed message (``key: value`` lines).

    Numbers become int/float (``nan``/``inf`` included), ``True``/``False`` bools, ``[a, b]`` lists of
    floats; a timestamp's "(… seconds ago)" is dropped.  Nothing printed (never published): ``[]``.
    """
    messages: list[dict[str, ListenerValue]] = []
    current: dict[str, ListenerValue] | None = None
    for raw in text.splitlines():
        line = raw.rstrip()
        if not line.strip() or line.startswith("TOPIC:"):
            continue
        indent = len(line) - len(line.lstrip())
        key, sep, rest = line.strip().partition(":")
        if indent >= 2 and sep and current is not None and " " not in key:
            current[key] = _value(rest)
        elif indent >= 1 and not sep:  # " estimator_status_flags": a message starts
            current = {}
            messages.append(current)
    return [m for m in messages if m]


# -- the instance --------------------------------------------------------------------------------------


def param_text(value: float | int | str) -> str:
    """A boot parameter's value as ``param set`` takes it (integers without a decimal point)."""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**31:
        return str(int(value))  # INT32 parameters do not take "15.0"; FLOAT ones take "15"
    return repr(value) if isinstance(value, float) else str(value)


class Px4Sitl:
    """One PX4 SITL instance.  :meth:`start` + :meth:`wait_ready`, or use it as a context manager.

    ``params``: boot parameters (``PX4_PARAM_<NAME>``).  ``output``: called with each line PX4 prints
    (they are also kept: :attr:`lines`, the last 2,000).  ``env``: extra environment (``PX4_HOME_LAT``,
    ``PX4_SIM_SPEED_FACTOR``…).  ``keep_log``: keep PX4's ULog flight log (off: it grows ~1 MB/s).
    """

    def __init__(
        self,
        instance: int,
        *,
        build: str | Path | None = None,
        params: Mapping[str, float | int | str] | None = None,
        model: str = DEFAULT_MODEL,
        env: Mapping[str, str] | None = None,
        output: Callable[[str], None] | None = None,
        keep_log: bool = False,
        ready_timeout: float = 60.0,
    ) -> None:
        self.instance = check_instance(instance)
        self.ports = ports(instance)
        self.build = find_build(build)
        self.params = dict(params or {})
        for name in self.params:
            if not re.fullmatch(r"[A-Z0-9_]{1,16}", name):
                raise Px4SitlError(f"not a PX4 parameter name: {name!r}")
        self.model = model
        self.extra_env = dict(env or {})
        self.output = output
        self.keep_log = keep_log
        self.ready_timeout = ready_timeout
        self.lines: collections.deque[str] = collections.deque(maxlen=2000)
        self.proc: subprocess.Popen[bytes] | None = None
        self.boot_s: float | None = None  # seconds from start to ready, last boot
        self.boots = 0
        self.boot_start = 0.0
        self._root: Path | None = None
        self._ready = threading.Event()
        self._reader: threading.Thread | None = None
        self._lock = threading.Lock()

    # -- paths and environment --------------------------------------------------------------------------
    @property
    def workdir(self) -> Path:
        """The working directory (parameters, dataman); kept across :meth:`restart`."""
        if self._root is None:
            raise Px4SitlError(f"PX4 SITL instance {self.instance} was never started")
        return self._root / "work"

    @property
    def tools(self) -> Path:
        """The private directory of ``px4*`` links."""
        if self._root is None:
            raise Px4SitlError(f"PX4 SITL instance {self.instance} was never started")
        return self._root / "bin"

    def environment(self) -> dict[str, str]:
        """The environment px4 runs in (what ``run.sh`` sets, then the boot parameters)."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_PARAM_")}
        env.update(self.extra_env)
        env["PATH"] = f"{self.tools}{os.pathsep}{env.get('PATH', '')}"
        env["PX4_SIM_MODEL"] = self.model
        if not self.keep_log:
            env["PX4_PARAM_SDLOG_MODE"] = "-1"
        for name, value in self.params.items():
            env[f"PX4_PARAM_{name}"] = param_text(value)
        return env

    @property
    def alive(self) -> bool:
        """True while the px4 process runs."""
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        """px4's exit status once it exited (None while it runs or before it started)."""
        return None if self.proc is None else self.proc.poll()

    # -- start / stop ----------------------------------------------------------------------------------
    def start(self) -> None:
        """Start px4 (a fresh working directory the first time; the same one after :meth:`stop` with
        ``keep=True`` or on :meth:`restart`).  Does not wait: see :meth:`wait_ready`.

        px4 is killed when the thread that started it ends (``PR_SET_PDEATHSIG``): start it from a
        thread that outlives it.  :class:`Px4SitlError` when the instance already runs on this machine.
        """
        with self._lock:
            if self.alive:
                return
            if instance_busy(self.instance):
                raise Px4SitlError(
                    f"PX4 SITL instance {self.instance} is already running on this machine (lock "
                    f"{LOCK_FILE.format(n=self.instance)} held): stop it or use another instance"
                )
            if self._root is None:
                self._root = Path(tempfile.mkdtemp(prefix=f"px4-sitl-{self.instance}."))
                link_tools(self.build, self._root / "bin")
                (self._root / "work").mkdir()
            self._ready.clear()
            self.boot_s = None
            self.boot_start = time.monotonic()
            argv = [str(self.tools / "px4"), str(self.build / "etc"), "-i", str(self.instance), "-d"]
            argv += ["-w", str(self.workdir)]
            try:
                self.proc = subprocess.Popen(
                    argv,
                    cwd=self.workdir,
                    env=self.environment(),
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    preexec_fn=child_setup(os.getpid(), signal.SIGKILL),  # dies with us
                    close_fds=True,
                )
            except OSError as exc:
                raise Px4SitlError(f"cannot start {argv[0]}: {exc.strerror or exc}") from None
            self.boots += 1
            self._reader = threading.Thread(
                target=self._pump, args=(self.proc,), name=f"px4-{self.instance}", daemon=True
            )
            self._reader.start()

    def _pump(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        with proc.stdout:
            for raw in iter(proc.stdout.readline, b""):
                line = re.sub(r"\x1b\[[0-9;]*m", "", raw.decode("utf-8", errors="replace")).rstrip()
                self.lines.append(line)
                if not self._ready.is_set() and any(mark in line for mark in READY_LINES):
                    self.boot_s = time.monotonic() - self.boot_start
                    self._ready.set()
                if self.output is not None:
                    try:
                        self.output(line)
                    except Exception:  # an observer's bug must not stop the pump
                        pass
        self._ready.set()  # wake a waiter: it sees the exit

    def wait_ready(self, timeout: float | None = None) -> float:
        """Block until px4 finished its start-up script; its boot time [s].  :class:`Px4SitlError`
        (with its last lines) when it exits or times out first."""
        timeout = self.ready_timeout if timeout is None else timeout
        if self.proc is None:
            raise Px4SitlError(f"PX4 SITL instance {self.instance} was never started")
        if not self._ready.wait(timeout):
            raise Px4SitlError(
                f"PX4 SITL instance {self.instance} not ready after {timeout:.0f} s; last lines:\n"
                + self.tail()
            )
        if self.boot_s is None or (not self.alive and self.proc.poll() is not None):
            # Its output ended: it exits; its status may take a moment to be there to reap.
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(5.0)
            raise Px4SitlError(
                f"PX4 SITL instance {self.instance} exited with status {self.proc.poll()} while starting;"
                f" last lines:\n{self.tail()}"
            )
        return self.boot_s

    def tail(self, n: int = 20) -> str:
        """PX4's last ``n`` lines."""
        return "\n".join(list(self.lines)[-n:])

    def wait(self, timeout: float | None = None) -> int | None:
        """Wait for px4 to exit (e.g. after a reboot command); its status, None on timeout."""
        if self.proc is None:
            return None
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout: float = 10.0, keep: bool = False) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``; the working directory is removed unless ``keep``.

        Returns px4's exit status (None if it never ran).  Idempotent.
        """
        with self._lock:
            code: int | None = None
            proc = self.proc
            if proc is not None:
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
                    try:
                        proc.wait(timeout)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait(5.0)
                code = proc.poll()
                if self._reader is not None:
                    self._reader.join(2.0)
            if not keep and self._root is not None:
                shutil.rmtree(self._root, ignore_errors=True)
                self._root = None
            return code

    def restart(self, timeout: float | None = None) -> float:
        """Stop px4 and boot it again with the same working directory (saved parameters); boot time."""
        self.stop(keep=True)
        self.start()
        return self.wait_ready(timeout)

    def __enter__(self) -> Px4Sitl:
        self.start()
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- PX4's own tools ---------------------------------------------------------------------------------
    def tool(self, name: str, *args: str, timeout: float = 10.0) -> subprocess.CompletedProcess[str]:
        """Run ``px4-<name> --instance N args…`` (``listener``, ``param``, ``commander``…) against it."""
        return run_tool(self.instance, name, *args, timeout=timeout, tools=self.tools)

    def listener(self, topic: str, timeout: float = 10.0) -> dict[str, ListenerValue]:
        """The latest message of uORB ``topic`` as PX4 prints it (see :func:`parse_listener`)."""
        return listener(self.instance, topic, timeout=timeout, tools=self.tools)

    def param(self, name: str, timeout: float = 10.0) -> float | None:
        """A parameter's current value, read with ``px4-param show`` (None when unknown)."""
        out = self.tool("param", "show", name, timeout=timeout).stdout
        for line in out.splitlines():
            m = re.search(rf"\b{re.escape(name)}\s*\[[^\]]*\]\s*:\s*(\S+)", line)
            if m:
                try:
                    return float(m.group(1))
                except ValueError:
                    return None
        return None


@contextlib.contextmanager
def _tool_dir(tools: Path | None) -> Iterator[Path]:
    if tools is not None:
        yield tools
        return
    with tempfile.TemporaryDirectory(prefix="px4-tools.") as tmp:
        yield link_tools(find_build(), Path(tmp) / "bin")


def run_tool(
    instance: int, name: str, *args: str, timeout: float = 10.0, tools: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """Run the build's ``px4-<name> --instance <instance> args…`` (a client of the running px4)."""
    if not re.fullmatch(r"[a-z0-9_]+", name):
        raise Px4SitlError(f"not a PX4 command name: {name!r}")
    with _tool_dir(tools) as d:
        exe = d / f"px4-{name}"
        if not exe.exists():
            raise Px4SitlError(f"the PX4 build has no command px4-{name}")
        try:
            return subprocess.run(
                [str(exe), "--instance", str(instance), *args],
                capture_output=True,
                text=True,
                timeout=timeout,
                stdin=subprocess.DEVNULL,
            )
        except subprocess.TimeoutExpired:
            raise Px4SitlError(
                f"px4-{name} --instance {instance} did not answer within {timeout} s"
            ) from None


def listener(
    instance: int, topic: str, timeout: float = 10.0, tools: Path | None = None
) -> dict[str, ListenerValue]:
    """``px4-listener --instance N topic`` parsed (the first message printed); :class:`Px4SitlError`
    when PX4 does not answer or the topic has never been published."""
    if not re.fullmatch(r"[a-z0-9_]+", topic):
        raise Px4SitlError(f"not a uORB topic name: {topic!r}")
    done = run_tool(instance, "listener", topic, timeout=timeout, tools=tools)
    messages = parse_listener(done.stdout)
    if not messages:
        text = (done.stdout + done.stderr).strip().splitlines()
        raise Px4SitlError(
            f"px4-listener --instance {instance} {topic}: no message (status {done.returncode}): "
            + (text[-1] if text else "no output")
        )
    return messages[0]


def is_true(message: Mapping[str, Any], key: str) -> bool:
    """A listener boolean (False when absent)."""
    return message.get(key) is True


def finite(value: Any) -> bool:
    """A listener number that is neither NaN nor infinite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def sitl_vehicle(cfg: ArenaConfig, vehicle: str) -> VehicleSpec:
    """The vehicle's spec; :class:`ConfigError` unless it is flown by a PX4 SITL instance."""
    spec = cfg.vehicle(vehicle)
    if not spec.px4_sitl or spec.px4_instance is None:
        raise ConfigError(
            f'{cfg.path}: vehicles.{vehicle}.autopilot is {spec.autopilot!r}, not "px4-sitl": '
            "no PX4 SITL instance to run for it"
        )
    return spec


def boot_params(cfg: ArenaConfig, spec: VehicleSpec) -> dict[str, float]:
    """The boot parameters of a PX4 SITL vehicle (``sim.px4_params`` preset, then its ``px4_params``)."""
    return arena_boot_params(cfg.sim.px4_params, spec.px4_params)
