"""The arena's performance targets, judged from a ``make bench`` result: met, missed (with the measured
reason) or not measured.

Targets are ratios within one run on the machine at hand (the arena against its floors and MAVProxy),
except the deployed point's absolute figures, the run's own duration and the micro-benchmarks' costs.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from bench.pipeline import CHAINS, PointResult

__all__ = [
    "PIPELINE_ROLES",
    "RUN_BUDGET_S",
    "VEHICLE_ROLES",
    "Target",
    "evaluate_targets",
    "floor_of",
    "point_of",
    "resource_summary",
    "short_reason",
]

PIPELINE_ROLES = ("router", "ingest", "transform", "downsampler", "gateway")
VEHICLE_ROLES = ("downsampler", "gateway")
MB = 1024 * 1024
RUN_BUDGET_S = 300.0  # a full ``make bench``
PEER_RATIO = 0.1  # the gateway's CPU per vision message, of MAVProxy's
GATEWAY_FLOOR_RATIO = 1.5  # the gateway's CPU per vision message, of its Zenoh floor's
PIPELINE_FLOOR_RATIO = 1.5  # the pipeline's CPU per vehicle, of its Zenoh floor's
LATENCY_FLOOR_RATIO = 1.2  # 1 vehicle × 180 Hz, p50 end to end, of the Zenoh floor's
MIN_VISION_RATE = 45.0  # poses/s every vehicle must get, deployed (vision 50 Hz)
DEPLOYED_P99_MS = 20.0
FLEET = 50  # vehicles of the fleet point (issue #27: fifty vehicles on one ground computer)
FLEET_P50_MS = 2.6  # NatNet frame → ODOMETRY, a tenth of Crazyswarm's 26 ms
FLEET_P99_MS = 10.0
FLEET_IDLE_RSS_MB = 40.0  # per per-vehicle process, idle
FLEET_IDLE_CPU = 0.2  # % of one core per per-vehicle process, idle (no mocap flowing)
FLEET_STARTUP_S = 30.0  # from the first process started to vision from every vehicle
_DEPLOYED = re.compile(r"^arena(-td)?-v[0-9.]+$")
_LOADED = re.compile(r"^arena(-td)?-v[0-9.]+-loaded$")


def resource_summary(point: PointResult) -> dict[str, Any]:
    """CPU (% of one core) and RSS (MB) per role, the pipeline's total and per vehicle."""
    roles: dict[str, dict[str, float]] = {}
    for info in point.per_service.values():
        r = roles.setdefault(
            info["role"], {"n": 0, "cpu": 0.0, "cpu_max": 0.0, "rss_mb": 0.0, "rss_max_mb": 0.0}
        )
        cpu = 0.0 if math.isnan(info["cpu"]) else info["cpu"]
        r["n"] += 1
        r["cpu"] += cpu
        r["cpu_max"] = max(r["cpu_max"], cpu)
        r["rss_mb"] += info["rss"] / MB
        r["rss_max_mb"] = max(r["rss_max_mb"], info["rss"] / MB)
    pipeline_cpu = sum(roles[r]["cpu"] for r in PIPELINE_ROLES if r in roles)
    pipeline_rss = sum(roles[r]["rss_mb"] for r in PIPELINE_ROLES if r in roles)
    per_vehicle = sum(roles[r]["cpu"] for r in VEHICLE_ROLES if r in roles) / max(1, point.vehicles)
    idle_rss = {name: info["rss"] / MB for name, info in point.idle.items() if info["role"] in VEHICLE_ROLES}
    return {
        "roles": roles,
        "pipeline_cpu": pipeline_cpu,
        "pipeline_rss_mb": pipeline_rss,
        "pipeline_cpu_per_vehicle": pipeline_cpu / max(1, point.vehicles),
        "per_vehicle_cpu": per_vehicle,
        "shared_cpu": pipeline_cpu - per_vehicle * point.vehicles,
        "idle_vehicle_rss_max_mb": max(idle_rss.values()) if idle_rss else math.nan,
        "idle_cpu": {name: info["cpu"] for name, info in point.idle.items()},
        "hogs_cpu": roles["load"]["cpu"] if "load" in roles else math.nan,
    }


@dataclass(frozen=True)
class Target:
    """One performance target, what was measured, and whether it was met."""

    name: str
    goal: str
    measured: str
    met: bool | None  # None: not measured in this run


def point_of(points: Sequence[PointResult], chain: str, n: int, rate: float) -> PointResult | None:
    for p in points:
        if p.chain == chain and p.vehicles == n and abs(p.rate - rate) < 1e-6:
            return p
    return None


def floor_of(points: Sequence[PointResult], p: PointResult, kind: str = "zenoh") -> PointResult | None:
    """The floor point ``p`` is read against: same load, same vision rate (``-v<rate>``) when measured.

    A loaded point has none (the floors run on a quiet machine)."""
    if p.chain.endswith("-loaded"):
        return None
    m = re.search(r"-v[0-9.]+$", p.chain)
    suffix = m.group(0) if m and p.chain.startswith("arena") else ""
    return point_of(points, f"floor-{kind}{suffix}", p.vehicles, p.rate)


def short_reason(text: str, limit: int = 200) -> str:
    """One line of a (possibly multi-line) reason: its first line and its last, boxes of tracebacks cut."""
    lines = [t for line in str(text).splitlines() if (t := line.strip(" │╭╰─┃━\t"))]
    if not lines:
        return ""
    one = lines[0] if len(lines) == 1 else f"{lines[0]} … {lines[-1]}"
    return one if len(one) <= limit else one[: limit - 1] + "…"


def _config(p: PointResult) -> str:
    return "transform decimates" if p.chain.startswith(CHAINS["transform"]) else "downsampler per vehicle"


def _vehicles(n: int) -> str:
    return f"{n} vehicle{'s' if n > 1 else ''}"


def _peer_targets(peer: dict[str, Any]) -> list[Target]:
    name, goal = "gateway CPU per forwarded vision message", f"≤ 1/{1 / PEER_RATIO:g} of MAVProxy's"
    fname, fgoal = (
        "gateway CPU per vision message vs its Zenoh floor (informative)",
        (f"≤ {GATEWAY_FLOOR_RATIO:g}× the floor's"),
    )
    g, m, fz, fu = (peer.get(k) or {} for k in ("gateway", "mavproxy", "floor-zenoh", "floor-udp"))

    def usable(d: dict[str, Any]) -> bool:
        return bool(d) and "unavailable" not in d and not math.isnan(d.get("cpu_us_per_msg", math.nan))

    out: list[Target] = []
    repeats = int(g.get("repeats", 1) or 1)
    runs = (f"median of {repeats} runs" if repeats > 1 else "1 run") if usable(g) else ""
    if not peer:
        out.append(Target(name, goal, "not run", None))
    elif not usable(g) or not usable(m):
        bad = g if not usable(g) else m
        why = short_reason(bad.get("unavailable", "no message forwarded"))
        out.append(Target(name, goal, f"{'gateway' if bad is g else 'MAVProxy'}: {why}", None))
    else:
        gc, mc = g["cpu_us_per_msg"], m["cpu_us_per_msg"]
        ratio = gc / mc
        lo, hi = peer.get("cpu_ratio_spread") or [math.nan, math.nan]
        spread = ""
        if lo is not None and hi is not None and not math.isnan(lo) and f"{lo:.2f}" != f"{hi:.2f}":
            spread = f", per run ×{lo:.2f}–×{hi:.2f}"
        if ratio <= PEER_RATIO:
            text = f"×{ratio:.2f} (gateway {gc:.0f} µs, MAVProxy {mc:.0f} µs; {runs}{spread})"
        else:
            text = f"×{ratio:.2f}: gateway {gc:.0f} µs"
            if usable(fz):
                fc = fz["cpu_us_per_msg"]
                text += (
                    f", its Zenoh floor {fc:.0f} µs, MAVProxy {mc:.0f} µs: the floor alone is ×{fc / mc:.2f}"
                )
                text += " of MAVProxy"
            else:
                text += f", MAVProxy {mc:.0f} µs"
            text += f" ({runs}{spread})"
        out.append(Target(name, goal, text, ratio <= PEER_RATIO))
    if usable(g) and usable(fz):
        gc, fc = g["cpu_us_per_msg"], fz["cpu_us_per_msg"]
        r = gc / fc
        udp = f", floor-udp {fu['cpu_us_per_msg']:.0f} µs" if usable(fu) else ""
        text = f"×{r:.2f} (gateway {gc:.0f} µs, floor-zenoh {fc:.0f} µs{udp}; {runs})"
        out.append(Target(fname, fgoal, text, r <= GATEWAY_FLOOR_RATIO))
    else:
        out.append(Target(fname, fgoal, "not run" if not peer else "a forwarder did not run", None))
    return out


def _pipeline_cpu_target(pts: Sequence[PointResult]) -> Target:
    name = "pipeline CPU per vehicle, 1 × 180 Hz mocap, 50 Hz vision"
    goal = f"≤ {PIPELINE_FLOOR_RATIO:g}× its Zenoh floor"
    cands = [p for p in pts if _DEPLOYED.match(p.chain) and p.vehicles == 1 and p.rate == 180.0]
    if not cands:
        why = "not run" if not pts else "not run (no deployed point at 1 vehicle × 180 Hz)"
        return Target(name, goal, why, None)
    p = min(cands, key=lambda p: resource_summary(p)["pipeline_cpu"])
    floor = floor_of(pts, p)
    note = ""
    if floor is None:
        floor = point_of(pts, "floor-zenoh", 1, 180.0)
        note = "; floor at full rate"
    if floor is None:
        return Target(name, goal, "the Zenoh floor was not run", None)
    a, f = resource_summary(p), resource_summary(floor)
    ratio = a["pipeline_cpu_per_vehicle"] / f["pipeline_cpu_per_vehicle"] if f["pipeline_cpu"] else math.inf
    roles = [r for r in PIPELINE_ROLES if r in a["roles"] or r in f["roles"]]

    def cpu(s: dict[str, Any], role: str) -> str:
        return f"{s['roles'][role]['cpu']:.1f}" if role in s["roles"] else "—"

    split = ", ".join(f"{r} {cpu(a, r)}/{cpu(f, r)}" for r in roles)
    text = (
        f"×{ratio:.2f}: {a['pipeline_cpu_per_vehicle']:.1f} % vs floor {f['pipeline_cpu_per_vehicle']:.1f} %"
        f" of one core ({_config(p)}{note}; arena/floor: {split})"
    )
    return Target(name, goal, text, ratio <= PIPELINE_FLOOR_RATIO)


def _latency_target(pts: Sequence[PointResult]) -> Target:
    name = "1 vehicle × 180 Hz end to end p50"
    goal = f"≤ {LATENCY_FLOOR_RATIO:g}× the Zenoh floor"
    found = [p for c in CHAINS.values() if (p := point_of(pts, c, 1, 180.0)) is not None]
    if not found:
        return Target(name, goal, "not run", None)
    p = min(found, key=lambda p: p.latency["p50"])
    floor = point_of(pts, "floor-zenoh", 1, 180.0)
    if floor is None or not floor.latency["p50"] > 0:
        return Target(name, goal, f"p50 {p.latency['p50']:.3f} ms; the Zenoh floor was not run", None)
    ratio = p.latency["p50"] / floor.latency["p50"]
    others = [f"{q.chain} {q.latency['p50']:.3f} ms" for q in found if q is not p]
    text = (
        f"×{ratio:.2f}: p50 {p.latency['p50']:.3f} ms vs floor {floor.latency['p50']:.3f} ms ({_config(p)}"
        + (f"; {', '.join(others)}" if others else "")
        + ")"
    )
    return Target(name, goal, text, ratio <= LATENCY_FLOOR_RATIO)


def _vision_text(p: PointResult) -> tuple[str, bool]:
    least = p.vision_rate.get("min", math.nan) if p.vision_rate else math.nan
    p99 = p.latency["p99"]
    text = (
        f"least {least:.1f} poses/s per vehicle (median {p.vision_rate.get('median', math.nan):.1f}), "
        f"p99 {p99:.1f} ms, lost {p.lost}/{p.expected}"
    )
    return text, least >= MIN_VISION_RATE and p.lost == 0


def _deployed_target(pts: Sequence[PointResult]) -> Target:
    name = "20 vehicles × 180 Hz as deployed (vision 50 Hz)"
    goal = f"every vehicle ≥ {MIN_VISION_RATE:g} vision poses/s, p99 ≤ {DEPLOYED_P99_MS:g} ms, no undesigned loss"
    cands = [p for p in pts if _DEPLOYED.match(p.chain) and p.vehicles == 20 and p.rate == 180.0]
    if not cands:
        return Target(name, goal, "not run", None)
    p = min(cands, key=lambda p: (p.lost, p.latency["p99"]))
    text, ok = _vision_text(p)
    ok = ok and p.latency["p99"] <= DEPLOYED_P99_MS
    misses = []
    if (p.vision_rate or {}).get("min", 0.0) < MIN_VISION_RATE:
        misses.append("a vehicle got too few poses")
    if not p.latency["p99"] <= DEPLOYED_P99_MS:
        misses.append("p99 too high")
    if p.lost:
        misses.append("poses lost")
    return Target(name, goal, f"{text} ({_config(p)}" + (f": {', '.join(misses)})" if misses else ")"), ok)


def _overload_target(pts: Sequence[PointResult]) -> Target:
    goal = f"every vehicle ≥ {MIN_VISION_RATE:g} vision poses/s, no undesigned loss (vision first)"
    cands = [p for p in pts if _LOADED.match(p.chain) and p.rate == 180.0]
    if not cands:
        return Target("vision first under overload", goal, "not run", None)
    p = max(cands, key=lambda p: p.vehicles)
    text, ok = _vision_text(p)
    hogs = resource_summary(p)["hogs_cpu"]
    took = f"; {p.hogs} hogs took {hogs:.0f} % of one core" if not math.isnan(hogs) else ""
    name = f"vision first under overload: {_vehicles(p.vehicles)} × 180 Hz as deployed, {p.hogs} CPU hogs"
    return Target(name, goal, f"{text}{took} ({_config(p)})", ok)


def _duration_target(result: dict[str, Any]) -> Target:
    from bench.run import PARTS

    name, goal = "make bench duration", f"under {RUN_BUDGET_S / 60:g} minutes"
    elapsed = result.get("elapsed_s")
    if elapsed is None or (isinstance(elapsed, float) and math.isnan(elapsed)):
        return Target(name, goal, "not measured", None)
    options = result.get("options") or {}
    full = not options.get("quick") and set(options.get("parts") or ()) >= set(PARTS)
    text = f"{elapsed:.0f} s"
    if not full:
        return Target(name, goal, f"{text} (not a full run: only `make bench` is judged)", None)
    return Target(name, goal, text, elapsed < RUN_BUDGET_S)


def _micro_targets(micro: dict[str, Any]) -> list[Target]:
    out: list[Target] = []
    dec = (micro.get("natnet_decode_us") or {}).get("10 bodies")
    out.append(
        Target(
            "NatNet decode, 10-body frame",
            "≤ 30 µs",
            "not run" if dec is None else f"{dec:.1f} µs",
            None if dec is None else dec <= 30.0,
        )
    )
    tf = micro.get("transform_us") or {}
    if tf:
        single = tf.get("pose (1 body)", math.nan)
        batch = tf.get("poses, batch of 10 (per pose)", math.nan)
        out.append(
            Target(
                "frame transform per pose",
                "≤ 10 µs amortised",
                f"{single:.1f} µs single, {batch:.1f} µs in batches of 10",
                single <= 10.0,
            )
        )
    else:
        out.append(Target("frame transform per pose", "≤ 10 µs amortised", "not run", None))
    return out


def _rss_target(pts: Sequence[PointResult]) -> Target:
    idle = {
        p.vehicles: resource_summary(p)["idle_vehicle_rss_max_mb"]
        for p in pts
        if p.chain in CHAINS.values() and p.idle
    }
    idle = {n: v for n, v in idle.items() if not math.isnan(v)}
    if not idle:
        return Target("idle per-vehicle process RSS", "≤ 60 MB", "not run", None)
    worst = max(idle.values())
    text = ", ".join(f"{v:.1f} MB at {_vehicles(n)}" for n, v in sorted(idle.items()))
    return Target("idle per-vehicle process RSS", "≤ 60 MB", f"largest: {text}", worst <= 60.0)


def _idle_vehicle(p: PointResult) -> tuple[dict[str, float], dict[str, float]]:
    """The idle RSS (MB) and CPU (% of one core) of each per-vehicle process of ``p``."""
    idle = {k: v for k, v in p.idle.items() if v["role"] in VEHICLE_ROLES}
    cpu = {k: v["cpu"] for k, v in idle.items() if not math.isnan(v["cpu"])}
    return {k: v["rss"] / MB for k, v in idle.items()}, cpu


def _per_vehicle(per_process: dict[str, float], vehicles: int, unit: str, fmt: str) -> tuple[float, str]:
    """The worst share of one vehicle in ``per_process`` (a figure of each per-vehicle process), with its text.

    One process each: the largest process.  Processes serving several vehicles (``--gateway-hosts``): each
    process's figure over the vehicles it serves, and never less than the total over every vehicle."""
    if not per_process or vehicles <= 0:
        return math.inf, "no per-vehicle process measured"
    total, largest = sum(per_process.values()), max(per_process.values())
    served = vehicles / len(per_process)
    each = max(largest / max(served, 1.0), total / vehicles)
    share = f" serving {served:g} vehicles each" if served > 1 else ""
    return each, (
        f"{each:{fmt}} {unit} per vehicle: largest process {largest:{fmt}} {unit}{share}, "
        f"total {total:{fmt}} {unit} over {len(per_process)} processes"
    )


def fleet_targets(pts: Sequence[PointResult], n: int = FLEET) -> list[Target]:
    """The fleet point's targets (``n`` vehicles × 180 Hz, issue #27): vision as deployed in each pipeline
    configuration, and beside CPU hogs; idle RSS and CPU per per-vehicle process (with the totals); the
    start-up time to vision from every vehicle."""
    at = [p for p in pts if p.vehicles == n and p.rate == 180.0]
    goal = (
        f"every vehicle ≥ {MIN_VISION_RATE:g} vision poses/s, p50 ≤ {FLEET_P50_MS:g} ms, "
        f"p99 ≤ {FLEET_P99_MS:g} ms, no undesigned loss"
    )
    out: list[Target] = []
    for config, chain in (
        ("transform decimates", CHAINS["transform"]),
        ("downsampler per vehicle", CHAINS["downsampler"]),
    ):
        for loaded, pattern in ((False, _DEPLOYED), (True, _LOADED)):
            found = [p for p in at if pattern.match(p.chain) and p.chain.startswith(chain + "-v")]
            if not found:
                continue
            p = found[-1]
            hogs = f" beside {p.hogs} CPU hogs" if loaded else ""
            text, ok = _vision_text(p)
            ok = ok and p.latency["p50"] <= FLEET_P50_MS and p.latency["p99"] <= FLEET_P99_MS
            name = f"{_vehicles(n)} × 180 Hz as deployed (vision 50 Hz){hogs}, {config}"
            out.append(Target(name, goal, f"p50 {p.latency['p50']:.1f} ms, {text}", ok))
    if not out:
        out.append(Target(f"{_vehicles(n)} × 180 Hz as deployed (vision 50 Hz)", goal, "not run", None))
    deployed = [p for p in at if _DEPLOYED.match(p.chain) and p.chain.startswith(CHAINS["transform"] + "-v")]
    core_name = f"the whole arena's CPU at {_vehicles(n)} as deployed, transform decimating"
    if deployed:
        cpu = resource_summary(deployed[-1])["pipeline_cpu"]
        out.append(Target(core_name, "under one core", f"{cpu:.0f} % of one core", cpu < 100.0))
    else:
        out.append(Target(core_name, "under one core", "not run", None))
    first = next((p for p in at if p.idle), None)
    rss_goal, cpu_goal = (
        f"≤ {FLEET_IDLE_RSS_MB:g} MB per vehicle",
        f"≤ {FLEET_IDLE_CPU:g} % of one core per vehicle",
    )
    rss_name = f"idle per-vehicle process RSS at {_vehicles(n)}"
    cpu_name = f"idle per-vehicle process CPU at {_vehicles(n)} (no mocap)"
    if first is None:
        out += [Target(rss_name, rss_goal, "not run", None), Target(cpu_name, cpu_goal, "not run", None)]
    else:
        rss, cpu = _idle_vehicle(first)
        arena_rss = sum(v["rss"] for v in first.idle.values() if v["role"] in PIPELINE_ROLES) / MB
        arena_cpu = sum(v["cpu"] for v in first.idle.values() if v["role"] in PIPELINE_ROLES)
        rss_each, rss_text = _per_vehicle(rss, first.vehicles, "MB", ".1f")
        out.append(
            Target(
                rss_name,
                rss_goal,
                f"{rss_text}; the whole arena {arena_rss:.0f} MB ({_config(first)})",
                rss_each <= FLEET_IDLE_RSS_MB,
            )
        )
        cpu_each, cpu_text = _per_vehicle(cpu, first.vehicles, "%", ".2f")
        out.append(
            Target(
                cpu_name,
                cpu_goal,
                f"{cpu_text}; the whole arena {arena_cpu:.1f} %",
                cpu_each <= FLEET_IDLE_CPU,
            )
        )
    up = next((p.startup for p in at if p.startup.get("vision") is not None), None)
    up_name, up_goal = f"start-up of {_vehicles(n)} to vision from every vehicle", f"≤ {FLEET_STARTUP_S:g} s"
    if up is None:
        out.append(Target(up_name, up_goal, "not run", None))
    else:
        total = up["services"] + up["vision"]
        text = f"{total:.1f} s: services alive {up['services']:.1f} s, then ODOMETRY from all {up['vision']:.1f} s"
        out.append(Target(up_name, up_goal, text, total <= FLEET_STARTUP_S))
    return out


def evaluate_targets(result: dict[str, Any]) -> list[Target]:
    """The arena's performance targets against a result of :func:`bench.run.run`."""
    pts = [PointResult(**p) for p in result.get("points", [])]
    return [
        *_peer_targets(result.get("peer") or {}),
        _pipeline_cpu_target(pts),
        _latency_target(pts),
        _deployed_target(pts),
        _overload_target(pts),
        _duration_target(result),
        *_micro_targets(result.get("micro") or {}),
        _rss_target(pts),
        *(fleet_targets(pts) if any(p.vehicles == FLEET for p in pts) else []),
    ]
