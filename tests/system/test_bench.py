"""``make bench`` keeps working: a tiny run of every part at the smallest load, and its analysis pieces.

No figure is judged here (a shared machine's timings say nothing); what is checked is that the harness
starts the real processes, matches every ODOMETRY to its frame, counts, and writes its result and tables.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import struct
from pathlib import Path
from typing import Any

import pytest

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from bench import report, targets
from bench import run as bench
from bench.floor import HEADER, kept
from bench.harness import BenchError, latency_stats
from bench.matching import (
    _f32,
    _FrameInfo,
    analyze_arena,
    analyze_floor,
    mavlink_frame,
    odometry_of,
    payload_sizes,
)
from bench.peer import summarise
from bench.pipeline import PointResult, RunSettings, run_arena, vision_rates
from tests.helpers import REPO

pytestmark = pytest.mark.system


def test_latency_stats_percentiles() -> None:
    s = latency_stats([i * 1_000_000 for i in range(1, 101)])  # 1 … 100 ms
    assert s.n == 100
    assert s.p50 == pytest.approx(50.5)
    assert s.p99 == pytest.approx(99.01)
    assert s.max == 100.0
    empty = latency_stats([])
    assert empty.n == 0 and math.isnan(empty.p50)


def test_odometry_is_found_in_a_datagram() -> None:
    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=191)
    args = px4.odometry_args(1_234_567, (1.5, -0.25, -1.0), (1.0, 0.0, 0.0, 0.0))
    raw = bytes(mav.odometry_encode(**args).pack(mav))
    assert odometry_of(raw) == (1_234_567, (1.5, -0.25, -1.0))
    hb = bytes(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav))
    parsed = mavlink_frame(hb)
    assert parsed is not None and parsed[0] == 0
    assert odometry_of(hb) is None
    assert mavlink_frame(b"\x00garbage") is None


def test_floor_analysis_counts_lost_and_duplicated_messages() -> None:
    frames = [(1_000 * fn, struct.pack("<Q", fn) + bytes(20)) for fn in range(1, 11)]
    outs = {
        0: [(1_000 * fn + 300, HEADER.pack(fn, 0)) for fn in range(1, 11) if fn != 4],
        1: [(1_000 * fn + 500, HEADER.pack(fn, 1)) for fn in range(1, 11)] + [(20_000, HEADER.pack(5, 1))],
    }
    found = analyze_floor(frames, outs, 2_000, 9_000)  # frames 2 … 9
    assert found["expected"] == 16
    assert found["delivered"] == 15 and found["lost"] == 1
    assert found["duplicates"] == 1
    assert sorted(set(found["latencies"])) == [300, 500]


def _odometry(usec: int, p: tuple[float, float, float]) -> bytes:
    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=191)
    return bytes(mav.odometry_encode(**px4.odometry_args(usec, p, (1.0, 0.0, 0.0, 0.0))).pack(mav))


def test_arena_analysis_matches_by_position_and_time() -> None:
    # 100 frames at 180 Hz; vehicle 0 moves 1 cm per frame; the gateway's clock is 0.123 s off Motive's.
    period, offset = 5_555_555, 123_456_789
    frames = [
        _FrameInfo(
            k,
            2_000_000_000 + k * period + 5_380_000,
            2_000_000_000 + k * period,
            {0: _f32((0.01 * k, 0.5, -1.0))},
        )
        for k in range(100)
    ]
    outs = [
        (f.stamp + 2_000_000, _odometry((f.mid_ns + offset) // 1000, f.positions[0]))  # type: ignore[arg-type]
        for f in frames
        if f.fn != 50
    ]
    outs.append((frames[60].stamp + 1_000_000, _odometry(frames[60].mid_ns // 1000, (9.0, 9.0, 9.0))))
    t0, t1 = frames[10].stamp, frames[89].stamp

    every = analyze_arena(frames, {0: outs}, t0, t1, 180.0, vision_rate=400.0)
    assert (every["expected"], every["delivered"], every["lost"]) == (80, 79, 1)
    assert every["designed_drops"] == 0 and every["mismatched"] == 1 and every["duplicates"] == 0
    assert set(every["latencies"]) == {2_000_000}

    # At 50 Hz the decimator wants about one frame in 3.6; what came beyond that is not loss.
    deployed = analyze_arena(frames, {0: outs}, t0, t1, 180.0, vision_rate=50.0)
    assert 20 <= deployed["expected"] <= 24
    assert deployed["expected"] + deployed["designed_drops"] == 80
    assert deployed["lost"] == 0  # a neighbour of a missing frame may stand in for it: net count
    assert 79 - deployed["expected"] <= deployed["substituted"] <= 80 - deployed["expected"]


def test_payload_sizes_grow_with_bodies() -> None:
    one, ten = payload_sizes(1), payload_sizes(10)
    assert ten["natnet"] > one["natnet"] > 0
    assert one["mocap"] > 50 and one["pose"] > 50 and one["odometry"] > 200
    assert ten["frames"] > one["frames"] > 50  # one message carries every body of a frame


def test_bad_options_name_the_problem() -> None:
    with pytest.raises(BenchError, match="unknown part 'speed'"):
        bench.BenchOptions(parts=("speed",)).check()
    with pytest.raises(BenchError, match="vehicle counts"):
        bench.BenchOptions(vehicles=(0,)).check()
    with pytest.raises(BenchError, match="floor"):
        bench.BenchOptions(floors=("tcp",)).check()


def test_tiny_run_of_every_part(tmp_path: Path) -> None:
    docs = tmp_path / "performance.md"
    docs.write_text("# Performance\n\nHand-written text stays.\n")
    options = bench.BenchOptions(
        vehicles=(1,),
        rates=(180.0,),
        duration=1.0,
        warmup=0.3,
        idle=0.3,
        overload=1,
        peer_rate=50.0,
        peer_duration=0.5,
        peer_repeats=2,
        micro_scale=0.01,
        fleet=0,  # the fleet of 50 is make bench's, not a tiny run's
        growth=(1,),  # the growth table's smallest point, deployed as the fleet is
        out_dir=tmp_path / "results",
        docs=docs,
        repo=REPO,
    )
    result = bench.run(options)

    growth = [p for p in result["points"] if p["vehicle_mode"] == "client"]
    assert [(p["chain"], p["vehicles"], p["hogs"]) for p in growth] == [("arena-td-v50", 1, 0)], growth
    assert growth[0]["idle"] and growth[0]["delivered"] > 0
    points = {p["chain"]: p for p in result["points"] if p["vehicle_mode"] != "client"}
    assert set(points) == {
        "arena",
        "arena-td",
        "arena-td-v50",
        "arena-td-v50-loaded",
        "floor-zenoh",
        "floor-zenoh-v50",
        "floor-udp",
        "floor-udp-v50",
    }
    for chain, decimator in (("arena", "downsampler"), ("arena-td", "transform")):
        arena = points[chain]
        # Every ODOMETRY found its frame (matched by position and time), and the frames were counted.
        assert arena["expected"] > 0 and arena["delivered"] > 0
        assert arena["mismatched"] == 0 and arena["duplicates"] == 0
        assert arena["delivered"] + arena["lost"] == arena["expected"]
        assert arena["latency"]["n"] == arena["delivered"]
        assert 0 < arena["latency"]["p50"] <= arena["latency"]["max"]
        roles = {info["role"] for info in arena["per_service"].values()}
        assert {"router", "ingest", "transform", "gateway", "emulator"} <= roles
        assert ("downsampler" in roles) == (decimator == "downsampler")
        assert all(info["rss"] > 0 for info in arena["per_service"].values())
        assert arena["idle"], "idle figures of the per-vehicle processes"
    # At 50 Hz of vision from 180 Hz of mocap the decimator keeps about 5 frames in 18, by design.
    deployed = points["arena-td-v50"]
    assert deployed["designed_drops"] > deployed["expected"] > 0
    assert deployed["delivered"] > 0 and deployed["mismatched"] == 0
    assert deployed["vision_rate"]["min"] > 0
    # Overloaded on purpose: what gets through is the measurement, not a condition of the harness working.
    loaded = points["arena-td-v50-loaded"]
    assert loaded["hogs"] == 1 and any(i["role"] == "load" for i in loaded["per_service"].values())
    assert loaded["mismatched"] == 0 and set(loaded["vision_rate"]) == {"min", "median", "max"}
    for chain in ("floor-zenoh", "floor-udp", "floor-zenoh-v50", "floor-udp-v50"):
        assert points[chain]["delivered"] > 0 and points[chain]["latency"]["n"] == points[chain]["delivered"]
    # The floors' decimating relay passes the same share of the frames as the arena's decimator.
    assert points["floor-zenoh-v50"]["expected"] < points["floor-zenoh"]["expected"] / 2

    peer = result["peer"]
    assert peer["order"][:3] == ["gateway", "floor-zenoh", "floor-udp"]
    for name in ("gateway", "floor-zenoh", "floor-udp"):
        assert peer[name]["forwarded"] > 0 and peer[name]["repeats"] == 2
        assert len(peer[name]["runs"]) == 2 and len(peer[name]["load"]) == 2
    assert "forwarded" in peer["mavproxy"] or "unavailable" in peer["mavproxy"]
    assert result["micro"]["natnet_decode_us"]["10 bodies"] > 0
    assert result["micro"]["recorder"]["json (messages/s)"] > 0

    stored = json.loads((tmp_path / "results" / "latest.json").read_text())
    assert stored["points"] == json.loads(json.dumps(result["points"]))
    names = {t["name"] for t in stored["targets"]}
    assert names >= {
        "NatNet decode, 10-body frame",
        "gateway CPU per forwarded vision message",
        "pipeline CPU per vehicle, 1 × 180 Hz mocap, 50 Hz vision",
        "make bench duration",
    }
    text = docs.read_text()
    assert "**How cost grows**" in text and re.search(r"^\| 1 \| [\d.]+ \| [\d.]+ \|", text, re.M), text
    assert "Hand-written text stays." in text
    assert text.count(report.DOCS_BEGIN) == 1 and "| 1 × 180 Hz | arena |" in text

    report.update_docs(docs, bench.load_result(tmp_path / "results" / "latest.json"))
    assert docs.read_text().count(report.DOCS_BEGIN) == 1  # replaced, not appended


def test_the_gateways_of_several_vehicles_in_one_process(tmp_path: Path) -> None:
    """``--gateway-hosts 1``: the fleet's gateways in one bench.gateway_host process, each vehicle's vision
    still reaching its own MAVLink socket, matched to its frames."""
    settings = RunSettings(
        duration=1.0, warmup=0.3, idle=0.3, logs=tmp_path, repo=REPO, vehicle_mode="client", gateway_hosts=1
    )
    (point,) = run_arena(
        3, [180.0], settings, realistic_vision=50.0, decimate="transform", deployed_only=True
    )
    gateways = [name for name, info in point.per_service.items() if info["role"] == "gateway"]
    assert gateways == ["gateway-host.0"], point.per_service
    assert point.vision_rate["min"] > 0 and point.mismatched == 0 and point.duplicates == 0
    assert point.delivered > 0 and point.delivered + point.lost == point.expected
    assert "gateways in 1 process (bench.gateway_host), vision per frame" in point.notes


def test_floor_decimation_keeps_the_share_evenly() -> None:
    share = 50.0 / 180.0
    passed = [fn for fn in range(1, 1801) if kept(fn, share)]
    assert len(passed) == 500  # 50 of every 180 frames
    gaps = {b - a for a, b in itertools.pairwise(passed)}
    assert gaps <= {3, 4}
    assert all(kept(fn, 1.0) for fn in range(1, 10))
    frames = [(1_000 * fn, struct.pack("<Q", fn) + bytes(20)) for fn in range(1, 37)]
    outs = {0: [(1_000 * fn + 300, HEADER.pack(fn, 0)) for fn in range(1, 37) if kept(fn, share)]}
    found = analyze_floor(frames, outs, 1_000, 36_000, keep=share)
    assert found["expected"] == 10 and found["lost"] == 0
    assert found["per_vehicle"][0] == {"expected": 10, "delivered": 10}


def test_vision_rates_take_the_least_served_vehicle() -> None:
    rates = vision_rates({0: {"delivered": 150}, 1: {"delivered": 120}}, 3, 3.0)
    assert rates == {"min": 0.0, "median": 40.0, "max": 50.0}  # vehicle 2 received nothing
    assert vision_rates({}, 2, 0.0) == {}


def _run(cpu: float, p50: float, load: float = 0.5) -> dict[str, object]:
    lat = {"n": 100, "p50": p50, "p99": 2 * p50, "p999": 3 * p50, "max": 4 * p50, "mean": p50}
    return {
        "sent": 100,
        "forwarded": 100,
        "lost": 0,
        "latency": lat,
        "cpu_percent": cpu / 50,
        "idle_cpu_percent": 0.1,
        "cpu_us_per_msg": cpu,
        "marginal_cpu_us_per_msg": cpu - 10,
        "rss": 50 << 20,
        "load": load,
    }


def test_peer_summary_is_the_median_with_its_spread() -> None:
    s = summarise([_run(300, 0.4, 0.2), _run(250, 0.5, 0.3), _run(400, 0.3, 0.4)])
    assert s["cpu_us_per_msg"] == 300 and s["spread"]["cpu_us_per_msg"] == [250, 400]
    assert s["latency"]["p50"] == 0.4 and s["spread"]["p50"] == [0.3, 0.5]
    assert s["latency"]["max"] == pytest.approx(2.0)
    assert (s["sent"], s["forwarded"], s["repeats"], s["load"]) == (300, 300, 3, [0.2, 0.3, 0.4])
    row = report.peer_rows({"gateway": s, "mavproxy": summarise([_run(600, 0.3)])})[0]
    assert row[0] == "gateway" and row[4] == "300 (250–400)" and row[6] == "×0.50"
    assert row[-1] == "0.2, 0.3, 0.4"


def _point(chain: str, n: int, cpu: dict[str, float], p50: float = 1.0, **extra: object) -> dict[str, object]:
    services = {
        f"{role}.{k}": {
            "role": role,
            "pid": 1,
            "cpu": c / (n if role in ("gateway", "downsampler") else 1),
            "rss": 50 << 20,
        }
        for role, c in cpu.items()
        for k in range(n if role in ("gateway", "downsampler") else 1)
    }
    lat = {"n": 100, "p50": p50, "p99": 3 * p50, "p999": 4 * p50, "max": 5 * p50, "mean": p50}
    base: dict[str, object] = {
        "chain": chain,
        "vehicles": n,
        "rate": 180.0,
        "latency": lat,
        "expected": 100,
        "delivered": 100,
        "lost": 0,
        "per_service": services,
    }
    return {**base, **extra}


def _result(gateway_cpu: float, points: list[dict[str, object]], **extra: object) -> dict[str, Any]:
    peer = {
        "rate": 200.0,
        "duration": 2.5,
        "repeats": 3,
        "gateway": summarise([_run(gateway_cpu, 0.4)] * 3),
        "floor-zenoh": summarise([_run(170, 0.3)] * 3),
        "floor-udp": summarise([_run(60, 0.1)] * 3),
        "mavproxy": summarise([_run(360, 0.3)] * 3),
        "cpu_ratio": gateway_cpu / 360,
        "cpu_ratio_spread": [gateway_cpu / 380, gateway_cpu / 340],
    }
    base = {
        "points": points,
        "peer": peer,
        "elapsed_s": 250.0,
        "options": {"quick": False, "parts": list(bench.PARTS)},
    }
    return {**base, **extra}


def _targets(result: dict[str, object]) -> dict[str, targets.Target]:
    """The targets by the start of their name (up to a comma or parenthesis)."""
    return {re.split(r"[,(]", t.name)[0].strip(): t for t in report.evaluate_targets(result)}


def test_targets_from_a_synthetic_run() -> None:
    arena = {"router": 0.5, "ingest": 5.0, "transform": 8.0, "gateway": 4.0}
    floor = {"router": 0.5, "ingest": 3.0, "transform": 4.0, "downsampler": 2.0, "gateway": 1.5}
    deployed = {"min": 49.0, "median": 50.0, "max": 50.3}
    points = [
        _point("arena-td", 1, arena, p50=1.0),
        _point("arena", 1, {**arena, "downsampler": 4.0}, p50=1.3),
        _point("floor-zenoh", 1, floor, p50=0.9),
        _point("arena-td-v50", 1, arena, vision_rate=deployed),
        _point("floor-zenoh-v50", 1, floor),
        _point("arena-td-v50", 20, arena, p50=5.0, vision_rate=deployed),
        _point(
            "arena-td-v50-loaded",
            20,
            {**arena, "load": 120.0},
            p50=6.0,
            hogs=2,
            vision_rate={**deployed, "min": 30.0},
        ),
    ]
    t = _targets(_result(250.0, points))

    peer = t["gateway CPU per forwarded vision message"]
    assert peer.met is False and peer.measured.startswith("×0.69: ")
    assert (
        "gateway 250 µs, its Zenoh floor 170 µs, MAVProxy 360 µs: the floor alone is ×0.47" in peer.measured
    )
    assert t["gateway CPU per vision message vs its Zenoh floor"].met is True  # 250 / 170 ≤ 1.5
    cpu = t["pipeline CPU per vehicle"]  # 17.5 % against the floor's 11.0 % at vision 50 Hz
    assert cpu.met is False and cpu.measured.startswith("×1.59: 17.5 % vs floor 11.0 %")
    assert "transform 8.0/4.0" in cpu.measured and "downsampler —/2.0" in cpu.measured
    lat = t["1 vehicle × 180 Hz end to end p50"]
    assert lat.met is True and lat.measured.startswith("×1.11")  # arena-td, the faster configuration
    deployed_t = t["20 vehicles × 180 Hz as deployed"]
    assert deployed_t.met is True and "least 49.0 poses/s" in deployed_t.measured
    assert "p99 15.0 ms, lost 0/100" in deployed_t.measured
    loaded = t["vision first under overload: 20 vehicles × 180 Hz as deployed"]
    assert loaded.met is False and "least 30.0 poses/s" in loaded.measured
    assert "2 hogs took 120 %" in loaded.measured
    assert t["make bench duration"].met is True and t["make bench duration"].measured == "250 s"
    assert t["idle per-vehicle process RSS"].met is None  # no idle figures in this result

    t = _targets(_result(30.0, points, elapsed_s=320.0, options={"quick": True, "parts": list(bench.PARTS)}))
    assert t["gateway CPU per forwarded vision message"].met is True
    assert t["make bench duration"].met is None and "not a full run" in t["make bench duration"].measured
    slow = _targets(_result(30.0, points, elapsed_s=320.0))
    assert slow["make bench duration"].met is False

    nothing = report.evaluate_targets(
        {"points": [], "peer": {}, "elapsed_s": 10.0, "options": {"parts": ["micro"]}}
    )
    assert all(x.met is None for x in nothing)
    gone = _result(250.0, [])
    gone["peer"]["mavproxy"] = {
        "unavailable": "mavproxy exited with status 1:\n│ Traceback\n│ ImportError: x │"
    }
    why = _targets(gone)["gateway CPU per forwarded vision message"]
    assert why.met is None and why.measured == "MAVProxy: mavproxy exited with status 1: … ImportError: x"


def test_flames_compare_the_widest_and_the_busiest_frames(tmp_path: Path) -> None:
    from bench import flames

    stacks = {
        "before": [
            "Thread.run (threading.py:982);main (services/frame_transform.py:9);"
            "PoseConverter.convert (services/frame_transform.py:90);update (arena_common/geometry/filters.py:5) 30",
            "Thread.run (threading.py:982);main (services/frame_transform.py:9);Channel.get "
            "(arena_common/bus/session.py:140) 70",
        ],
        "after": ["main (services/frame_transform.py:9);Channel.get (arena_common/bus/session.py:141) 10"],
    }
    for label, lines in stacks.items():
        (tmp_path / label).mkdir()
        (tmp_path / label / "transform.txt").write_text("\n".join(lines) + "\n")
    before = flames.read(tmp_path / "before" / "transform.txt")
    assert before.samples == 100
    # Inclusive: the arena's own frames below the entry points; self: the leaves, file names without lines.
    assert before.inclusive == [
        ("Channel.get (session.py)", 70.0),
        ("PoseConverter.convert (frame_transform.py)", 30.0),
        ("update (filters.py)", 30.0),
    ]
    assert before.self_time == [("Channel.get (session.py)", 70.0), ("update (filters.py)", 30.0)]
    table = flames.table(tmp_path / "before", tmp_path / "after", 0, rate=100.0, seconds=2.0)
    rows = {tuple(c.strip() for c in r.split("|")[1:3]): r for r in table.splitlines()}
    assert "| 50.0 % |" in rows[("transform", "before")]  # 100 samples of 100 Hz × 2 s
    assert "| 5.0 % |" in rows[("transform", "after")]
    assert "(no profile)" in rows[("gateway.d1", "after")]


def test_the_rate_sweep_compares_each_forwarder_with_mavproxy_at_the_same_rate() -> None:
    def fig(us: float, forwarded: int = 1000) -> dict[str, Any]:
        return {"marginal_cpu_us_per_msg": us, "forwarded": forwarded, "sent": 1000}

    peer: dict[str, Any] = {
        "rate": 200.0,
        "gateway": {"marginal_cpu_us_per_msg": 150.0},
        "mavproxy": {"marginal_cpu_us_per_msg": 300.0},
        "floor-udp": {"unavailable": "not started"},
        "sweep": {
            "gateway": {"1000": fig(100.0), "4000": {"unavailable": "went away"}},
            "mavproxy": {"1000": fig(250.0, 990), "4000": fig(200.0)},
        },
    }
    assert report.sweep_header(peer) == ["forwarder", "200 Hz (median)", "1000 Hz", "4000 Hz"]
    rows = {r[0]: r[1:] for r in report.sweep_rows(peer)}
    assert rows["gateway"][:2] == ["150 µs (×0.50)", "100 µs (×0.40)"] and "went away" in rows["gateway"][2]
    assert rows["mavproxy"] == ["300 µs", "250 µs, 990/1000 forwarded", "200 µs"]
    assert "floor-udp" not in rows
    assert report.sweep_rows({"rate": 200.0}) == []


def test_the_fleet_point_is_judged_against_issue_27s_targets() -> None:
    """50 vehicles: vision as deployed in each configuration and beside CPU hogs (p50 ≤ 2.6 ms, p99 ≤ 10 ms),
    idle RSS and CPU per per-vehicle process with the whole arena's, start-up to vision."""
    arena = {"router": 1.0, "ingest": 9.0, "transform": 30.0, "gateway": 150.0}
    idle = {
        f"gateway.d{k}": {"role": "gateway", "pid": 1, "cpu": 0.15 if k else 0.3, "rss": 45 << 20}
        for k in range(50)
    }
    idle["transform"] = {"role": "transform", "pid": 1, "cpu": 2.0, "rss": 90 << 20}
    deployed = {"min": 48.0, "median": 50.0, "max": 50.2}
    points = [  # the fleet point runs deployed only: its idle figures and start-up come with the first
        _point(
            "arena-td-v50",
            50,
            arena,
            p50=2.0,
            vision_rate=deployed,
            idle=idle,
            startup={"services": 21.0, "vision": 4.5},
        ),
        _point("arena-td-v50-loaded", 50, arena, p50=4.0, vision_rate=deployed, hogs=2),
        _point("arena-v50", 50, arena, p50=2.5, vision_rate={"min": 30.0, "median": 50.0, "max": 50.0}),
    ]
    t = {x.name: x for x in report.evaluate_targets(_result(250.0, points))}
    vision = t["50 vehicles × 180 Hz as deployed (vision 50 Hz), transform decimates"]
    assert vision.met is True and vision.measured.startswith("p50 2.0 ms, least 48.0 poses/s")
    assert vision.goal.endswith("p50 ≤ 2.6 ms, p99 ≤ 10 ms, no undesigned loss")
    loaded = t["50 vehicles × 180 Hz as deployed (vision 50 Hz) beside 2 CPU hogs, transform decimates"]
    assert loaded.met is False and loaded.measured.startswith("p50 4.0 ms")  # p50 and p99 over
    per_vehicle = t["50 vehicles × 180 Hz as deployed (vision 50 Hz), downsampler per vehicle"]
    assert per_vehicle.met is False and "least 30.0 poses/s" in per_vehicle.measured  # a vehicle starved
    rss = t["idle per-vehicle process RSS at 50 vehicles"]
    assert rss.met is False and rss.measured.startswith(
        "45.0 MB per vehicle: largest process 45.0 MB, total 2250.0 MB over 50 processes"
    )
    assert rss.measured.endswith("the whole arena 2340 MB (transform decimates)")
    cpu = t["idle per-vehicle process CPU at 50 vehicles (no mocap)"]
    assert cpu.met is False and cpu.measured.startswith(
        "0.30 % per vehicle: largest process 0.30 %, total 7.65 %"
    )
    hosted = {"gateways.0": {"role": "gateway", "pid": 2, "cpu": 8.0, "rss": 62 << 20}}
    hosted_point = _point("arena-td-v50", 50, arena, p50=6.0, vision_rate=deployed, idle=hosted)
    one_host = _targets(_result(250.0, [hosted_point]))  # one process serving the 50 vehicles' links
    assert one_host["idle per-vehicle process RSS at 50 vehicles"].met is True
    assert one_host["idle per-vehicle process RSS at 50 vehicles"].measured.startswith("1.2 MB per vehicle")
    assert one_host["idle per-vehicle process CPU at 50 vehicles"].met is True
    assert "0.16 % per vehicle: largest process 8.00 % serving 50 vehicles each" in (
        one_host["idle per-vehicle process CPU at 50 vehicles"].measured
    )
    up = t["start-up of 50 vehicles to vision from every vehicle"]
    assert up.met is True and up.measured.startswith("25.5 s: services alive 21.0 s")
    assert _targets(_result(250.0, points[1:]))["idle per-vehicle process RSS at 50 vehicles"].met is None
    core = t["the whole arena's CPU at 50 vehicles as deployed, transform decimating"]
    assert core.met is False and core.measured == "190 % of one core"  # router, ingest, transform, gateways
    no_fleet = _targets(_result(250.0, [_point("arena-td", 20, arena)]))
    assert not [name for name in no_fleet if "50 vehicles" in name]  # judged only when a fleet point ran


def test_the_growth_table_reads_the_cost_per_vehicle_across_fleet_sizes() -> None:
    """One row per vehicle count deployed as the fleet is (an explicit vehicle mode, no hogs); the default
    configuration's points and the overloaded ones stay out."""
    idle = {"gateway.d0": {"role": "gateway", "pid": 1, "cpu": 0.25, "rss": 40 << 20}}
    points = [
        _point("arena-td-v50", 1, {"router": 1.0, "ingest": 5.0, "transform": 6.0, "gateway": 3.0},
               vehicle_mode="client", idle=idle),
        _point("arena-td-v50", 10, {"router": 2.0, "ingest": 8.0, "transform": 20.0, "gateway": 30.0},
               vehicle_mode="client", idle=idle, p50=1.5),
        _point("arena-td-v50", 10, {"router": 9.0, "gateway": 90.0}, p50=9.0),  # the config's default mode
        _point("arena-td-v50-loaded", 10, {"router": 9.0, "gateway": 90.0}, vehicle_mode="client", hogs=2),
    ]  # fmt: skip
    rows = report.growth_rows([PointResult(**p) for p in points])  # type: ignore[arg-type]
    assert [r[:4] for r in rows] == [["1", "15.0", "15.00", "3.00"], ["10", "60.0", "6.00", "3.00"]], rows
    assert rows[0][4] == "50.0" and rows[0][5] == "0.25" and rows[1][6] == "1.500", rows
