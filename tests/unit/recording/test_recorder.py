"""The recorder service: a stream recorded without loss, kill -9 safety, experiments, splits, guards."""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
from mcap.reader import make_reader
from typer.testing import CliRunner

from arena_common.bus.session import Bus
from arena_common.cli import app
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, RecorderSpec
from arena_common.recording import mcap as recording
from arena_common.recording.mcap import Recorder, Sample
from services import recorder as recorder_service
from tests.helpers import REPO, wait_for

runner = CliRunner()
HOST = "rt"


@contextmanager
def recorder_thread(cfg: ArenaConfig, directory: Path, host: str = HOST) -> Iterator[threading.Thread]:
    """The recorder's ``main`` in a thread, stopped and joined at the end."""
    stop = threading.Event()
    th = threading.Thread(
        target=recorder_service.main,
        args=(cfg,),
        kwargs={"host": host, "stop": stop, "directory": directory},
        daemon=True,
    )
    th.start()
    try:
        yield th
    finally:
        stop.set()
        th.join(timeout=15)
        assert not th.is_alive(), "the recorder did not stop"


def ping(bus: Bus, host: str = HOST) -> dict[str, Any]:
    res = bus.request(keys.rec_control(host), wire.Command(op="ping", timeout=2.0))
    return dict(res.value) if res.ok else {}


def wait_ready(bus: Bus, host: str = HOST, timeout: float = 20.0) -> dict[str, Any]:
    """Until the recorder answers and records what this bus publishes (its subscription is in place)."""
    wait_for(lambda: ping(bus, host), timeout, 0.1, "the recorder's control queryable")
    probe = bus.command_publisher("arena/probe/events", wire.Event)

    def seen() -> dict[str, Any]:
        probe.put(wire.Event(t=wire.now_ns(), kind="info", text="probe"))
        st = ping(bus, host)
        return st if "arena/probe/events" in st.get("keys", []) else {}

    return wait_for(seen, timeout, 0.1, "the recorder to record a probe")


def file_counts(path: Path) -> dict[str, int]:
    """Messages per key readable now (the file may still be open)."""
    try:
        return recording.info(path).counts_by_key()
    except recording.RecordingError:
        return {}


def test_realistic_stream_recorded_without_loss(
    tmp_path: Path, arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """Three vehicles' poses at 180 Hz, states at 50 Hz, events and bad payloads: every one recorded."""
    cfg = arena_config(n_vehicles=3, extra="[recorder]\nflush_s = 0.2\n")
    bus = bus_factory()
    names = ("d1", "d2", "d3")
    with recorder_thread(cfg, tmp_path / "rec"):
        st = wait_ready(bus)
        path = Path(st["file"])
        assert path.name.startswith(f"rec_{HOST}_") and path.parent == tmp_path / "rec"
        pose_pubs = {n: bus.stream_publisher(keys.pose(n), wire.Pose) for n in names}
        state_pubs = {n: bus.stream_publisher(keys.state(n), wire.State) for n in names}
        event_pub = bus.command_publisher(keys.events("d1"), wire.Event)
        expected: dict[str, int] = {}

        def sent(key: str) -> None:
            expected[key] = expected.get(key, 0) + 1

        t_start = time.monotonic()
        ticks = 360  # 2 s at 180 Hz
        for i in range(ticks):
            now = wire.now_ns()
            for j, n in enumerate(names):
                pose_pubs[n].put(
                    wire.Pose(
                        t=now, p=(0.01 * i, float(j), -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=i + 1, tp=now
                    )
                )
                sent(keys.pose(n))
                if (i * 50) // 180 != ((i - 1) * 50) // 180 or i == 0:
                    state_pubs[n].put(
                        wire.State(t=now, armed=True, mode="OFFBOARD", p=(0.0, 0.0, -1.0), tp=now)
                    )
                    sent(keys.state(n))
            if i % 60 == 0:
                event_pub.put(wire.Event(t=now, kind="info", text=f"tick {i}", data={"i": i}))
                sent(keys.events("d1"))
            if i % 120 == 7:
                pose_pubs["d2"].put_raw(b"\xc1 not msgpack")
                sent(keys.pose("d2"))
                state_pubs["d3"].put_raw(msgpack.packb({"t": now, "armed": "yes"}))
                sent(keys.state("d3"))
            delay = t_start + (i + 1) / 180.0 - time.monotonic()
            if delay > 0:
                time.sleep(delay)

        def complete() -> bool:
            got = file_counts(path)
            return all(got.get(k, 0) >= n for k, n in expected.items())

        wait_for(complete, 20, 0.3, "every published sample in the file")
    ri = recording.info(path)
    assert ri.complete and ri.error is None and ri.dropped == 0
    counts = ri.counts_by_key()
    assert {k: counts.get(k, 0) for k in expected} == expected
    assert sum(c.count for c in ri.channels if c.undecodable) == 6
    assert ri.meta["host"] == HOST and ri.meta["config"] == Path(cfg.path).read_text()
    assert ri.meta["version"] == recording.software_version()
    res = runner.invoke(app, ["rec", "info", str(path)])
    assert res.exit_code == 0, res.output
    for key, count in expected.items():
        line = next(
            ln
            for ln in res.output.splitlines()
            if ln.split()[:2] in ([key, "arena.Pose"], [key, "arena.State"], [key, "arena.Event"])
        )
        assert int(line.split()[3]) == count - (3 if key in ("arena/d2/pose", "arena/d3/state") else 0)

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        validators = {
            sid: jsonschema.Draft202012Validator(json.loads(s.data))
            for sid, s in summary.schemas.items()
            if s.encoding == "jsonschema"
        }
        # the arena's keys in JSON, and beside them the Foxglove 3D scene in protobuf
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema", "protobuf"}
        scene_ids = {cid for cid, ch in summary.channels.items() if ch.metadata.get("arena_scene") == "true"}
        assert {summary.channels[c].topic for c in scene_ids} >= {"/arena/tf", "/arena/scene/room"}
        for cid, ch in summary.channels.items():
            if cid in scene_ids:
                assert ch.message_encoding == "protobuf"
                assert summary.schemas[ch.schema_id].name.startswith("foxglove.")
                continue
            assert (ch.schema_id == 0) == (ch.metadata["undecodable"] == "true")
            assert ch.metadata["zenoh_encoding"].startswith("application/msgpack;arena.")
        n_json = n_scene = 0
        for schema, channel, message in reader.iter_messages():
            if channel.id in scene_ids:
                n_scene += 1
                continue
            if schema is None:
                assert channel.topic in ("arena/d2/pose", "arena/d3/state")
                continue
            doc = json.loads(message.data)
            validators[schema.id].validate(doc)
            n_json += 1
            if channel.topic == "arena/d1/pose":
                t = doc["t"]["sec"] * 10**9 + doc["t"]["nsec"]
                assert message.publish_time == t and message.log_time >= t  # publish = tp, log = receipt
        assert n_scene > 0 and n_json == ri.messages - 6 - n_scene


def test_kill_9_keeps_everything_before_the_last_flush(
    tmp_path: Path, arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(extra="[recorder]\nflush_s = 0.25\n")
    out = tmp_path / "rec"
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.recorder", "-c", cfg.path, "--host", "rk", "--dir", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    bus = bus_factory()
    published: list[tuple[int, float]] = []  # (fn, monotonic time of publication)
    stop_pub = threading.Event()
    try:
        path = Path(wait_ready(bus, "rk", timeout=40)["file"])
        pub = bus.stream_publisher(keys.pose("d1"), wire.Pose)

        def stream() -> None:
            fn = 0
            t0 = time.monotonic()
            while not stop_pub.is_set() and fn < 180 * 30:
                fn += 1
                pub.put(
                    wire.Pose(t=wire.now_ns(), p=(0.0, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=fn)
                )
                published.append((fn, time.monotonic()))
                delay = t0 + fn / 180.0 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)

        th = threading.Thread(target=stream, daemon=True)
        th.start()
        wait_for(
            lambda: file_counts(path).get("arena/d1/pose", 0) > 180, 20, 0.2, "a second of poses on disk"
        )
        on_disk = file_counts(path)["arena/d1/pose"]  # flushed before the kill, however late (a busy host)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        time.sleep(0.1)
        stop_pub.set()
        th.join(timeout=5)
    finally:
        stop_pub.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    reader = recording.RecordingReader(path)
    fns = [m.wire_map()["fn"] for m in reader.messages() if m.channel.key == "arena/d1/pose"]  # type: ignore[index]
    assert not reader.complete
    assert fns == list(range(1, len(fns) + 1)), "a hole in what was read"
    assert len(fns) >= on_disk > 180  # everything flushed before the kill is still there
    assert fns[-1] < published[-1][0]  # what came after the kill is not there

    res = runner.invoke(app, ["rec", "repair", str(path)])
    assert res.exit_code == 0, res.output
    with open(recording.repaired_path(path), "rb") as fh:
        r = make_reader(fh)
        summary = r.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.channel_message_counts[
            next(c.id for c in summary.channels.values() if c.topic == "arena/d1/pose")
        ] == len(fns)


def test_rec_start_stop_and_status_by_command(
    tmp_path: Path,
    arena_config: Callable[..., ArenaConfig],
    bus_factory: Callable[[], Bus],
    router_endpoint: str,
) -> None:
    cfg = arena_config()
    out = tmp_path / "rec"
    bus = bus_factory()
    cli = ["-e", router_endpoint, "-r", HOST]
    with recorder_thread(cfg, out):
        first = Path(wait_ready(bus)["file"])
        res = runner.invoke(app, ["rec", "start", "exp1", *cli])
        assert res.exit_code == 0, res.output
        assert f"{HOST}: ACCEPTED recording to {out}/exp1_{HOST}_" in res.output
        assert recording.info(first).complete  # the previous file was closed properly
        st = ping(bus)
        exp = Path(st["file"])
        assert exp.name.startswith(f"exp1_{HOST}_") and exp.name.endswith(".mcap")
        pub = bus.command_publisher(keys.events("d1"), wire.Event)
        for i in range(5):
            pub.put(wire.Event(t=wire.now_ns(), kind="info", text=f"during {i}"))
        wait_for(lambda: file_counts(exp).get("arena/d1/events", 0) == 5, 10, 0.2, "events in the file")
        res = runner.invoke(app, ["rec", "stop", *cli])
        assert res.exit_code == 0 and f"closed {exp}" in res.output, res.output
        ri = recording.info(exp)
        assert ri.complete and ri.counts_by_key()["arena/d1/events"] == 5
        res = runner.invoke(app, ["rec", "status", *cli])
        assert res.exit_code == 0 and f"{HOST}: idle -" in res.output, res.output
        pub.put(wire.Event(t=wire.now_ns(), kind="info", text="while idle"))
        res = runner.invoke(app, ["rec", "start", "bad name", *cli])
        assert res.exit_code == 2 and "invalid experiment name" in res.output
        res = runner.invoke(app, ["rec", "start", "exp2", *cli])
        assert res.exit_code == 0, res.output
        assert sorted(p.name.split("_")[0] for p in out.iterdir()) == ["exp1", "exp2", "rec"]
        assert bus.request(keys.rec_control(HOST), wire.Command(op="arm")).result == "UNSUPPORTED"
    assert recording.info(exp).counts_by_key()["arena/d1/events"] == 5  # nothing while idle
    res = runner.invoke(app, ["rec", "status", "-e", router_endpoint, "-r", "nobody"])
    assert res.exit_code == 1 and "no recorder answers" in res.output


def test_two_recorders_answer_one_start(
    tmp_path: Path,
    arena_config: Callable[..., ArenaConfig],
    bus_factory: Callable[[], Bus],
    router_endpoint: str,
) -> None:
    """Recorders on several hosts at once: one `rec start` reaches all; file names carry the host."""
    cfg = arena_config()
    bus = bus_factory()
    out = tmp_path / "rec"
    with recorder_thread(cfg, out, host="ra"), recorder_thread(cfg, out, host="rb"):
        wait_ready(bus, "ra")
        wait_ready(bus, "rb")
        res = runner.invoke(app, ["rec", "start", "both", "-e", router_endpoint])
        assert res.exit_code == 0, res.output
        assert "ra: ACCEPTED recording to" in res.output and "rb: ACCEPTED recording to" in res.output
        assert {ping(bus, h)["file"].rsplit("/", 1)[-1].split("_")[1] for h in ("ra", "rb")} == {"ra", "rb"}
    names = sorted(p.name.rsplit("_", 1)[0] for p in out.iterdir())
    assert names == ["both_ra", "both_rb", "rec_ra", "rec_rb"]


def test_auto_on_arm_starts_a_file(
    tmp_path: Path, arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(extra='[recorder]\nauto_on_arm = true\nkeys = ["arena/*/pose", "arena/probe/**"]\n')
    assert recorder_service.key_exprs(cfg) == ["arena/*/pose", "arena/probe/**", "arena/*/state"]
    bus = bus_factory()
    with recorder_thread(cfg, tmp_path / "rec"):
        first = wait_ready(bus)["file"]
        pub = bus.command_publisher(keys.state("d1"), wire.State)
        pub.put(wire.State(t=wire.now_ns(), armed=False))
        wait_for(lambda: "arena/d1/state" in ping(bus)["keys"], 10, 0.1, "the disarmed state")
        pub.put(wire.State(t=wire.now_ns(), armed=True))
        st = wait_for(lambda: (s := ping(bus))["file"] != first and s, 10, 0.1, "a new file on arming")
        assert Path(st["file"]).name.startswith(f"arm-d1_{HOST}_")
        pub.put(wire.State(t=wire.now_ns(), armed=True))
        time.sleep(0.3)
        assert ping(bus)["file"] == st["file"]  # staying armed does not split again


def test_disk_guard_refuses_to_fill_the_disk(
    tmp_path: Path,
    arena_config: Callable[..., ArenaConfig],
    bus_factory: Callable[[], Bus],
    router_endpoint: str,
) -> None:
    cfg = arena_config(extra="[recorder]\nmin_free_mb = 1e7\n")  # 10 TB free required
    bus = bus_factory()
    with recorder_thread(cfg, tmp_path / "rec"):
        st = wait_for(lambda: ping(bus), 20, 0.1, "the recorder")
        assert st["state"] == "disk_full" and "MB free" in st["reason"] and st["file"] == ""
        res = runner.invoke(app, ["rec", "start", "x", "-e", router_endpoint, "-r", HOST])
        assert res.exit_code == 1 and "FAILED only" in res.output, res.output
    assert not (tmp_path / "rec").exists() or not any((tmp_path / "rec").iterdir())


# -- the Recorder without a bus: splits and drop records --------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _sample(i: int, pad: int = 0) -> Sample:
    p = wire.Event(
        t=1_700_000_000_000_000_000 + i, kind="info", text=secrets.token_hex(pad // 2), data={"i": i}
    )
    return Sample(keys.events("d1"), p.encode(), p.encoding(), p.t)


def test_recorder_splits_by_size_and_duration_and_records_drops(tmp_path: Path) -> None:
    events: list[tuple[str, int]] = []
    clock = FakeClock()
    spec = RecorderSpec(flush_s=0.5, split_mb=1.0, split_s=10.0, min_free_mb=0.0, encoding="msgpack")
    rec = Recorder(spec, "h1", directory=tmp_path, on_event=lambda t, s: events.append((t, s)), clock=clock)
    first = rec.start("sz")
    assert first is not None
    for i in range(700):  # ≈1.5 MB after compression: split once at the next flush after 1 MB
        rec.write(_sample(i, pad=4000))
        if i % 50 == 49:
            clock.now += 0.6
            rec.tick()
    assert rec.note_drops(7) == 7 and rec.note_drops(7) == 0
    clock.now += 10.5  # the duration limit
    rec.tick()
    rec.write(_sample(9999))
    rec.close()
    names = [p.name for p in rec.files]
    assert len(names) == 3 and names[1].endswith("_p2.mcap") and names[2].endswith("_p3.mcap")
    infos = [recording.info(p) for p in rec.files]
    assert all(ri.complete for ri in infos)
    assert infos[0].size >= 1_000_000 and sum(sum(ri.counts_by_key().values()) for ri in infos) == 701
    assert infos[1].dropped == 7 and infos[0].dropped == 0
    assert any("7 samples dropped" in t for t, _ in events)
    assert [ri.meta["part"] for ri in infos] == ["1", "2", "3"]
    ch = next(c for c in infos[0].channels if not c.scene)
    assert ch.encoding == "msgpack" and ch.schema == "arena.Event"
