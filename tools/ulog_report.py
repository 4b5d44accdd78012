"""How closely a PX4 SITL (SIH) flight held its position and tracked the truth, from PX4's own ULog.

``python -m tools.ulog_report LOG.ulg [--hover T0 T1] [--json]`` prints, from the topics PX4 logs:

- **hover**: the true position's (``vehicle_local_position_groundtruth``) distance from its median over the
  hover window, p50 / max, 3-D and horizontal;
- **estimate vs truth**: the time shift of ``vehicle_local_position`` behind the truth that fits best, and
  the rms error at that shift and at none (airborne part of the flight);
- **estimate vs vision**: the same against the vision PX4 received (``vehicle_visual_odometry`` at its
  ``timestamp_sample``): how far PX4's estimate trails the mocap pose;
- **vision vs truth**: the vision's own lag and error as PX4 stamped it (the arena's stamp mapped by PX4's
  TIMESYNC estimate), and the same with PX4's TIMESYNC tracking error taken out (**synced**): the arena's
  stamps and the truth's own delivery alone;
- **TIMESYNC error**: PX4's offset estimate minus the offsets its accepted TIMESYNC answers observed
  (``timesync_status``, logged at 1 Hz; a running median of 5), p50 and largest magnitude over the airborne
  vision: how far PX4 itself shifted the stamps;
- **innovations**: rms innovation and p95 test ratio of the EV (or GNSS) position fusion
  (``estimator_aid_src_ev_pos`` / ``estimator_aid_src_gnss_pos``);
- **output predictor**: ``estimator_status.output_tracking_error[2]`` (position; [0] is angular, [1]
  velocity) p50 / p95;
- **offboard**: over the longest Offboard stretch, the truth's largest distance from the position
  setpoint PX4 was given at the same time (``trajectory_setpoint``) and the rms of that distance, and over
  its last 2 s the truth's distance from the final setpoint, p50 / max;
- **timesync**: when PX4 started converting vision stamps with its TIMESYNC estimate (the first sample whose
  ``timestamp_sample`` is more than 1 ms before its arrival; before that it uses arrival time).

Times are PX4's boot clock in seconds.  The estimate's frame (vision or GNSS origin) differs from SIH's
ground-truth frame by a constant: it is taken as the median difference over the last 5 s before arming.
The hover window defaults to the Hold (AUTO.LOITER) stretch after take-off, from 4 s after the truth came
within 10 cm of that stretch's final height, at most 10 s.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

NAV_AUTO_LOITER = 4  # vehicle_status.nav_state of Hold
ARMED = 2  # vehicle_status.arming_state
TOPICS = (
    "vehicle_local_position",
    "vehicle_local_position_groundtruth",
    "vehicle_visual_odometry",
    "vehicle_status",
    "estimator_status",
    "estimator_aid_src_ev_pos",
    "estimator_aid_src_gnss_pos",
    "trajectory_setpoint",
    "timesync_status",
)
NAV_OFFBOARD = 14
TIMESYNC_SOURCE_MAVLINK = 1  # uORB timesync_status.SOURCE_PROTOCOL_MAVLINK (not a MAVLink number)
MAX_RTT_US = 10_000  # PX4 takes a TIMESYNC answer as a sample only below this round trip (Timesync.hpp)
REQUIRED = ("vehicle_local_position", "vehicle_local_position_groundtruth", "vehicle_status")

Arrays = Mapping[str, np.ndarray]


@dataclass(frozen=True, slots=True)
class Lag:
    """The shift (ms) of a signal behind a reference that fits best, and the rms error there and at 0."""

    ms: float
    rms_m: float
    rms0_m: float


@dataclass(frozen=True, slots=True)
class Report:
    """The figures of one flight (distances in m, times in ms unless named otherwise)."""

    hover_s: tuple[float, float]
    hover_p50_m: float
    hover_max_m: float
    hover_xy_p50_m: float
    hover_xy_max_m: float
    hover_height_m: float  # the truth's median height above SIH's home (the floor) in the window
    estimate_vs_truth: Lag | None
    estimate_vs_truth_hover: Lag | None
    estimate_vs_vision: Lag | None
    vision_vs_truth: Lag | None
    innovation_source: str | None
    innovation_rms_m: float | None
    test_ratio_p95: float | None
    tracking_error_p50_m: float | None
    tracking_error_p95_m: float | None
    timesync_from_s: float | None
    offboard_s: tuple[float, float] | None = None
    offboard_max_m: float | None = None
    offboard_end_p50_m: float | None = None
    offboard_end_max_m: float | None = None
    offboard_rms_m: float | None = None
    vision_vs_truth_synced: Lag | None = None
    timesync_error_ms: tuple[float, float] | None = None  # p50, largest magnitude


def xyz(data: Arrays, keys: Sequence[str] = ("x", "y", "z")) -> np.ndarray:
    """Columns ``keys`` of a topic as an (n, len(keys)) float array."""
    return np.stack([np.asarray(data[k], dtype=float) for k in keys], axis=1)


def best_lag(
    t: np.ndarray,
    x: np.ndarray,
    t_ref: np.ndarray,
    ref: np.ndarray,
    lags_ms: Sequence[float] = tuple(range(-100, 405, 5)),
) -> Lag | None:
    """How far ``x`` (sampled at ``t``, µs) trails ``ref`` (at ``t_ref``): the shift d (ms) minimising the rms
    of x(t) − ref(t − d), with the rms there and at d = 0.  Samples outside ``ref``'s span are left out."""
    if len(t) < 10 or len(t_ref) < 10:
        return None
    results: dict[float, float] = {}
    for ms in lags_ms:
        ts = t - ms * 1e3
        keep = (ts >= t_ref[0]) & (ts <= t_ref[-1])
        if keep.sum() < 10:
            continue
        shifted = np.stack([np.interp(ts[keep], t_ref, ref[:, k]) for k in range(ref.shape[1])], axis=1)
        results[float(ms)] = float(np.sqrt(np.mean(np.sum((x[keep] - shifted) ** 2, axis=1))))
    if not results:
        return None
    best = min(results, key=lambda k: results[k])
    at0 = results.get(0.0, float("nan"))
    return Lag(best, results[best], at0)


def spread(points: np.ndarray) -> tuple[float, float]:
    """Distance of each point from the points' median: (p50, max)."""
    if len(points) == 0:
        return float("nan"), float("nan")
    d = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    return float(np.median(d)), float(d.max())


def timesync_start(
    timestamp: np.ndarray, timestamp_sample: np.ndarray, gap_us: float = 1000.0
) -> float | None:
    """PX4 boot time (s) of the first vision sample stamped more than ``gap_us`` before its arrival, i.e.
    from when PX4's TIMESYNC had converged (before, PX4 stamps vision with its arrival time)."""
    late = np.nonzero((timestamp - timestamp_sample) > gap_us)[0]
    return float(timestamp[late[0]]) * 1e-6 if len(late) else None


def timesync_error(ts: Arrays, window: int = 5) -> tuple[np.ndarray, np.ndarray] | None:
    """PX4's TIMESYNC tracking error (times, errors; µs): at each logged answer PX4 took as a sample (a round
    trip under :data:`MAX_RTT_US`), its offset estimate minus the offset that answer observed, as a running
    median of ``window`` answers.  Positive: PX4 maps a remote stamp later than its answers say.

    PX4 (``src/lib/timesync/Timesync.cpp``) maps a vision stamp as ``time_usec + estimated_offset`` and
    observes ``(ts1 + now) / 2 - tc1`` on each answer; after its 500 first answers it follows them with
    gains of 0.003 (at 10 Hz: ~33 s), which follow a steady skew but not a change of it.  SITL's clock runs
    slower as the machine is loaded (0.8 % on this 2-core machine, docs/px4.md): PX4's filter, run on a
    change of that rate by 0.1 % (0.2 %), ends up to 18 ms (36 ms) off within the 45 s after it.
    """
    if not len(ts.get("timestamp", ())):
        return None
    keep = (np.asarray(ts["remote_timestamp"], float) > 0) & (
        np.asarray(ts["round_trip_time"], float) < MAX_RTT_US
    )
    if keep.sum() < window:
        return None
    t = np.asarray(ts["timestamp"], float)[keep]
    raw = (np.asarray(ts["estimated_offset"], float) - np.asarray(ts["observed_offset"], float))[keep]
    half = window // 2
    smooth = np.array([np.median(raw[max(0, i - half) : i + half + 1]) for i in range(len(raw))])
    return t, smooth


def hover_window(
    t_status: np.ndarray,
    nav_state: np.ndarray,
    arming: np.ndarray,
    t_truth: np.ndarray,
    down: np.ndarray,
    settle_s: float = 4.0,
    length_s: float = 10.0,
) -> tuple[float, float] | None:
    """The default hover window (µs): in the first armed Hold stretch that ends above 0.5 m, from
    ``settle_s`` after the truth came within 10 cm of the stretch's final height, ``length_s`` long at most."""
    edges = [*t_status.tolist(), float("inf")]
    for i, (state, armed) in enumerate(zip(nav_state, arming, strict=True)):
        if state != NAV_AUTO_LOITER or armed != ARMED:
            continue
        j = i
        while j + 1 < len(nav_state) and nav_state[j + 1] == NAV_AUTO_LOITER and arming[j + 1] == ARMED:
            j += 1
        t0, t1 = float(edges[i]), min(float(edges[j + 1]), float(t_truth[-1]))
        inside = (t_truth >= t0) & (t_truth <= t1)
        if inside.sum() < 10 or -down[inside][-1] < 0.5:
            continue
        final = down[inside][-1]
        near = np.nonzero(inside & (np.abs(down - final) < 0.10))[0]
        start = float(t_truth[near[0]]) + settle_s * 1e6
        if start < t1:
            return start, min(t1, start + length_s * 1e6)
    return None


def stretches(t: np.ndarray, flags: np.ndarray, t_end: float) -> list[tuple[float, float]]:
    """The (start, end) times of each run of true ``flags`` in a status topic sampled at ``t``."""
    out, start = [], None
    for ti, flag in zip(t, flags, strict=True):
        if flag and start is None:
            start = float(ti)
        elif not flag and start is not None:
            out.append((start, float(ti)))
            start = None
    if start is not None:
        out.append((start, t_end))
    return out


def offboard_tracking(
    t_sp: np.ndarray,
    setpoint: np.ndarray,
    t_truth: np.ndarray,
    truth: np.ndarray,
    window: tuple[float, float],
    end_s: float = 2.0,
) -> tuple[float, float, float, float] | None:
    """Truth vs the position setpoint in ``window`` (µs): the largest distance at the same time, over the
    last ``end_s`` the distance from the final setpoint (p50 and max), and the rms distance at the same time.
    Setpoints without a position left out."""
    keep = (t_sp >= window[0]) & (t_sp <= window[1]) & np.all(np.isfinite(setpoint), axis=1)
    if keep.sum() < 10:
        return None
    ts, sp = t_sp[keep], setpoint[keep]
    at = np.stack([np.interp(ts, t_truth, truth[:, k]) for k in range(3)], axis=1)
    distance = np.linalg.norm(at - sp, axis=1)
    deviation, rms = float(distance.max()), float(np.sqrt(np.mean(distance**2)))
    end = (t_truth >= window[1] - end_s * 1e6) & (t_truth <= window[1])
    if end.sum() < 3:
        return None
    held = np.linalg.norm(truth[end] - sp[-1], axis=1)
    return deviation, float(np.median(held)), float(held.max()), rms


def analyse(topics: Mapping[str, Arrays], hover: tuple[float, float] | None = None) -> Report:
    """The :class:`Report` of a flight from its topics' arrays (``hover`` in PX4 seconds, else found)."""
    lp, gt, st = (
        topics["vehicle_local_position"],
        topics["vehicle_local_position_groundtruth"],
        topics["vehicle_status"],
    )
    t_lp, t_gt = np.asarray(lp["timestamp"], float), np.asarray(gt["timestamp"], float)
    est, truth = xyz(lp), xyz(gt)
    t_st = np.asarray(st["timestamp"], float)
    armed_at = t_st[np.nonzero(np.asarray(st["arming_state"]) == ARMED)[0]]
    t_arm = float(armed_at[0]) if len(armed_at) else float(t_lp[-1])
    pre = (t_lp > t_arm - 5e6) & (t_lp < t_arm)
    if pre.sum() < 5:
        pre = t_lp < t_arm
    truth_at_lp = np.stack([np.interp(t_lp, t_gt, truth[:, k]) for k in range(3)], axis=1)
    offset = np.median(est[pre] - truth_at_lp[pre], axis=0) if pre.any() else np.zeros(3)
    est = est - offset

    if hover is not None:
        window = (hover[0] * 1e6, hover[1] * 1e6)
    else:
        found = hover_window(
            t_st, np.asarray(st["nav_state"]), np.asarray(st["arming_state"]), t_gt, truth[:, 2]
        )
        if found is None:
            raise ValueError("no hover found (an armed Hold above 0.5 m): give --hover T0 T1")
        window = found
    in_hover = (t_gt >= window[0]) & (t_gt <= window[1])
    h50, hmax = spread(truth[in_hover])
    xy50, xymax = spread(truth[in_hover, :2])

    airborne_gt = np.interp(t_lp, t_gt, -truth[:, 2]) > 0.3
    flying = airborne_gt & (t_lp > t_arm)
    est_truth = best_lag(t_lp[flying], est[flying], t_gt, truth)
    lp_hover = (t_lp >= window[0]) & (t_lp <= window[1])
    est_truth_hover = best_lag(t_lp[lp_hover], est[lp_hover], t_gt, truth)

    est_vision = vision_truth = vision_synced = None
    ts_from = ts_error = None
    vo = topics.get("vehicle_visual_odometry")
    if vo is not None and len(vo["timestamp"]) > 10:
        t_vo = np.asarray(vo["timestamp"], float)
        t_vs = np.asarray(vo["timestamp_sample"], float)
        vis = xyz(vo, ("position[0]", "position[1]", "position[2]")) - offset
        order = np.argsort(t_vs)
        est_vision = best_lag(t_lp[flying], est[flying], t_vs[order], vis[order])
        vflying = np.interp(t_vs, t_gt, -truth[:, 2]) > 0.3
        vision_truth = best_lag(t_vs[vflying], vis[vflying], t_gt, truth, tuple(range(-50, 105, 1)))
        ts_from = timesync_start(t_vo, t_vs)
        found_error = timesync_error(topics["timesync_status"]) if "timesync_status" in topics else None
        if found_error is not None and ts_from is not None:
            # Only once PX4 used its estimate (converged); before, its stamps were arrival times.
            synced = vflying & (t_vo >= ts_from * 1e6)
            error = np.interp(t_vs, *found_error)
            if synced.sum() >= 10:
                vision_synced = best_lag(
                    t_vs[synced] - error[synced], vis[synced], t_gt, truth, tuple(range(-50, 105, 1))
                )
                ts_error = (float(np.median(error[synced])) * 1e-3, float(np.abs(error[synced]).max()) * 1e-3)

    source = innov_rms = ratio95 = None
    for name, label in (("estimator_aid_src_ev_pos", "ev"), ("estimator_aid_src_gnss_pos", "gnss")):
        aid = topics.get(name)
        if aid is None or len(aid["timestamp"]) < 10:
            continue
        fused = np.asarray(aid["fused"]).astype(bool)
        t_aid = np.asarray(aid["timestamp"], float)
        keep = fused & (t_aid > t_arm)
        if keep.sum() < 10:
            continue
        innov = xyz(aid, ("innovation[0]", "innovation[1]"))[keep]
        ratio = xyz(aid, ("test_ratio[0]", "test_ratio[1]"))[keep]
        source = label
        innov_rms = float(np.sqrt(np.mean(np.sum(innov**2, axis=1) / 2)))
        ratio95 = float(np.percentile(ratio.max(axis=1), 95))
        break

    te50 = te95 = None
    es = topics.get("estimator_status")
    if es is not None and len(es["timestamp"]):
        t_es = np.asarray(es["timestamp"], float)
        te = np.asarray(es["output_tracking_error[2]"], float)[t_es > t_arm]
        if len(te):
            te50, te95 = float(np.median(te)), float(np.percentile(te, 95))

    offboard = offboard_figures(topics, t_st, np.asarray(st["nav_state"]), t_gt, truth + offset)
    return Report(
        hover_s=(window[0] * 1e-6, window[1] * 1e-6),
        hover_p50_m=h50,
        hover_max_m=hmax,
        hover_xy_p50_m=xy50,
        hover_xy_max_m=xymax,
        hover_height_m=float(-np.median(truth[in_hover, 2])) if in_hover.any() else float("nan"),
        estimate_vs_truth=est_truth,
        estimate_vs_truth_hover=est_truth_hover,
        estimate_vs_vision=est_vision,
        vision_vs_truth=vision_truth,
        innovation_source=source,
        innovation_rms_m=innov_rms,
        test_ratio_p95=ratio95,
        tracking_error_p50_m=te50,
        tracking_error_p95_m=te95,
        timesync_from_s=ts_from,
        vision_vs_truth_synced=vision_synced,
        timesync_error_ms=ts_error,
        **offboard,
    )


class OffboardFigures(TypedDict, total=False):
    """:class:`Report`'s ``offboard_*`` fields, all or none (typed, for ``Report(**figures)``)."""

    offboard_s: tuple[float, float]
    offboard_max_m: float
    offboard_end_p50_m: float
    offboard_end_max_m: float
    offboard_rms_m: float


def offboard_figures(
    topics: Mapping[str, Arrays], t_st: np.ndarray, nav_state: np.ndarray, t_gt: np.ndarray, truth: np.ndarray
) -> OffboardFigures:
    """The :class:`Report`'s ``offboard_*`` fields over the longest Offboard stretch (none without one);
    ``truth`` in the setpoints' frame."""
    sp_topic = topics.get("trajectory_setpoint")
    if sp_topic is None or len(sp_topic["timestamp"]) <= 10:
        return {}
    runs = stretches(t_st, nav_state == NAV_OFFBOARD, float(t_gt[-1]))
    if not runs:
        return {}
    window = max(runs, key=lambda r: r[1] - r[0])
    sp = xyz(sp_topic, ("position[0]", "position[1]", "position[2]"))
    off = offboard_tracking(np.asarray(sp_topic["timestamp"], float), sp, t_gt, truth, window)
    if off is None:
        return {}
    return {
        "offboard_s": (window[0] * 1e-6, window[1] * 1e-6),
        "offboard_max_m": off[0],
        "offboard_end_p50_m": off[1],
        "offboard_end_max_m": off[2],
        "offboard_rms_m": off[3],
    }


def read_ulog(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """The first instance of each of :data:`TOPICS` in a ULog, as arrays by field name."""
    from pyulog import ULog  # the dev extra: only this tool and the PX4 tier read ULogs

    ulog = ULog(str(path), list(TOPICS))
    out: dict[str, dict[str, np.ndarray]] = {}
    for d in ulog.data_list:
        if d.name == "timesync_status":  # one instance per link that got answers: the MAVLink one with most
            proto = d.data.get("source_protocol")
            if proto is not None and not np.all(np.asarray(proto) == TIMESYNC_SOURCE_MAVLINK):
                continue
            if d.name in out and len(out[d.name]["timestamp"]) >= len(d.data["timestamp"]):
                continue
            out[d.name] = dict(d.data)
        elif d.multi_id == 0:
            out[d.name] = dict(d.data)
    missing = [t for t in REQUIRED if t not in out]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)} in this log (not an SIH SITL flight?)")
    return out


def _lag_text(name: str, lag: Lag | None) -> str:
    if lag is None:
        return f"{name}: -"
    return (
        f"{name}: {lag.ms:.0f} ms behind, rms {lag.rms_m * 100:.1f} cm there, {lag.rms0_m * 100:.1f} cm at 0"
    )


def render(report: Report) -> str:
    """The report as text, one figure a line."""
    r = report
    lines = [
        f"hover {r.hover_s[0]:.1f}-{r.hover_s[1]:.1f} s: true distance from its median p50 "
        f"{r.hover_p50_m * 100:.1f} cm, max {r.hover_max_m * 100:.1f} cm (horizontal "
        f"{r.hover_xy_p50_m * 100:.1f} / {r.hover_xy_max_m * 100:.1f} cm), height {r.hover_height_m:.3f} m",
        _lag_text("estimate vs truth (airborne)", r.estimate_vs_truth),
        _lag_text("estimate vs truth (hover)", r.estimate_vs_truth_hover),
        _lag_text("estimate vs vision", r.estimate_vs_vision),
        _lag_text("vision vs truth", r.vision_vs_truth),
        _lag_text("vision vs truth, PX4's TIMESYNC error taken out", r.vision_vs_truth_synced),
    ]
    if r.timesync_error_ms is not None:
        lines.append(
            f"PX4's TIMESYNC estimate minus its answers (airborne): p50 {r.timesync_error_ms[0]:.1f} ms, "
            f"largest {r.timesync_error_ms[1]:.1f} ms"
        )
    if r.innovation_source is not None and r.innovation_rms_m is not None and r.test_ratio_p95 is not None:
        lines.append(
            f"{r.innovation_source} position innovations: rms {r.innovation_rms_m * 100:.1f} cm, "
            f"test ratio p95 {r.test_ratio_p95:.3f}"
        )
    if r.tracking_error_p50_m is not None and r.tracking_error_p95_m is not None:
        lines.append(
            f"output predictor tracking error: p50 {r.tracking_error_p50_m * 100:.1f} cm, "
            f"p95 {r.tracking_error_p95_m * 100:.1f} cm"
        )
    if r.offboard_s is not None and r.offboard_max_m is not None:
        lines.append(
            f"offboard {r.offboard_s[0]:.1f}-{r.offboard_s[1]:.1f} s: truth at most "
            f"{r.offboard_max_m * 100:.1f} cm from the setpoint (rms {(r.offboard_rms_m or 0) * 100:.1f} cm); "
            f"last 2 s from the final one p50 "
            f"{(r.offboard_end_p50_m or 0) * 100:.1f} cm, max {(r.offboard_end_max_m or 0) * 100:.1f} cm"
        )
    ts = "never (arrival times)" if r.timesync_from_s is None else f"from {r.timesync_from_s:.1f} s"
    lines.append(f"vision stamped with TIMESYNC: {ts}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: print the report of one ULog."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ulog", type=Path)
    parser.add_argument("--hover", nargs=2, type=float, metavar=("T0", "T1"), help="PX4 boot seconds")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    try:
        report = analyse(read_ulog(args.ulog), tuple(args.hover) if args.hover else None)
    except (OSError, ValueError) as exc:
        print(f"ulog_report: {exc}", file=sys.stderr)
        return 1
    out: Any = asdict(report)
    print(json.dumps(out, indent=1) if args.json else render(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
