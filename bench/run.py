"""``make bench``: how fast the arena is, against the transport's floor and against a peer.

Parts (each optional, see :class:`BenchOptions`):

- ``pipeline`` — the real vision pipeline end to end on loopback (Motive emulator → ingest → transform →
  downsampler → gateway, one process each, one downsampler and gateway per vehicle) at every load point
  (vehicles × mocap rate): NatNet frame leaving the emulator → its ODOMETRY leaving the gateway, p50, p99,
  p99.9, max, messages lost, poses per second per vehicle, and every process's CPU and memory
  (:mod:`bench.pipeline`); at every vehicle count one more point as deployed (vision 50 Hz), and at the
  largest that point again with CPU hogs overloading the machine;
- ``floor`` — the same process topology moving bytes only, over Zenoh and over UDP, at the same loads
  (:mod:`bench.floor_run`);
- ``peer`` — the gateway beside its Zenoh and UDP floors and MAVProxy forwarding the same vision stream,
  each measured several times in alternating order (:mod:`bench.peer`);
- ``micro`` — per-stage costs in one process (:mod:`bench.micro`).

:func:`run` prints rich tables as parts finish, writes ``<out>/bench-<time>.json`` and ``<out>/latest.json``
and, unless told not to, puts the tables into ``docs/performance.md`` between its generated-block markers.
Loads are measured one after the other, never together; the machine's load average is recorded with
them because a shared machine's figures are only as good as its idleness.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from rich.console import Console

from bench import flames
from bench.floor_run import run_floor
from bench.harness import BenchError, ProcessSet
from bench.pipeline import CHAINS, PointResult, RunSettings, run_arena
from bench.report import (
    GROWTH_HEADER,
    HOPS_HEADER,
    LATENCY_HEADER,
    PEER_HEADER,
    RESOURCE_HEADER,
    VEHICLE_ROLES,
    Target,
    _f,
    _rich,
    evaluate_targets,
    growth_point,
    growth_rows,
    hop_rows,
    latency_rows,
    markdown_report,
    micro_rows,
    peer_rows,
    resource_rows,
    sweep_header,
    sweep_rows,
    target_rows,
    update_docs,
)

__all__ = [
    "PARTS",
    "BenchError",
    "BenchOptions",
    "Target",
    "evaluate_targets",
    "markdown_report",
    "run",
    "update_docs",
]

PARTS = ("pipeline", "floor", "peer", "micro")
FLOORS = ("zenoh", "udp")


@dataclass(frozen=True)
class BenchOptions:
    """What to measure and for how long."""

    parts: tuple[str, ...] = PARTS
    vehicles: tuple[int, ...] = (1, 20)
    rates: tuple[float, ...] = (180.0,)
    floors: tuple[str, ...] = FLOORS
    duration: float = 3.0  # s measured per load point
    warmup: float = 1.0  # s of flow before each measurement
    idle: float = 1.0  # s of idle CPU measured per process set (0: skip)
    peer_rate: float = 200.0  # Hz of vision in the peer comparison
    peer_duration: float = 2.5  # s per run of each forwarder
    peer_repeats: int = 3  # runs of each forwarder (alternating order): median and spread
    peer_sweep: tuple[float, ...] = (1000.0, 4000.0)  # Hz: one short run of each forwarder at each
    micro_scale: float = 1.0  # loop lengths of the micro-benchmarks (1 = full)
    out_dir: Path = Path("bench-results")
    docs: Path | None = Path("docs/performance.md")
    repo: Path = Path(".")
    profile: bool = False  # py-spy the services during each pipeline measurement
    hops: bool = False  # per-stage latency of the first vehicle (one more subscriber on its keys)
    realistic_vision: float | None = 50.0  # Hz: one more point per vehicle count with this vision rate
    overload: int = 2  # CPU hogs beside the deployed point at the largest load, measured again (0: skip)
    decimate: tuple[str, ...] = tuple(CHAINS)  # the pipeline configurations measured ([pipeline] decimate)
    vehicle_mode: str = ""  # zenoh.vehicle_mode of the pipeline's config ("": the config's default)
    fleet: int = 50  # vehicles of the fleet point: deployed vision only, every configuration, per-vehicle
    # processes as clients of the router unless vehicle_mode says otherwise (0: skip)
    fleet_settle: float = 5.0  # s after the fleet's services came up before its idle window
    # Vehicle counts of the growth table: each deployed as the fleet is (the fleet's own point reused), so
    # that the cost per vehicle reads across fleet sizes (() or 0: skip)
    growth: tuple[int, ...] = (1, 10, 20, 50)
    gateway_hosts: int = 0  # processes the fleet's gateways run in (0: one per vehicle, as deployed)
    gateway_vision: str = "frame"  # how those processes get vision: one message per frame, or per vehicle
    quick: bool = False

    @classmethod
    def quick_options(cls, **changes: Any) -> BenchOptions:
        """Short runs at 1 and 10 vehicles, 180 Hz: a check that everything works, not figures."""
        base = cls(
            vehicles=(1, 10),
            rates=(180.0,),
            duration=2.0,
            warmup=1.0,
            idle=1.0,
            peer_duration=1.0,
            peer_repeats=1,
            peer_sweep=(1000.0,),
            micro_scale=0.2,
            fleet=0,
            growth=(),
            quick=True,
        )
        return replace(base, **changes)

    def check(self) -> None:
        """Raise :class:`BenchError` on options that cannot run."""
        unknown = [p for p in self.parts if p not in PARTS]
        if unknown:
            raise BenchError(f"unknown part {unknown[0]!r} (parts: {', '.join(PARTS)})")
        bad_floor = [f for f in self.floors if f not in FLOORS]
        if bad_floor:
            raise BenchError(f"unknown floor {bad_floor[0]!r} (floors: {', '.join(FLOORS)})")
        if not self.vehicles or any(not 1 <= n <= 200 for n in self.vehicles):
            raise BenchError(f"vehicle counts must be within 1..200, got {self.vehicles}")
        if not self.rates or any(not 1 <= r <= 1000 for r in self.rates):
            raise BenchError(f"mocap rates must be within 1..1000 Hz, got {self.rates}")
        if not self.duration > 0 or self.warmup < 0 or self.idle < 0:
            raise BenchError("duration must be positive, warm-up and idle not negative")
        if not self.peer_rate > 0 or not self.peer_duration > 0 or not self.micro_scale > 0:
            raise BenchError("peer rate, peer duration and micro scale must be positive")
        if self.peer_repeats < 1 or self.overload < 0:
            raise BenchError("peer repeats must be at least 1, overload hogs not negative")
        if any(not 1 <= n <= 200 for n in self.growth):
            raise BenchError(f"growth vehicle counts must be within 1..200, got {self.growth}")
        if self.fleet and not 1 <= self.fleet <= 200:
            raise BenchError(f"the fleet must be within 1..200 vehicles, got {self.fleet}")
        if self.gateway_vision not in ("frame", "vehicle"):
            raise BenchError(f"--gateway-vision must be frame or vehicle, got {self.gateway_vision!r}")
        if self.gateway_hosts < 0:
            raise BenchError(f"--gateway-hosts must not be negative, got {self.gateway_hosts}")
        if self.vehicle_mode not in ("", "client", "same"):
            raise BenchError(f"--vehicle-mode must be client or same, got {self.vehicle_mode!r}")
        bad = [d for d in self.decimate if d not in CHAINS]
        if bad or not self.decimate:
            raise BenchError(f"--decimate must be among {', '.join(CHAINS)}, got {list(self.decimate)}")


# -- machine -------------------------------------------------------------------------------------------------


def machine_info() -> dict[str, Any]:
    """The machine the figures came from: CPU, cores, memory, load, software versions."""
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = 0
    try:
        with open("/proc/meminfo") as f:
            mem = int(f.readline().split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import zenoh

        zv = getattr(zenoh, "__version__", "")
    except ImportError:  # pragma: no cover - zenoh is a dependency
        zv = ""
    if not zv:
        try:
            from importlib.metadata import version

            zv = version("eclipse-zenoh")
        except Exception:
            zv = "?"
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "memory_gb": round(mem / 1e9, 1),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "zenoh": zv,
        "load": list(os.getloadavg()) if hasattr(os, "getloadavg") else [],
    }


# -- profiling -----------------------------------------------------------------------------------------------


def _pyspy() -> str | None:
    local = Path(sys.executable).parent / "py-spy"
    return str(local) if local.exists() else shutil.which("py-spy")


def make_profiler(out_dir: Path) -> Callable[[ProcessSet, float], dict[str, Any]]:
    """A profile hook for :class:`RunSettings`: py-spy on the ingest, transform and the first vehicle's
    downsampler and gateway."""
    exe = _pyspy()
    if exe is None:
        raise BenchError("--profile needs py-spy (pip install py-spy)")

    def profile(procs: ProcessSet, duration: float) -> dict[str, Any]:
        wanted: dict[str, Any] = {}
        for c in procs.children:
            if c.role in ("ingest", "transform") or (c.role in VEHICLE_ROLES and c.name.endswith(".d1")):
                wanted[c.name] = c
        out_dir.mkdir(parents=True, exist_ok=True)
        spies = []
        for name, c in wanted.items():
            path = out_dir / f"{name}-{int(time.time())}.txt"
            argv = [
                exe,
                "record",
                "--pid",
                str(c.pid),
                "--duration",
                str(max(1, int(duration))),
                "--rate",
                "500",
                "--format",
                "raw",
                "--nonblocking",
                "--gil",  # only threads holding the GIL: where the Python CPU goes, not where it waits
                "--output",
                str(path),
            ]
            spies.append(
                (name, path, subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            )
        result: dict[str, Any] = {}
        for name, path, proc in spies:
            try:
                proc.wait(duration + 20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
            try:
                result[name] = flames.read(path, limit=8).self_time
            except OSError:
                result[name] = []
        return result

    return profile


# -- the run -------------------------------------------------------------------------------------------------


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and math.isnan(obj):
        return None
    raise TypeError(f"not serialisable: {type(obj).__name__}")


def _clean(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def run(options: BenchOptions, console: Console | None = None) -> dict[str, Any]:
    """Measure what ``options`` asks for; print tables; write the JSON result (and the docs). Returns it."""
    options.check()
    console = console or Console(width=None if sys.stdout.isatty() else 160)
    started = time.time()
    out_dir = options.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(started))
    logs = Path(tempfile.mkdtemp(prefix=f"arena-bench-{stamp}-"))
    settings = _settings(options, logs, out_dir / f"profile-{stamp}")
    result: dict[str, Any] = {
        "version": 1,
        "started": time.strftime("%Y-%m-%d %H:%M:%S %z", time.localtime(started)),
        "options": _clean(asdict(options)),
        "machine": machine_info(),
        "load_before": list(os.getloadavg()) if hasattr(os, "getloadavg") else [],
        "points": [],
    }
    points: list[PointResult] = []
    timings: dict[str, float] = {}
    result["timings_s"] = timings
    _announce(console, result, logs)
    try:
        if "pipeline" in options.parts or "floor" in options.parts:
            on_point = _point_printer(console, points)
            _run_loads(console, options, settings, on_point, timings)
            if "pipeline" in options.parts and options.fleet and options.realistic_vision is not None:
                console.print(
                    f"[bold]fleet[/bold], {options.fleet} vehicles, vision {options.realistic_vision:g} Hz"
                )
                _run_fleet(options, settings, on_point, timings)
            if "pipeline" in options.parts and options.growth and options.realistic_vision is not None:
                _run_growth(options, settings, on_point, timings, points)
            result["points"] = [_clean(p.as_dict()) for p in points]
            _print_points(console, points)
        if "peer" in options.parts:
            _run_peer(console, options, settings, timings, result)
        if "micro" in options.parts:
            from bench.micro import run_micro

            console.print("[bold]micro[/bold]-benchmarks")
            with _timed(timings, "micro"):
                result["micro"] = _clean(run_micro(options.micro_scale))
            console.print(
                _rich("Per-stage micro-benchmarks", ["stage", "case", "cost"], micro_rows(result["micro"]))
            )
    finally:
        result["points"] = [_clean(p.as_dict()) for p in points]
        result["elapsed_s"] = time.time() - started
        result["load_after"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else []
        result["logs"] = str(logs)
        targets = evaluate_targets(_with_nan(result))
        result["targets"] = [asdict(t) for t in targets]
        path = _write_result(result, out_dir, stamp)
    console.print(_rich("Targets", ["target", "goal", "measured", ""], target_rows(targets)))
    if options.docs is not None:
        update_docs(options.docs, _with_nan(result))
        console.print(f"tables written into {options.docs}")
    console.print(f"result: {path} ({result['elapsed_s']:.0f} s)")
    shutil.rmtree(logs, ignore_errors=True)
    return result


def _settings(options: BenchOptions, logs: Path, profile_dir: Path) -> RunSettings:
    """The pipeline's run settings from ``options`` (the other parts adapt them)."""
    return RunSettings(
        duration=options.duration,
        warmup=options.warmup,
        idle=options.idle,
        logs=logs,
        repo=options.repo,
        profile=make_profiler(profile_dir) if options.profile else None,
        hops=options.hops,
        vehicle_mode=options.vehicle_mode,
    )


@contextlib.contextmanager
def _timed(timings: dict[str, float], name: str) -> Iterator[None]:
    """``timings[name]``: the seconds the block took (0.1 s), exception or not."""
    t = time.monotonic()
    try:
        yield
    finally:
        timings[name] = round(time.monotonic() - t, 1)


def _point_printer(console: Console, points: list[PointResult]) -> Callable[[PointResult], None]:
    """Each point as it comes: kept in ``points``, and one line on the console."""

    def on_point(p: PointResult) -> None:
        points.append(p)
        lat = p.latency
        least = (p.vision_rate or {}).get("min")
        console.print(
            f"  {p.chain:<20} {p.vehicles:>3} × {p.rate:>5g} Hz  p50 {_f(lat['p50'])} ms"
            f"  p99 {_f(lat['p99'])} ms  max {_f(lat['max'])} ms  lost {p.lost}/{p.expected}"
            + (f"  ≥ {least:.1f} poses/s per vehicle" if least is not None else "")
            + f"  load {os.getloadavg()[0]:.2f}"
        )

    return on_point


def _announce(console: Console, result: dict[str, Any], logs: Path) -> None:
    """The machine, its load (a warning when busy) and where the logs go."""
    busy = result["load_before"] and result["load_before"][0] > (os.cpu_count() or 1) * 0.75
    if busy:
        console.print(
            "[yellow]the machine is busy (load average above its cores): figures will be inflated; "
            "prefer a quiet moment[/yellow]"
        )
    console.print(
        f"[bold]make bench[/bold]: {result['machine']['cpu']}, {result['machine']['cores']} cores, "
        f"load {', '.join(f'{x:.2f}' for x in result['load_before'])}; logs in {logs}"
    )


def _run_loads(
    console: Console,
    options: BenchOptions,
    settings: RunSettings,
    on_point: Callable[[PointResult], None],
    timings: dict[str, float],
) -> None:
    """The pipeline and floor parts: at each vehicle count, every configuration, then every floor."""
    for n in options.vehicles:
        if "pipeline" in options.parts:
            console.print(f"[bold]pipeline[/bold], {n} vehicle(s)")
            with _timed(timings, f"pipeline {n}"):
                for decimate in options.decimate:
                    # The deployed point (vision 50 Hz), and at the largest load the overloaded one, for
                    # the last configuration measured only (transform by default): it keeps the run short.
                    last = decimate == options.decimate[-1]
                    real = options.realistic_vision if last else None
                    hogs = options.overload if n == max(options.vehicles) else 0
                    run_arena(
                        n,
                        options.rates,
                        settings,
                        realistic_vision=real,
                        overload=hogs if real is not None else 0,
                        on_point=on_point,
                        decimate=decimate,
                    )
        if "floor" in options.parts:
            for kind in options.floors:
                with _timed(timings, f"floor-{kind} {n}"):
                    floor_settings = replace(settings, profile=None, idle=0.0, hops=False)
                    run_floor(
                        kind,
                        n,
                        options.rates,
                        floor_settings,
                        vision_rate=options.realistic_vision,
                        on_point=on_point,
                    )


def _run_fleet(
    options: BenchOptions,
    settings: RunSettings,
    on_point: Callable[[PointResult], None],
    timings: dict[str, float],
) -> None:
    """The fleet point: ``options.fleet`` vehicles as deployed, in every configuration (transform first)."""
    assert options.realistic_vision is not None
    n = options.fleet
    fleet_settings = _fleet_settings(options, settings)
    for decimate in reversed(options.decimate):  # transform first: it keeps up best
        with _timed(timings, f"fleet {n} {decimate}"):
            run_arena(
                n,
                options.rates[:1],
                fleet_settings,
                realistic_vision=options.realistic_vision,
                overload=options.overload if decimate == "transform" else 0,
                on_point=on_point,
                decimate=decimate,
                deployed_only=True,
            )


def _fleet_settings(options: BenchOptions, settings: RunSettings) -> RunSettings:
    """How the fleet (and the growth table's points) run: as `arena demo --vehicles N` deploys them."""
    return replace(
        settings,
        settle=options.fleet_settle,
        idle=max(settings.idle, 2.0),
        vehicle_mode=options.vehicle_mode or "client",
        gateway_hosts=options.gateway_hosts,
        gateway_vision=options.gateway_vision,
    )


def _run_growth(
    options: BenchOptions,
    settings: RunSettings,
    on_point: Callable[[PointResult], None],
    timings: dict[str, float],
    points: list[PointResult],
) -> None:
    """The growth table's points: each vehicle count deployed as the fleet is, the transform decimating
    (a count the fleet point already measured so is not run again)."""
    assert options.realistic_vision is not None
    fleet_settings = _fleet_settings(options, settings)
    for n in sorted(set(options.growth)):
        if growth_point(points, n, options.realistic_vision) is not None:
            continue
        with _timed(timings, f"growth {n}"):
            run_arena(
                n,
                options.rates[:1],
                fleet_settings,
                realistic_vision=options.realistic_vision,
                on_point=on_point,
                decimate="transform",
                deployed_only=True,
            )


def _print_points(console: Console, points: list[PointResult]) -> None:
    console.print(_rich("End-to-end latency", LATENCY_HEADER, latency_rows(points)))
    console.print(_rich("CPU (% of one core) and memory", RESOURCE_HEADER, resource_rows(points)))
    growth = growth_rows(points)
    if growth:
        console.print(_rich("How cost grows", GROWTH_HEADER, growth))
    if hop_rows(points):
        console.print(_rich("Per stage, first vehicle (p50 / p99 ms)", HOPS_HEADER, hop_rows(points)))


def _run_peer(
    console: Console,
    options: BenchOptions,
    settings: RunSettings,
    timings: dict[str, float],
    result: dict[str, Any],
) -> None:
    """The peer comparison into ``result["peer"]``, and its tables."""
    from bench.peer import run_peers

    console.print("[bold]peer[/bold]: gateway, its floors and MAVProxy")
    peer_settings = replace(settings, duration=options.peer_duration, profile=None)
    with _timed(timings, "peer"):
        result["peer"] = _clean(
            run_peers(options.peer_rate, peer_settings, options.peer_repeats, options.peer_sweep)
        )
    runs = f"median (min–max) of {options.peer_repeats} runs" if options.peer_repeats > 1 else "1 run"
    title = (
        f"Gateway vs its floors and MAVProxy ({options.peer_rate:g} Hz, {runs} of "
        f"{options.peer_duration:g} s each)"
    )
    _print_peer(console, title, result["peer"])


def _write_result(result: dict[str, Any], out_dir: Path, stamp: str) -> Path:
    """``result`` as ``<out_dir>/bench-<stamp>.json`` and ``latest.json``; its ``path`` set to the first."""
    text = json.dumps(_clean(result), indent=1, default=_json_default, allow_nan=False)
    path = out_dir / f"bench-{stamp}.json"
    path.write_text(text)
    (out_dir / "latest.json").write_text(text)
    result["path"] = str(path)
    return path


def _print_peer(console: Console, title: str, peer: dict[str, Any]) -> None:
    console.print(_rich(title, PEER_HEADER, peer_rows(peer)))
    sweep = sweep_rows(peer)
    if sweep:
        console.print(_rich("CPU per message by rate", sweep_header(peer), sweep))


def _with_nan(result: dict[str, Any]) -> dict[str, Any]:
    """A result whose ``None`` figures (JSON's stand-in for NaN) read as NaN again."""

    def fix(obj: Any, figure: bool = False) -> Any:
        if obj is None and figure:
            return math.nan
        if isinstance(obj, dict):
            return {k: fix(v, k in _FIGURES) for k, v in obj.items()}
        if isinstance(obj, list):
            return [fix(v, figure) for v in obj]
        return obj

    fixed: dict[str, Any] = fix(result)
    return fixed


_FIGURES = frozenset(
    {
        "p50",
        "p99",
        "p999",
        "max",
        "mean",
        "cpu",
        "cpu_us_per_msg",
        "marginal_cpu_us_per_msg",
        "cpu_ratio",
        "marginal_cpu_ratio",
        "cpu_ratio_spread",
        "floor_ratio",
        "floor_mavproxy_ratio",
    }
)


def load_result(path: Path) -> dict[str, Any]:
    """A result written by :func:`run` (for re-rendering the docs from it)."""
    return _with_nan(json.loads(path.read_text()))


def rerender(path: Path, docs: Path | None, console: Console | None = None) -> None:
    """Print the tables of a stored result (and write its docs block into ``docs``)."""
    result = load_result(path)
    if docs is not None:
        update_docs(docs, result)
    console = console or Console(width=None if sys.stdout.isatty() else 160)
    points = [PointResult(**p) for p in result.get("points", [])]
    if points:
        console.print(_rich("End-to-end latency", LATENCY_HEADER, latency_rows(points)))
        console.print(_rich("CPU (% of one core) and memory", RESOURCE_HEADER, resource_rows(points)))
    if result.get("peer"):
        _print_peer(console, "Gateway vs its floors and MAVProxy", result["peer"])
    console.print(_rich("Targets", ["target", "goal", "measured", ""], target_rows(evaluate_targets(result))))
