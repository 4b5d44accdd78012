"""Where rigid-body poses come from: NatNet (Motive), the ``motioncapture`` package, or a Motive CSV take.

Every source has the same small interface (:class:`MocapSource`): ``open()``, ``poll(timeout)`` returning a
:class:`~arena_common.mocap.client.TimedFrame` or ``None``, ``close()``; problems are reported through
``on_reject(reason, detail)``, never raised from ``poll``. :func:`open_source` builds the one the config's
``mocap.source`` names:

- ``natnet``: :class:`~arena_common.mocap.client.NatNetClient`, the arena's own client.
- ``motioncapture``: IMRCLab's libmotioncapture (PyPI ``motioncapture``: VRPN, Vicon, Qualisys, OptiTrack…).
  Its calls block without a timeout *and hold the GIL* while they wait, so a thread cannot watch them: the
  library runs in a child process (``python -m arena_common.mocap.sources --worker``) that streams frames
  back through a pipe. Silence is loss; a child silent for too long is killed and started again.
- ``csv``: a Motive CSV take export, replayed at its original timing, for offline work.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import msgpack

from arena_common.core.config import ArenaConfig, MocapSpec
from arena_common.core.services import missing_extra
from arena_common.mocap.client import MocapError, NatNetClient, TimedFrame
from arena_common.mocap.natnet import RigidBody

__all__ = [
    "SOURCES",
    "CsvTake",
    "CsvTakeError",
    "CsvTakeSource",
    "MocapSource",
    "MotionCaptureSource",
    "SourceKind",
    "describe_source",
    "open_source",
    "read_csv_take",
]

log = logging.getLogger("arena.mocap")

RejectHook = Callable[[str, str], None]
CountHook = Callable[[str, int], None]
_IDENTITY = (0.0, 0.0, 0.0, 1.0)
_ORIGIN = (0.0, 0.0, 0.0)


class MocapSource(Protocol):
    """What the ingest service needs from a source of poses."""

    def open(self) -> Any:
        """Start (raise :class:`~arena_common.mocap.client.MocapError` if it cannot be set up at all)."""

    def poll(self, timeout: float = 0.1) -> TimedFrame | None:
        """The next frame, or ``None`` after ``timeout`` seconds; never raises on bad input."""

    def close(self) -> None:
        """Stop and release everything."""


# ------------------------------------------------------------------------------------------------------------
# Motive CSV takes
# ------------------------------------------------------------------------------------------------------------


class CsvTakeError(MocapError):
    """A file that is not a Motive CSV export this reader understands; names the file, row and column."""


@dataclass(frozen=True, slots=True)
class CsvTake:
    """A Motive CSV take: its metadata, rigid bodies (id, name) and frames ``(frame, seconds, bodies)``."""

    path: str
    metadata: dict[str, str]
    bodies: tuple[tuple[int, str], ...]
    frames: tuple[tuple[int, float, tuple[RigidBody, ...]], ...]

    @property
    def frame_rate(self) -> float | None:
        """The export frame rate the header states, if any."""
        for key in ("Export Frame Rate", "Capture Frame Rate"):
            try:
                return float(self.metadata[key])
            except (KeyError, ValueError):
                continue
        return None


_UNITS = {"meters": 1.0, "centimeters": 0.01, "millimeters": 0.001}


def _number(text: str, where: str) -> float | None:
    if text.strip() == "":
        return None
    try:
        value = float(text)
    except ValueError:
        raise CsvTakeError(f"{where}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        return None
    return value


def read_csv_take(path: str | Path) -> CsvTake:
    """Read the rigid bodies of a Motive CSV export (quaternion rotations; markers and skeletons ignored).

    The layout: a metadata row of ``key,value`` pairs (``Format Version``, ``Rotation Type``,
    ``Length Units``…), an optional blank row, the header rows ``Type``, ``Name``, ``ID``, the row saying
    ``Rotation``/``Position`` for each column, the row ``Frame,Time (Seconds),X,Y,Z,W,…``, then one row per
    frame. Blank cells (the body was not tracked) give an untracked pose. Raises :class:`CsvTakeError`.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise CsvTakeError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise CsvTakeError(f"{p}: not a text file") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise CsvTakeError(f"{p}: empty file")
    first = rows[0]
    metadata: dict[str, str] = {}
    if first and first[0].strip() == "Format Version":
        metadata = {first[i].strip(): first[i + 1].strip() for i in range(0, len(first) - 1, 2) if first[i]}
    rotation = metadata.get("Rotation Type", "Quaternion")
    if rotation.lower() != "quaternion":
        raise CsvTakeError(f"{p}: row 1: Rotation Type is {rotation!r}; export the take with quaternions")
    units = metadata.get("Length Units", "Meters")
    if units.lower() not in _UNITS:
        raise CsvTakeError(f"{p}: row 1: Length Units {units!r} not one of Meters, Centimeters, Millimeters")
    scale = _UNITS[units.lower()]

    header: dict[str, int] = {}
    frame_row = None
    for index, row in enumerate(rows[:20]):
        label = row[0].strip() if row else ""
        if label in ("Type", "Name", "ID"):
            header[label] = index
        elif label == "Frame":
            frame_row = index
            break
    if frame_row is None or "Type" not in header or "Name" not in header:
        raise CsvTakeError(f"{p}: no 'Type', 'Name' and 'Frame' header rows: not a Motive CSV export")
    kinds, names, axes = rows[header["Type"]], rows[header["Name"]], rows[frame_row]
    ids = rows[header["ID"]] if "ID" in header else []
    groups = rows[frame_row - 1]
    if len(axes) < 2 or axes[1].strip() != "Time (Seconds)":
        raise CsvTakeError(f"{p}: row {frame_row + 1}: expected 'Frame,Time (Seconds),…'")

    # For each rigid body, the columns of its quaternion (x, y, z, w) and position (x, y, z).
    columns: dict[str, dict[str, int]] = {}
    order: list[str] = []
    body_ids: dict[str, int] = {}
    for col in range(2, len(kinds)):
        if kinds[col].strip() != "Rigid Body" or col >= len(names):
            continue
        name = names[col].strip()
        group = groups[col].strip() if col < len(groups) else ""
        axis = axes[col].strip() if col < len(axes) else ""
        if name not in columns:
            columns[name] = {}
            order.append(name)
            raw_id = ids[col].strip() if col < len(ids) else ""
            try:
                body_ids[name] = int(raw_id)
            except ValueError:
                body_ids[name] = -len(order)  # Motive gave no numeric id: a stable negative one
        if group in ("Rotation", "Position") and axis in ("X", "Y", "Z", "W"):
            columns[name][f"{group[0]}{axis}"] = col
        elif group == "Mean Marker Error":
            columns[name]["E"] = col
    if not columns:
        raise CsvTakeError(f"{p}: no rigid body columns (export the take with rigid bodies)")
    wanted = ("RX", "RY", "RZ", "RW", "PX", "PY", "PZ")
    for name, cols in columns.items():
        missing = [k for k in wanted if k not in cols]
        if missing:
            raise CsvTakeError(
                f"{p}: rigid body {name!r}: no {', '.join(missing)} column (Rotation X Y Z W, Position X Y Z)"
            )

    frames: list[tuple[int, float, tuple[RigidBody, ...]]] = []
    for index in range(frame_row + 1, len(rows)):
        row = rows[index]
        if not row or all(c.strip() == "" for c in row):
            continue
        where = f"{p}: row {index + 1}"
        try:
            number = int(row[0])
        except ValueError:
            raise CsvTakeError(f"{where}: frame number {row[0]!r} is not an integer") from None
        seconds = _number(row[1], f"{where}, column 2") if len(row) > 1 else None
        if seconds is None:
            raise CsvTakeError(f"{where}: no time")
        bodies = []
        for name in order:
            cols = columns[name]
            values = [
                _number(row[c], f"{where}, column {c + 1}") if c < len(row) else None
                for c in (cols[k] for k in wanted)
            ]
            error = None
            if "E" in cols and cols["E"] < len(row):
                error = _number(row[cols["E"]], f"{where}, column {cols['E'] + 1}")
            if any(v is None for v in values):
                bodies.append(RigidBody(body_ids[name], _ORIGIN, _IDENTITY, error, False, 0))
                continue
            qx, qy, qz, qw, px, py, pz = (float(v) for v in values)  # type: ignore[arg-type]
            pos = (px * scale, py * scale, pz * scale)
            bodies.append(RigidBody(body_ids[name], pos, (qx, qy, qz, qw), error, True, 1))
        frames.append((number, seconds, tuple(bodies)))
    if not frames:
        raise CsvTakeError(f"{p}: no frames after the header")
    return CsvTake(str(p), metadata, tuple((body_ids[n], n) for n in order), tuple(frames))


class CsvTakeSource:
    """Replays a Motive CSV take at its original timing (``speed`` times faster), once or in a loop.

    Each frame's ``t`` is the wall-clock time it is due (``tsrc="arrival"``), ``mts`` its time in the take.
    When the take is over, :attr:`finished` is true and :meth:`poll` returns ``None``.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        speed: float = 1.0,
        loop: bool = False,
        on_reject: RejectHook | None = None,
        on_count: CountHook | None = None,
    ) -> None:
        if speed <= 0:
            raise MocapError(f"replay speed must be positive, got {speed}")
        self.path = Path(path)
        self.speed = speed
        self.loop = loop
        self.on_reject = on_reject
        self.on_count = on_count
        self.take: CsvTake | None = None
        self.finished = False
        self._names: dict[int, str] = {}
        self._index = 0
        self._start_mono = 0.0
        self._start_wall = 0
        self._t0 = 0.0
        self._laps = 0

    def open(self) -> CsvTakeSource:
        """Read the take (raise :class:`CsvTakeError` if it is not one) and start the clock."""
        self.take = read_csv_take(self.path)
        self._names = {bid: name for bid, name in self.take.bodies}
        self._restart()
        return self

    def _restart(self) -> None:
        assert self.take is not None
        self._index = 0
        self._t0 = self.take.frames[0][1]
        self._start_mono = time.monotonic()
        self._start_wall = time.time_ns()

    def poll(self, timeout: float = 0.1) -> TimedFrame | None:
        """The next frame when it is due, or ``None`` after ``timeout`` seconds."""
        take = self.take
        if take is None or self.finished:
            time.sleep(timeout)
            return None
        if self._index >= len(take.frames):
            if not self.loop:
                self.finished = True
                log.info("take %s finished (%d frames)", self.path.name, len(take.frames))
                return None
            self._laps += 1
            self._restart()
        number, seconds, bodies = take.frames[self._index]
        offset = (seconds - self._t0) / self.speed
        wait = self._start_mono + offset - time.monotonic()
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        self._index += 1
        t = self._start_wall + round(offset * 1e9)
        if self.on_count is not None:
            self.on_count("frames", 1)
        return TimedFrame(number, bodies, t, "arrival", -1, seconds, time.time_ns(), self._names, 1)

    def close(self) -> None:
        """Nothing to release; the take stays readable."""
        self.finished = True


# ------------------------------------------------------------------------------------------------------------
# The motioncapture package, in a child process
# ------------------------------------------------------------------------------------------------------------


def motioncapture_params(spec: MocapSpec) -> tuple[str, dict[str, str]]:
    """The ``motioncapture.connect`` type and parameters for the config's mocap section."""
    kind = spec.motioncapture_type
    params = {"hostname": spec.server}
    if kind == "optitrack":
        params.update(port_command=str(spec.command_port), interface_ip=spec.interface)
    return kind, params


class MotionCaptureSource:
    """Poses from ``motioncapture.connect(kind, params)``, read by a child process.

    The child writes one msgpack record per frame (``[arrival ns, [[name, x, y, z, qw, qx, qy, qz], …]]``)
    to a pipe. No frame for ``loss_timeout`` is reported as ``no_data``; a child silent for ``restart_after``
    seconds (stuck in a connect that never returns), or one that exits, is started again with back-off.
    The library gives names, not ids: bodies get stable negative ids in the order they first appear, and a
    body seen before but missing from a frame is reported untracked.
    """

    def __init__(
        self,
        kind: str,
        params: dict[str, str],
        *,
        loss_timeout: float = 1.0,
        restart_after: float = 5.0,
        max_backoff: float = 5.0,
        on_reject: RejectHook | None = None,
        on_count: CountHook | None = None,
    ) -> None:
        self.kind = kind
        self.params = dict(params)
        self.loss_timeout = loss_timeout
        self.restart_after = restart_after
        self.max_backoff = max_backoff
        self.on_reject = on_reject
        self.on_count = on_count
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0
        self.frames = 0
        self._unpacker = msgpack.Unpacker(raw=False)
        self._pending: list[Any] = []
        self._ids: dict[str, int] = {}
        self._names: dict[int, str] = {}
        self._models = 0
        self._last_data = 0.0
        self._lost = False
        self._backoff = 0.5
        self._next_start = 0.0
        self._stderr_tail = b""

    def _reject(self, reason: str, detail: str) -> None:
        if self.on_reject is not None:
            self.on_reject(reason, detail)
        else:
            log.warning("%s: %s", reason, detail)

    def open(self) -> MotionCaptureSource:
        """Check the library is installed and start the child."""
        why = missing_extra("mocap")
        if why:
            raise MocapError(f"mocap.source = 'motioncapture': {why}")
        self._start()
        return self

    def _start(self) -> None:
        self._stop_child()
        cmd = [
            sys.executable,
            "-m",
            "arena_common.mocap.sources",
            "--worker",
            self.kind,
            json.dumps(self.params),
        ]
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        for stream in (self.proc.stdout, self.proc.stderr):
            assert stream is not None
            os.set_blocking(stream.fileno(), False)
        self._unpacker = msgpack.Unpacker(raw=False)
        self._pending = []
        self._stderr_tail = b""
        self.starts += 1
        self._last_data = time.monotonic()
        if self.on_count is not None:
            self.on_count("worker_start", 1)

    def _stop_child(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.kill()  # it may be blocked inside the library: SIGTERM would wait for the GIL
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=2.0)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()

    def poll(self, timeout: float = 0.1) -> TimedFrame | None:
        """The next frame, or ``None`` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            if self._pending:
                return self._frame(self._pending.pop(0))
            now = time.monotonic()
            proc = self.proc
            if proc is None or proc.poll() is not None:
                if proc is not None:
                    tail = self._stderr_tail.decode("utf-8", "replace").strip().splitlines()
                    last = tail[-1] if tail else "no message"
                    self._reject("worker_exit", f"motioncapture child exited ({proc.returncode}): {last}")
                    self._stop_child()
                    self._next_start = now + self._backoff
                    self._backoff = min(self._backoff * 2, self.max_backoff)
                if now >= self._next_start:
                    self._start()
                    continue
                time.sleep(max(0.0, min(deadline, self._next_start) - now))
                if time.monotonic() >= deadline:
                    return None
                continue
            silent = now - self._last_data
            if silent > self.loss_timeout and not self._lost:
                self._lost = True
                self._reject("no_data", f"no frame from {self.kind} for {silent:.1f} s")
            if silent > self.restart_after:
                self._reject("worker_restart", f"{self.kind} silent for {silent:.1f} s: restarting its child")
                self._stop_child()
                self._next_start = now + self._backoff
                self._backoff = min(self._backoff * 2, self.max_backoff)
                continue
            assert proc.stdout is not None and proc.stderr is not None
            wait = max(0.0, min(deadline, self._last_data + self.loss_timeout + 0.001) - now)
            ready, _, _ = select.select([proc.stdout, proc.stderr], [], [], wait)
            for stream in ready:
                chunk = os.read(stream.fileno(), 65536)
                if stream is proc.stderr:
                    self._stderr_tail = (self._stderr_tail + chunk)[-2048:]
                    continue
                self._unpacker.feed(chunk)
                for record in self._unpacker:
                    self._pending.append(record)
            if not self._pending and time.monotonic() >= deadline:
                return None

    def _frame(self, record: Any) -> TimedFrame | None:
        try:
            arrival, items = int(record[0]), record[1]
            seen: dict[int, RigidBody] = {}
            for name, x, y, z, qw, qx, qy, qz in items:
                bid = self._ids.get(name)
                if bid is None:
                    bid = self._ids[name] = -(len(self._ids) + 1)
                    self._names = {v: k for k, v in self._ids.items()}
                    self._models += 1
                ok = all(math.isfinite(v) for v in (x, y, z, qw, qx, qy, qz))
                pos, quat = ((x, y, z), (qx, qy, qz, qw)) if ok else (_ORIGIN, _IDENTITY)
                seen[bid] = RigidBody(bid, pos, quat, None, ok, 1 if ok else 0)
        except (TypeError, ValueError, IndexError) as exc:
            self._reject("bad_record", f"motioncapture child sent {record!r:.80}: {exc}")
            return None
        self._last_data = time.monotonic()
        self._lost = False
        self._backoff = 0.5
        self.frames += 1
        bodies = tuple(
            seen.get(bid) or RigidBody(bid, _ORIGIN, _IDENTITY, None, False, 0) for bid in self._names
        )
        return TimedFrame(
            self.frames, bodies, arrival, "arrival", -1, 0.0, arrival, self._names, self._models
        )

    def close(self) -> None:
        """Stop the child."""
        self._stop_child()


def _worker(kind: str, params_json: str) -> int:
    """Child process: connect with the motioncapture library, write each frame to the parent, forever."""
    out = os.dup(1)
    os.dup2(2, 1)  # the library prints on stdout: keep the frame pipe clean
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    import motioncapture

    params = json.loads(params_json)
    mc = motioncapture.connect(kind, params)
    pack = msgpack.Packer()
    with os.fdopen(out, "wb", buffering=0) as pipe:
        while True:
            mc.waitForNextFrame()
            arrival = time.time_ns()
            items = []
            for name, body in mc.rigidBodies.items():
                p, q = body.position, body.rotation
                items.append([name, float(p[0]), float(p[1]), float(p[2]), q.w, q.x, q.y, q.z])
            pipe.write(pack.pack([arrival, items]))


# ------------------------------------------------------------------------------------------------------------
# From the config
# ------------------------------------------------------------------------------------------------------------


def resolve_csv(cfg: ArenaConfig) -> Path:
    """``mocap.csv_file``: absolute, else relative to the config file, else to the working directory."""
    name = cfg.mocap.csv_file
    if not name:
        raise MocapError(f"{cfg.path}: mocap.source = 'csv' needs mocap.csv_file")
    p = Path(name)
    if p.is_absolute():
        return p
    beside = Path(cfg.path).parent / p
    return beside if beside.exists() else p


@dataclass(frozen=True, slots=True)
class SourceKind:
    """One kind of ``mocap.source``: how to build it from the config, and how to say where it reads."""

    build: Callable[[ArenaConfig, RejectHook | None, CountHook | None, float], MocapSource]
    describe: Callable[[ArenaConfig], str]


def _natnet(
    cfg: ArenaConfig, on_reject: RejectHook | None, on_count: CountHook | None, loss: float
) -> MocapSource:
    m = cfg.mocap
    return NatNetClient(
        m.server,
        command_port=m.command_port,
        interface=m.interface,
        multicast=m.multicast,
        group=m.group if m.multicast else None,
        data_port=m.data_port,
        loss_timeout=loss,
        on_reject=on_reject,
        on_count=on_count,
    )


def _motioncapture(
    cfg: ArenaConfig, on_reject: RejectHook | None, on_count: CountHook | None, loss: float
) -> MocapSource:
    kind, params = motioncapture_params(cfg.mocap)
    return MotionCaptureSource(kind, params, loss_timeout=loss, on_reject=on_reject, on_count=on_count)


def _natnet_where(cfg: ArenaConfig) -> str:
    m = cfg.mocap
    mode = f"multicast {m.group}:{m.data_port}" if m.multicast else "unicast"
    return f"server {m.server}:{m.command_port}, {mode}, interface {m.interface}"


#: Every ``mocap.source``, by name.
SOURCES: dict[str, SourceKind] = {
    "natnet": SourceKind(_natnet, _natnet_where),
    "motioncapture": SourceKind(
        _motioncapture, lambda c: f"{c.mocap.motioncapture_type} at {c.mocap.server}"
    ),
    "csv": SourceKind(
        lambda c, r, n, _loss: CsvTakeSource(resolve_csv(c), on_reject=r, on_count=n),
        lambda c: c.mocap.csv_file,
    ),
}


def _kind(cfg: ArenaConfig) -> SourceKind:
    kind = SOURCES.get(cfg.mocap.source)
    if kind is None:
        raise MocapError(
            f"{cfg.path}: unknown mocap.source {cfg.mocap.source!r} (known: {', '.join(SOURCES)})"
        )
    return kind


def open_source(
    cfg: ArenaConfig,
    *,
    on_reject: RejectHook | None = None,
    on_count: CountHook | None = None,
    loss_timeout: float = 1.0,
) -> MocapSource:
    """Build the source ``cfg.mocap.source`` names (not opened yet)."""
    return _kind(cfg).build(cfg, on_reject, on_count, loss_timeout)


def describe_source(cfg: ArenaConfig) -> str:
    """Where the configured source reads (``server 10.0.0.5:1510, multicast 239.255.42.99:1511, …``)."""
    return _kind(cfg).describe(cfg)


if __name__ == "__main__":
    args = sys.argv[1:]
    if len(args) == 3 and args[0] == "--worker":
        sys.exit(_worker(args[1], args[2]))
    sys.stderr.write("usage: python -m arena_common.mocap.sources --worker TYPE PARAMS_JSON\n")
    sys.exit(2)
