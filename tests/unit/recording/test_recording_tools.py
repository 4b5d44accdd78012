"""Recording files and their tools: JSON form, unfinished files, repair, info, replay, export, plot."""

from __future__ import annotations

import base64
import csv
import gc
import json
import math
import os
import statistics
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import pytest
import zenoh
from mcap.exceptions import McapError
from mcap.reader import make_reader
from typer.testing import CliRunner

from arena_common.bus.session import Bus
from arena_common.cli import app
from arena_common.core import keys, wire
from arena_common.geometry import frames
from arena_common.recording import mcap as recording
from arena_common.recording.mcap import RecordingError, RecordingWriter, Sample
from tests.helpers import REPO, wait_for

runner = CliRunner()
ARENA = (sys.executable, "-m", "arena_common.cli")
T0 = 1_700_000_000_123_456_789  # ns: above 2^53, as every wall-clock time
BAD_SAMPLES = (
    ("arena/d1/pose", b"\xc1not msgpack", wire.Pose.encoding()),
    ("arena/d2/state", msgpack.packb({"t": 5, "armed": "yes"}), wire.State.encoding()),
    ("arena/d1/events", b"", "zenoh/bytes"),
)


@dataclass
class Flight:
    """What a synthetic flight recording holds."""

    path: Path
    samples: list[Sample]
    counts: dict[str, int]


def _reference(name: str, t: float) -> tuple[tuple[float, float, float], float]:
    """A flight plan: ground 0–2 s, climb to 1 m 2–4 s, circle or figure-eight until 16 s, land, ground."""
    cn, ce = (-1.5, -0.5) if name == "d1" else (1.2, 0.6)
    if t < 2.0:
        return (cn, ce, 0.0), 0.0
    if t < 4.0:
        return (cn, ce, -(t - 2.0) / 2.0), 0.0
    if t < 16.0:
        w = 2 * math.pi * (t - 4.0) / 6.0
        if name == "d1":
            return (cn + math.sin(w), ce + 1.0 - math.cos(w), -1.0), w
        return (cn + 0.9 * math.sin(w), ce + 0.6 * math.sin(2 * w), -1.0 - 0.3 * math.sin(w)), 0.5 * w
    w = 2 * math.pi * 12.0 / 6.0
    end = _reference(name, 15.999)[0]
    if t < 18.0:
        return (end[0], end[1], end[2] * (18.0 - t) / 2.0), w
    return (end[0], end[1], 0.0), w


def _true_state(name: str, t: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The vehicle lags its plan by 0.15 s and leans into its acceleration."""
    p, yaw = _reference(name, max(0.0, t - 0.15))
    p2, _ = _reference(name, max(0.0, t - 0.14))
    p0, _ = _reference(name, max(0.0, t - 0.16))
    acc = [(a - 2 * b + c) / 0.01**2 for a, b, c in zip(p2, p, p0, strict=True)]
    pitch = max(-0.4, min(0.4, -acc[0] / 9.81))
    roll = max(-0.4, min(0.4, acc[1] / 9.81))
    return p, frames.quat_from_euler(roll, pitch, yaw)


def flight_samples(duration: float = 20.0, names: tuple[str, ...] = ("d1", "d2")) -> list[Sample]:
    """Two vehicles flying: pose 180 Hz, vision 60 Hz, state 50 Hz, setpoints 20 Hz, events, telemetry,
    a few undecodable samples — in receive order."""
    out: list[tuple[int, Sample]] = []

    def add(key: str, payload: wire.Payload, t_recv: int) -> None:
        out.append((t_recv, Sample(key, payload.encode(), payload.encoding(), t_recv)))

    for name in names:
        n_pose = int(duration * 180)
        for i in range(n_pose):
            t = i / 180.0
            tn = T0 + round(t * 1e9)
            p, q = _true_state(name, t)
            ok = not (7.0 <= t < 7.05 and name == "d2")  # a short occlusion
            pose = wire.Pose(t=tn, p=p, q=q, ok=ok, fn=i + 1, tp=tn + 400_000)
            add(keys.pose(name), pose, tn + 600_000 + (i % 7) * 20_000)
            if i % 3 == 0:
                add(keys.vision(name), pose.replace(tp=tn + 700_000), tn + 900_000 + (i % 5) * 100_000)
        for i in range(int(duration * 50)):
            t = i / 50.0
            tn = T0 + round(t * 1e9)
            p, q = _true_state(name, t - 0.02)
            armed = 1.5 <= t < 18.5
            state = wire.State(
                t=tn,
                sysid=1 if name == "d1" else 2,
                link=True,
                armed=armed,
                mode="OFFBOARD" if 2.0 <= t < 16.0 else ("AUTO.LAND" if armed else "POSCTL"),
                landed="in_air" if 2.2 <= t < 17.8 else "on_ground",
                p=(p[0] + 0.004 * math.sin(37 * t), p[1] + 0.004 * math.cos(29 * t), p[2]),
                v=(0.0, 0.0, 0.0),
                q=q,
                bat=0.95 - 0.12 * t / duration,
                volt=16.4 - 0.8 * t / duration,
                vis_rate=60.0 if t > 0.5 else 0.0,
                vis_age=0.008 + 0.004 * math.sin(3 * t),
                vis_fused=True,
                ofb=2.0 <= t < 16.0,
                setup_ok=True,
                tp=tn + 300_000,
            )
            add(keys.state(name), state, tn + 800_000)
        for i in range(int(2.0 * 20), int(16.0 * 20)):
            t = i / 20.0
            tn = T0 + round(t * 1e9)
            p, yaw = _reference(name, t)
            add(
                keys.setpoint(name),
                wire.Setpoint(t=tn, p=p, yaw=frames.wrap_angle(yaw), src="test"),
                tn + 500_000,
            )
        for t, text in ((1.5, "armed"), (2.0, "mode OFFBOARD"), (16.0, "mode AUTO.LAND"), (18.5, "disarmed")):
            tn = T0 + round(t * 1e9)
            add(
                keys.events(name),
                wire.Event(t=tn, kind="mode", text=text, data={"x": math.nan}),
                tn + 1_000_000,
            )
        hb = wire.Telemetry(t=T0, msg="HEARTBEAT", f={"type": 2, "autopilot": 12, "custom_mode": 393216})
        add(keys.telemetry(name, "HEARTBEAT"), hb, T0 + 2_000_000)
    mocap = wire.MocapPose(t=T0, fn=1, id=1, p=(0.1, 0.2, 0.3), q=(1.0, 0.0, 0.0, 0.0), ok=True, name="d1")
    add(keys.mocap("d1"), mocap, T0 + 3_000_000)  # err is NaN: a nan_ok field, faithful in JSON
    for j, (key, raw, enc) in enumerate(BAD_SAMPLES):
        out.append((T0 + 5_000_000 + j, Sample(key, raw, enc, T0 + 5_000_000 + j)))
    out.sort(key=lambda x: x[0])
    return [s for _, s in out]


def write_flight(path: Path, encoding: str = "json", duration: float = 20.0, **meta: str) -> Flight:
    """Write a synthetic flight with :class:`RecordingWriter`, as the recorder does."""
    samples = flight_samples(duration)
    config_text = (REPO / "deploy/sim.toml").read_text()
    w = RecordingWriter(path, encoding=encoding, metadata={"config": config_text, "host": "test", **meta})
    counts: dict[str, int] = {}
    for s in samples:
        w.record(s)
        counts[s.key] = counts.get(s.key, 0) + 1
    w.close()
    return Flight(path, samples, counts)


# -- the JSON form ------------------------------------------------------------------------------------------


def test_json_form_times_nan_and_raw_fallback() -> None:
    pose = wire.MocapPose(t=T0, fn=3, id=1, p=(1.0, 2.0, 3.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, tp=T0 + 7)
    raw = pose.encode()
    data = json.loads(recording.encode_json(wire.MocapPose, msgpack.unpackb(raw), raw))
    assert data["t"] == {"sec": T0 // 10**9, "nsec": T0 % 10**9}
    assert data["tp"] == {"sec": T0 // 10**9, "nsec": T0 % 10**9 + 7}
    assert data["err"] is None and "_raw" not in data  # NaN of a nan_ok field: faithful without _raw
    assert msgpack.packb(recording.from_json_map(wire.MocapPose, data), use_bin_type=True) == raw
    jsonschema.validate(data, recording.record_schema(wire.MocapPose))

    ev = wire.Event(t=T0, kind="info", text="x", data={"v": math.nan, "b": 1})
    raw = ev.encode()
    data = json.loads(recording.encode_json(wire.Event, msgpack.unpackb(raw), raw))
    assert data["data"] == {"v": None, "b": 1}  # NaN inside a map cannot be told from nil in JSON…
    assert base64.b64decode(data["_raw"]) == raw  # …so the original bytes ride along
    jsonschema.validate(data, recording.record_schema(wire.Event))

    assert recording.time_from_json(recording.time_to_json(-1)) == -1
    assert recording.time_to_json(-1) == {"sec": -1, "nsec": 999_999_999}


# -- writing, reading, info ---------------------------------------------------------------------------------


def test_written_file_opens_with_mcap_reader_and_validates(tmp_path: Path) -> None:
    f = write_flight(tmp_path / "flight.mcap", duration=4.0)
    with open(f.path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        validators: dict[int, jsonschema.protocols.Validator] = {}
        for sid, sch in summary.schemas.items():
            assert sch.encoding == "jsonschema"
            doc = json.loads(sch.data)
            jsonschema.Draft202012Validator.check_schema(doc)
            validators[sid] = jsonschema.Draft202012Validator(doc)
        raw_keys: set[str] = set()
        n = 0
        for schema, channel, message in reader.iter_messages():
            n += 1
            if schema is None:
                raw_keys.add(channel.topic)
                assert channel.metadata["undecodable"] == "true"
                continue
            assert channel.message_encoding == "json"
            validators[schema.id].validate(json.loads(message.data))
        assert n == len(f.samples)
        assert raw_keys == {k for k, _, _ in BAD_SAMPLES}
    ri = recording.info(f.path)
    assert ri.complete and ri.error is None
    assert ri.counts_by_key() == f.counts
    pose = next(c for c in ri.channels if c.key == "arena/d1/pose" and not c.undecodable)
    assert pose.schema == "arena.Pose" and pose.zenoh_encoding == wire.Pose.encoding()
    assert 179.0 < pose.rate < 181.0
    d2 = next(c for c in ri.channels if c.key == "arena/d2/pose" and not c.undecodable)
    assert d2.max_gap < 0.0065e9  # 180 Hz with jitter, and the occlusion still sends (ok=false) poses
    assert ri.meta["host"] == "test" and ri.dropped == 0


def test_info_cli_and_drop_records(tmp_path: Path) -> None:
    path = tmp_path / "drops.mcap"
    w = RecordingWriter(path, metadata={"host": "h", "name": "x", "encoding": "json"})
    for i in range(10):
        w.record(Sample("arena/d1/pose", _pose(i).encode(), wire.Pose.encoding(), T0 + i * 10_000_000))
    w.add_drops(42, T0, T0 + 50_000_000)
    for i in range(10, 20):
        w.record(Sample("arena/d1/pose", _pose(i).encode(), wire.Pose.encoding(), T0 + i * 10_000_000))
    w.close()
    ri = recording.info(path)
    assert ri.dropped == 42 and len(ri.drops) == 1
    res = runner.invoke(app, ["rec", "info", str(path)])
    assert res.exit_code == 0, res.output
    assert "arena/d1/pose" in res.output and "DROPS:     42 samples lost in 1 episodes" in res.output
    assert "state:     complete" in res.output and "0.190 s" in res.output


def _pose(i: int) -> wire.Pose:
    return wire.Pose(t=T0 + i * 10_000_000, p=(0.01 * i, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=i)


def test_unfinished_file_reads_up_to_last_flush_and_repairs(tmp_path: Path) -> None:
    """A writer that never closed (the process was killed): what was flushed is read, the tail is not."""
    path = tmp_path / "killed.mcap"
    w = RecordingWriter(path, metadata={"host": "h"})
    for i in range(300):
        w.record(Sample("arena/d1/pose", _pose(i).encode(), wire.Pose.encoding(), T0 + i * 10_000_000))
        if i % 100 == 99:
            w.flush()
    for i in range(300, 350):  # in the open chunk when the process dies
        w.record(Sample("arena/d1/pose", _pose(i).encode(), wire.Pose.encoding(), T0 + i * 10_000_000))
    full = path.read_bytes()  # the file as the kill left it; the writer object is abandoned
    with open(path, "rb") as fh, pytest.raises(McapError):
        make_reader(fh).get_summary()  # no footer: the stock reader needs a repair
    reader = recording.RecordingReader(path)
    fns = [m.wire_map()["fn"] for m in reader.messages()]  # type: ignore[index]
    assert fns == list(range(300)) and not reader.complete and reader.chunks == 3
    # A torn last chunk (a power cut mid-write) loses only that chunk.
    torn = tmp_path / "torn.mcap"
    index = 9 + 2 + 4 + 100 * 16  # the third chunk's message index record follows it
    torn.write_bytes(full[: len(full) - index - 85])
    reader = recording.RecordingReader(torn)
    assert [m.wire_map()["fn"] for m in reader.messages()] == list(range(200))  # type: ignore[index]
    assert reader.error is not None

    res = runner.invoke(app, ["rec", "repair", str(path)])
    assert res.exit_code == 0, res.output
    fixed = tmp_path / "killed.repaired.mcap"
    assert "300 messages on 1 channels" in res.output
    with open(fixed, "rb") as fh:
        r = make_reader(fh)
        summary = r.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 300
        assert [json.loads(m.data)["fn"] for _, _, m in r.iter_messages()] == list(range(300))
        assert any(md.name == recording.META_RECORDING for md in r.iter_metadata())
    assert runner.invoke(app, ["rec", "repair", str(path)]).exit_code == 2  # refuses to overwrite
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"hello, not an mcap file at all")
    res = runner.invoke(app, ["rec", "repair", str(garbage)])
    assert res.exit_code == 2 and "not an MCAP file" in res.output


# -- replay -------------------------------------------------------------------------------------------------


def _replay_source(path: Path, encoding: str) -> list[Sample]:
    """Irregular gaps (5–45 ms) on three keys, NaN in an event's map, a MocapPose with NaN ``err``, a bad
    payload, and a setpoint (which replay leaves out by default); returns what should come back."""
    w = RecordingWriter(path, encoding=encoding, metadata={})
    sent: list[Sample] = []
    t = T0
    for i in range(60):
        t += (5 + (i * 7) % 41) * 1_000_000
        if i % 10 == 3:
            p: wire.Payload = wire.Event(t=t, kind="info", text=f"e{i}", data={"n": math.nan})
            key = keys.events("d1")
        elif i % 10 == 6:
            p = wire.MocapPose(t=t, fn=i, id=2, p=(1.0, 2.0, 3.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)
            key = keys.mocap("d2")
        else:
            p = _pose(i).replace(t=t)
            key = keys.pose("d1")
        s = Sample(key, p.encode(), p.encoding(), t)
        sent.append(s)
        w.record(s)
    bad = Sample("arena/d1/pose", b"\x93\x01\x02", wire.Pose.encoding(), t + 10_000_000)
    w.record(bad)
    sent.append(bad)
    sp = wire.Setpoint(t=t, p=(0, 0, -1))
    w.record(Sample("arena/d1/setpoint", sp.encode(), sp.encoding(), t + 20_000_000))
    w.close()
    return sent


@contextmanager
def few_gc_pauses() -> Iterator[None]:
    """Freeze this (large) test process's objects so a full collection cannot stall the timing."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


class Collector:
    """Samples arriving on ``replayed/**``: key, bytes, encoding, arrival (monotonic)."""

    def __init__(self, bus: Bus) -> None:
        self.got: list[tuple[str, bytes, str, float]] = []
        self._lock = threading.Lock()
        self._sub = bus.session.declare_subscriber("replayed/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append(
                (str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding), time.monotonic())
            )

    def clear(self) -> None:
        with self._lock:
            self.got.clear()

    def check(self, sent: list[Sample]) -> float:
        """Same keys (remapped), bytes and encodings in order, and the original timing.

        Returns the median inter-arrival error (s).  What is checked is the schedule, robustly against
        other work starving this shared 2-core machine for a moment: the median gap error is below 3 ms,
        three gaps in four are within 10 ms, and there is no drift (the median offset from the schedule
        over the last third differs from the first third's by less than 3 ms).
        """
        wait_for(lambda: len(self.got) >= len(sent), 15, 0.01, "replayed samples")
        self._sub.undeclare()
        assert [(k, b, e) for k, b, e, _ in self.got] == [
            (recording.remap_key(s.key, {"arena": "replayed"}), s.raw, s.encoding) for s in sent
        ]
        errors = sorted(
            abs((self.got[i][3] - self.got[i - 1][3]) - (sent[i].t_recv - sent[i - 1].t_recv) / 1e9)
            for i in range(1, len(sent))
        )
        median = errors[len(errors) // 2]
        text = f"inter-arrival errors: median {median * 1e3:.2f} ms, max {errors[-1] * 1e3:.2f} ms"
        assert median < 0.003, text  # about 0.2 ms idle; a loaded machine stretches it (1.25 ms seen)
        assert errors[int(len(errors) * 0.75)] < 0.01, text
        offsets = [
            (g[3] - self.got[0][3]) - (s.t_recv - sent[0].t_recv) / 1e9
            for g, s in zip(self.got, sent, strict=True)
        ]
        third = len(offsets) // 3
        drift = statistics.median(offsets[-third:]) - statistics.median(offsets[:third])
        assert abs(drift) < 0.01, f"the replay drifts from the schedule by {drift * 1e3:.2f} ms"
        return median


def test_replay_reproduces_bytes_and_timing(tmp_path: Path, bus_factory: Any) -> None:
    """The library function, msgpack file: publishes through a caller's function."""
    path = tmp_path / "r.mcap"
    sent = _replay_source(path, "msgpack")
    pub_bus: Bus = bus_factory()
    col = Collector(bus_factory())
    pubs: dict[tuple[str, str], Any] = {}

    def publish(key: str, data: bytes, enc: str) -> None:
        if (key, enc) not in pubs:
            pubs[(key, enc)] = pub_bus.session.declare_publisher(key, encoding=zenoh.Encoding(enc))
        pubs[(key, enc)].put(data)

    for key, enc in {(s.key, s.encoding) for s in sent}:  # routes known before the timing starts
        k = recording.remap_key(key, {"arena": "replayed"})
        pubs[(k, enc)] = pub_bus.session.declare_publisher(k, encoding=zenoh.Encoding(enc))
    wait_for(lambda: all(p.matching_status.matching for p in pubs.values()), 10, 0.01, "the subscriber")
    with few_gc_pauses():
        rep = recording.replay(path, publish, remap=recording.parse_remap(["arena=replayed"]))
        assert rep.sent == len(sent) and rep.skipped == 1  # the setpoint is not replayed by default
        col.check(sent)


def test_arena_replay_process_reproduces_a_json_file(
    tmp_path: Path, bus_factory: Any, router_endpoint: str
) -> None:
    """`arena replay` as a real process: JSON re-encoded to the original msgpack bytes, original timing."""
    path = tmp_path / "r.mcap"
    sent = _replay_source(path, "json")
    col = Collector(bus_factory())
    with few_gc_pauses():
        proc = subprocess.run(
            [
                *ARENA,
                "replay",
                str(path),
                "-e",
                router_endpoint,
                "--remap",
                "arena=replayed",
                "--start-delay",
                "20",
            ],
            cwd=REPO,
            env={**os.environ, "ARENA_CONFIG": "/nonexistent"},
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert proc.returncode == 0, proc.stderr
        assert f"replayed {len(sent)} messages in 1 pass(es), skipped 1" in proc.stdout
        col.check(sent)


def test_replay_filters_and_errors(tmp_path: Path) -> None:
    f = write_flight(tmp_path / "f.mcap", duration=0.5)
    seen: list[str] = []
    rep = recording.replay(
        f.path, lambda k, d, e: seen.append(k), speed=50.0, key_exprs=["arena/d2/**"], include_control=True
    )
    assert seen and all(k.startswith("arena/d2/") for k in seen)
    assert rep.sent == sum(n for k, n in f.counts.items() if k.startswith("arena/d2/"))
    with pytest.raises(RecordingError, match="speed"):
        recording.replay(f.path, lambda k, d, e: None, speed=0.0)
    with pytest.raises(RecordingError, match="--remap"):
        recording.parse_remap(["arena/*=x"])
    assert recording.remap_key("arena/d10/pose", {"arena/d1": "x"}) == "arena/d10/pose"
    assert recording.remap_key("arena/d1/pose", {"arena/d1": "x/y"}) == "x/y/pose"


# -- export and plots ---------------------------------------------------------------------------------------


def test_export_csv_and_parquet(tmp_path: Path) -> None:
    f = write_flight(tmp_path / "flight.mcap", duration=2.0)
    res = runner.invoke(app, ["export", str(f.path), "--format", "csv", "-o", str(tmp_path / "csv")])
    assert res.exit_code == 0, res.output
    pose_csv = tmp_path / "csv" / "arena.d1.pose.csv"
    with open(pose_csv) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == f.counts["arena/d1/pose"] - 1  # one was undecodable: in its own table
    assert {"log_time", "publish_time", "t_rel", "t", "p.0", "p.1", "p.2", "q.0", "q.3", "ok", "fn"} <= set(
        rows[0]
    )
    first_pose = next(s for s in f.samples if s.key == "arena/d1/pose")
    want = wire.Pose.decode(first_pose.raw)
    assert int(rows[0]["t"]) == want.t and float(rows[0]["p.0"]) == want.p[0]
    assert int(rows[0]["log_time"]) == first_pose.t_recv and int(rows[0]["publish_time"]) == want.tp
    assert (tmp_path / "csv" / "arena.d1.pose.undecodable.csv").exists()
    assert (
        (tmp_path / "csv" / "arena.d1.telemetry.HEARTBEAT.csv")
        .read_text()
        .splitlines()[0]
        .endswith("f.type,f.autopilot,f.custom_mode")
    )

    written = recording.export(f.path, tmp_path / "pq", "parquet")
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "pq" / "arena.d1.state.parquet")
    assert table.num_rows == f.counts["arena/d1/state"]
    assert str(table.schema.field("t").type) == "int64" and str(table.schema.field("p.2").type) == "double"
    assert len(written) == len({(s.key) for s in f.samples}) + len(BAD_SAMPLES)
    with pytest.raises(RecordingError, match="unknown export format"):
        recording.export(f.path, tmp_path, "xlsx")


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_plot_writes_figures(tmp_path: Path) -> None:
    f = write_flight(tmp_path / "flight.mcap", duration=20.0)
    res = runner.invoke(app, ["plot", str(f.path), "-o", str(tmp_path / "plots")])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    per = ("position", "attitude", "tracking", "vision", "battery")
    assert names == sorted(
        ["paths_top.png", "paths_side.png", *(f"{d}_{k}.png" for d in ("d1", "d2") for k in per)]
    )
    for p in (tmp_path / "plots").iterdir():
        w, h = _png_size(p)
        assert 600 <= w <= 2000 and 300 <= h <= 1200, (p.name, w, h)
        assert p.stat().st_size > 20_000, p.name  # a real figure, not a blank canvas
    empty = tmp_path / "empty.mcap"
    RecordingWriter(empty, metadata={}).close()
    res = runner.invoke(app, ["plot", str(empty), "-o", str(tmp_path / "none")])
    assert res.exit_code == 2 and "nothing" not in res.output and "no pose" in res.output
