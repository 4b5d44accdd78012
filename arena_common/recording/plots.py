"""Figures of a recording (PNG, matplotlib without a display): what a flight looked like.

:func:`plot_recording` writes, into a directory:

- ``paths_top.png`` — every vehicle's path seen from above (North up, East right) inside the arena's
  walls and its safety margin, taken from the config stored in the recording;
- ``paths_side.png`` — the same from the side: North–height and East–height;
- per vehicle ``<d>_position.png`` (north, east, height vs time: mocap pose, the autopilot's estimate
  from ``state``, the setpoints), ``<d>_attitude.png`` (roll, pitch, yaw: pose vs estimate),
  ``<d>_tracking.png`` (setpoint minus pose, per axis and its norm), ``<d>_vision.png`` (vision
  messages per second on the bus and as the gateway reports it, and their age), ``<d>_battery.png``.

A figure whose data is absent from the recording is not written.  Times are seconds since the
recording's first message.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from arena_common.core import config as config_mod
from arena_common.core import keys
from arena_common.core.errors import ConfigError, InvalidName
from arena_common.geometry import frames
from arena_common.recording.mcap import NS, RecordingError, Series, load_series

DPI = 100
COLORS = (
    "tab:blue",
    "tab:orange",
    "tab:green",
    "tab:red",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
)


def arena_of(meta: dict[str, str]) -> config_mod.ArenaSpec:
    """The arena of the config stored in a recording's metadata (the default arena without one)."""
    text = meta.get("config", "")
    if not text:
        return config_mod.ArenaSpec()
    try:
        return config_mod.parse(tomllib.loads(text), meta.get("config_path") or "<recorded config>").arena
    except (tomllib.TOMLDecodeError, ConfigError):
        return config_mod.ArenaSpec()


def _vec(maps: Sequence[dict[str, Any]], name: str, n: int) -> np.ndarray:
    out = np.full((len(maps), n), np.nan)
    for i, m in enumerate(maps):
        v = m.get(name)
        if isinstance(v, list) and len(v) == n:
            out[i] = [np.nan if x is None else x for x in v]
    return out


def _scalar(maps: Sequence[dict[str, Any]], name: str) -> np.ndarray:
    out = np.full(len(maps), np.nan)
    for i, m in enumerate(maps):
        v = m.get(name)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = v
    return out


def _euler_deg(q: np.ndarray) -> np.ndarray:
    out = np.full((len(q), 3), np.nan)
    for i, row in enumerate(q):
        if np.all(np.isfinite(row)) and abs(float(np.linalg.norm(row)) - 1.0) < 0.01:
            out[i] = np.degrees(frames.quat_to_euler(tuple(row)))
    return out


def _break_wraps(t: np.ndarray, deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert a gap where an angle wraps at ±180° so the line does not cross the whole plot."""
    jumps = np.flatnonzero(np.abs(np.diff(deg)) > 180.0) + 1
    return np.insert(t, jumps, np.nan), np.insert(deg, jumps, np.nan)


class _Vehicle:
    """The series of one vehicle, as arrays."""

    def __init__(self, name: str, series: dict[str, Series], t0: int) -> None:
        self.name = name

        def get(leaf: str) -> tuple[np.ndarray, list[dict[str, Any]]]:
            s = series.get(f"{keys.ROOT}/{name}/{leaf}")
            if s is None:
                return np.zeros(0), []
            return (np.asarray(s.log_time, dtype=np.int64) - t0) / NS, s.maps

        vision_series = series.get(f"{keys.ROOT}/{name}/vision")

        self.pose_t, pose = get("pose")
        ok = np.array([bool(m.get("ok", True)) for m in pose], dtype=bool)
        self.pose_p = _vec(pose, "p", 3)
        self.pose_q = _vec(pose, "q", 4)
        self.pose_p[~ok] = np.nan
        self.pose_q[~ok] = np.nan
        self.truth_t, truth = get("truth")
        self.truth_p = _vec(truth, "p", 3)
        self.vision_t, vision = get("vision")
        # Age of each vision sample when the recorder got it: integer ns, exact before the subtraction.
        self.vision_age_ms = np.array(
            [(lt - int(m.get("t", lt))) / 1e6 for lt, m in zip(vision_series.log_time, vision, strict=True)]
            if vision_series is not None
            else []
        )
        self.state_t, state = get("state")
        self.state_p = _vec(state, "p", 3)
        self.state_q = _vec(state, "q", 4)
        self.bat = _scalar(state, "bat")
        self.volt = _scalar(state, "volt")
        self.vis_rate = _scalar(state, "vis_rate")
        self.vis_age = _scalar(state, "vis_age")
        self.armed = np.array([bool(m.get("armed", False)) for m in state], dtype=bool)
        self.sp_t, sp = get("setpoint")
        self.sp_p = _vec(sp, "p", 3)

    def path(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The best position track: mocap pose, else the simulated truth, else the estimate."""
        for t, p in ((self.pose_t, self.pose_p), (self.truth_t, self.truth_p), (self.state_t, self.state_p)):
            if len(t) and np.isfinite(p).any():
                return t, p
        return None


def _outline(
    ax: Axes, walls: tuple[tuple[float, float], tuple[float, float]], safe: tuple[tuple[float, float], ...]
) -> None:
    """The room's walls (solid) and the volume the gateways allow (dashed)."""
    (x0, x1), (y0, y1) = walls
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=2.0, color="black"))
    (sx0, sx1), (sy0, sy1) = safe
    ax.add_patch(Rectangle((sx0, sy0), sx1 - sx0, sy1 - sy0, fill=False, lw=1.0, ls="--", color="gray"))
    pad = 0.3
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)


def _save(fig: Figure, path: Path, written: list[Path]) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    written.append(path)


def _paths(
    vehicles: list[_Vehicle], arena: config_mod.ArenaSpec, name: str, out: Path, written: list[Path]
) -> None:
    n, e, h = arena.size
    tracks: list[tuple[_Vehicle, tuple[np.ndarray, np.ndarray]]] = []
    for v in vehicles:
        track = v.path()
        if track is not None:
            tracks.append((v, track))
    if not tracks:
        return
    (sn0, sn1), (se0, se1), (sd0, sd1) = arena.safe_box()
    safe_height = (-sd1, -sd0)
    fig = Figure(figsize=(6 + 2 * e / n, 8))
    ax = fig.add_subplot()
    _outline(ax, ((-e / 2, e / 2), (-n / 2, n / 2)), ((se0, se1), (sn0, sn1)))
    for i, (v, (_, p)) in enumerate(tracks):
        c = COLORS[i % len(COLORS)]
        ax.plot(p[:, 1], p[:, 0], color=c, lw=1.2, label=v.name)
        good = np.flatnonzero(np.isfinite(p[:, 0]))
        if len(good):
            ax.plot(p[good[0], 1], p[good[0], 0], "o", color=c, ms=7)
            ax.plot(p[good[-1], 1], p[good[-1], 0], "x", color=c, ms=9, mew=2)
    ax.set_xlabel("East [m]")
    ax.set_ylabel("North [m]")
    ax.set_title(f"{name}: paths from above (o start, x end; dashed: safety margin)", fontsize=10)
    ax.legend(loc="upper right")
    _save(fig, out / "paths_top.png", written)

    fig = Figure(figsize=(12, 5))
    sides = ((0, "North [m]", n, (sn0, sn1)), (1, "East [m]", e, (se0, se1)))
    for j, (axis, label, width, safe) in enumerate(sides):
        ax = fig.add_subplot(1, 2, j + 1)
        _outline(ax, ((-width / 2, width / 2), (0.0, h)), (safe, safe_height))
        for i, (v, (_, p)) in enumerate(tracks):
            ax.plot(p[:, axis], -p[:, 2], color=COLORS[i % len(COLORS)], lw=1.2, label=v.name)
        ax.set_xlabel(label)
        ax.set_ylabel("Height [m]")
        ax.set_title(f"side view, looking {'east' if axis == 0 else 'north'}")
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", ncol=len(labels))
    fig.suptitle(f"{name}: paths from the side (dashed: where the gateways allow setpoints)")
    _save(fig, out / "paths_side.png", written)


def _position(v: _Vehicle, out: Path, written: list[Path]) -> None:
    if not (len(v.pose_t) or len(v.state_t)):
        return
    fig = Figure(figsize=(11, 8))
    labels = ("north [m]", "east [m]", "height [m]")
    sign = (1.0, 1.0, -1.0)
    for j in range(3):
        ax = fig.add_subplot(3, 1, j + 1)
        if len(v.pose_t):
            ax.plot(v.pose_t, sign[j] * v.pose_p[:, j], lw=1.0, label="mocap pose")
        if len(v.state_t) and np.isfinite(v.state_p).any():
            ax.plot(v.state_t, sign[j] * v.state_p[:, j], lw=1.0, ls="--", label="autopilot estimate")
        if len(v.sp_t) and np.isfinite(v.sp_p).any():
            ax.plot(v.sp_t, sign[j] * v.sp_p[:, j], lw=0.8, ls=":", color="black", label="setpoint")
        ax.set_ylabel(labels[j])
        ax.grid(True, alpha=0.3)
        if j == 0:
            ax.legend(loc="upper right", ncol=3)
    ax.set_xlabel("time [s]")
    fig.suptitle(f"{v.name}: position, mocap vs autopilot estimate")
    _save(fig, out / f"{v.name}_position.png", written)


def _attitude(v: _Vehicle, out: Path, written: list[Path]) -> None:
    has_pose = len(v.pose_t) and np.isfinite(v.pose_q).any()
    has_state = len(v.state_t) and np.isfinite(v.state_q).any()
    if not (has_pose or has_state):
        return
    fig = Figure(figsize=(11, 8))
    pe = _euler_deg(v.pose_q) if has_pose else None
    se = _euler_deg(v.state_q) if has_state else None
    for j, label in enumerate(("roll [deg]", "pitch [deg]", "yaw [deg]")):
        ax = fig.add_subplot(3, 1, j + 1)
        if pe is not None:
            ax.plot(*_break_wraps(v.pose_t, pe[:, j]), lw=1.0, label="mocap pose")
        if se is not None:
            ax.plot(*_break_wraps(v.state_t, se[:, j]), lw=1.0, ls="--", label="autopilot estimate")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        if j == 0:
            ax.legend(loc="upper right", ncol=2)
    ax.set_xlabel("time [s]")
    fig.suptitle(f"{v.name}: attitude, mocap vs autopilot estimate")
    _save(fig, out / f"{v.name}_attitude.png", written)


def _tracking(v: _Vehicle, out: Path, written: list[Path]) -> None:
    if not (len(v.sp_t) and np.isfinite(v.sp_p).any()):
        return
    track = v.path()
    if track is None:
        return
    t, p = track
    good = np.all(np.isfinite(p), axis=1)
    if good.sum() < 2:
        return
    inside = (v.sp_t >= t[good][0]) & (v.sp_t <= t[good][-1]) & np.all(np.isfinite(v.sp_p), axis=1)
    if not inside.any():
        return
    st = v.sp_t[inside]
    actual = np.column_stack([np.interp(st, t[good], p[good, j]) for j in range(3)])
    err = v.sp_p[inside] - actual
    norm = np.linalg.norm(err, axis=1)
    fig = Figure(figsize=(11, 6))
    ax = fig.add_subplot(2, 1, 1)
    for j, label in enumerate(("north", "east", "down")):
        ax.plot(st, err[:, j], lw=1.0, label=label)
    ax.set_ylabel("setpoint − pose [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", ncol=3)
    ax = fig.add_subplot(2, 1, 2)
    ax.plot(st, norm, lw=1.0, color="black")
    ax.set_ylabel("|error| [m]")
    ax.set_xlabel("time [s]")
    ax.grid(True, alpha=0.3)
    ax.set_title(
        f"mean {np.mean(norm):.3f} m, 95 % {np.percentile(norm, 95):.3f} m, max {np.max(norm):.3f} m"
    )
    fig.suptitle(f"{v.name}: setpoint tracking error")
    _save(fig, out / f"{v.name}_tracking.png", written)


def _vision(v: _Vehicle, out: Path, written: list[Path]) -> None:
    has_bus = len(v.vision_t) > 1
    has_state = len(v.state_t) and (np.isfinite(v.vis_rate).any() or np.isfinite(v.vis_age).any())
    if not (has_bus or has_state):
        return
    fig = Figure(figsize=(11, 6))
    ax = fig.add_subplot(2, 1, 1)
    if has_bus:
        edges = np.arange(math.floor(v.vision_t[0]), math.ceil(v.vision_t[-1]) + 1.0, 1.0)
        if len(edges) > 1:
            counts, _ = np.histogram(v.vision_t, bins=edges)
            ax.step(edges[1:], counts, where="pre", label="vision on the bus (per 1 s)")
    if has_state:
        ax.plot(v.state_t, v.vis_rate, lw=1.0, ls="--", label="sent to the autopilot (gateway)")
    ax.set_ylabel("rate [Hz]")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right")
    ax = fig.add_subplot(2, 1, 2)
    if has_bus:
        ax.plot(v.vision_t, v.vision_age_ms, ".", ms=2, label="receive − measurement time (recorder)")
    if has_state and np.isfinite(v.vis_age).any():
        ax.plot(v.state_t, v.vis_age * 1e3, lw=1.0, label="age of the last vision sent (gateway)")
    ax.set_ylabel("age [ms]")
    ax.set_xlabel("time [s]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right")
    fig.suptitle(f"{v.name}: vision rate and age")
    _save(fig, out / f"{v.name}_vision.png", written)


def _battery(v: _Vehicle, out: Path, written: list[Path]) -> None:
    has_bat = np.isfinite(v.bat).any()
    has_volt = np.isfinite(v.volt).any()
    if not (has_bat or has_volt):
        return
    fig = Figure(figsize=(11, 4.5))
    ax = fig.add_subplot()
    if has_bat:
        ax.plot(v.state_t, 100 * v.bat, color="tab:green", label="remaining")
        ax.axhline(15, color="tab:orange", ls=":", lw=1, label="warn 15 %")
        ax.axhline(7, color="tab:red", ls=":", lw=1, label="land 7 %")
        ax.set_ylabel("remaining [%]")
        ax.set_ylim(0, 100)
    if has_volt:
        ax2 = ax.twinx() if has_bat else ax
        ax2.plot(v.state_t, v.volt, color="tab:blue", lw=1.0, label="voltage (right axis)")
        ax2.set_ylabel("voltage [V]")
    handles: list[Any] = []
    labels: list[str] = []
    for a in fig.axes:
        hs, ls = a.get_legend_handles_labels()
        handles, labels = handles + hs, labels + ls
    ax.legend(handles, labels, loc="lower left")
    ax.set_xlabel("time [s]")
    ax.grid(True, alpha=0.3)
    fig.suptitle(f"{v.name}: battery")
    _save(fig, out / f"{v.name}_battery.png", written)


def vehicles_in(series: dict[str, Series]) -> list[str]:
    """Vehicle names of the keys present, sorted."""
    names: set[str] = set()
    for key in series:
        try:
            parsed = keys.parse(key)
        except InvalidName:
            continue
        if parsed.drone:
            names.add(parsed.drone)
    return sorted(names)


def plot_recording(path: str | Path, out_dir: str | Path) -> list[Path]:
    """Write the figures of a recording into ``out_dir``; returns the files written."""
    exprs = [f"{keys.ROOT}/*/{leaf}" for leaf in ("pose", "truth", "vision", "state", "setpoint")]
    series, meta = load_series(path, exprs)
    if not series:
        raise RecordingError(f"{path}: no pose, state, vision or setpoint to plot")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"{out}: cannot create: {exc.strerror or exc}") from None
    t0 = min(s.log_time[0] for s in series.values() if s.log_time)
    arena = arena_of(meta)
    vehicles = [_Vehicle(n, series, t0) for n in vehicles_in(series)]
    written: list[Path] = []
    _paths(vehicles, arena, arena.name, out, written)
    for v in vehicles:
        _position(v, out, written)
        _attitude(v, out, written)
        _tracking(v, out, written)
        _vision(v, out, written)
        _battery(v, out, written)
    return written
