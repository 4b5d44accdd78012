"""``make bench`` keeps working: a tiny run of every part at the smallest load, and its analysis pieces.

No figure is judged here (a shared machine's timings say nothing); what is checked is that the harness
starts the real processes, matches every ODOMETRY to its frame, counts, and writes its result and tables.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import pytest

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from bench import report
from bench import run as bench
from bench.floor import HEADER
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
from tests.conftest import REPO

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
        peer_rate=50.0,
        peer_duration=1.0,
        micro_scale=0.01,
        out_dir=tmp_path / "results",
        docs=docs,
        repo=REPO,
    )
    result = bench.run(options)

    points = {p["chain"]: p for p in result["points"]}
    assert set(points) == {"arena", "arena-td", "arena-td-v50", "floor-zenoh", "floor-udp"}
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
    for chain in ("floor-zenoh", "floor-udp"):
        assert points[chain]["delivered"] > 0 and points[chain]["latency"]["n"] == points[chain]["delivered"]

    peer = result["peer"]
    assert peer["gateway"]["forwarded"] > 0
    assert "forwarded" in peer["mavproxy"] or "unavailable" in peer["mavproxy"]
    assert result["micro"]["natnet_decode_us"]["10 bodies"] > 0
    assert result["micro"]["recorder"]["json (messages/s)"] > 0

    stored = json.loads((tmp_path / "results" / "latest.json").read_text())
    assert stored["points"] == json.loads(json.dumps(result["points"]))
    names = {t["name"] for t in stored["targets"]}
    assert names >= {"NatNet decode, 10-body frame", "20 × 360 Hz without loss"}
    text = docs.read_text()
    assert "Hand-written text stays." in text
    assert text.count(report.DOCS_BEGIN) == 1 and "| 1 × 180 Hz | arena |" in text

    report.update_docs(docs, bench.load_result(tmp_path / "results" / "latest.json"))
    assert docs.read_text().count(report.DOCS_BEGIN) == 1  # replaced, not appended
