"""The mocap ingest service: rigid bodies from a NatNet server (or a CSV take) to ``arena/<drone>/mocap``.

The server is the test's own :class:`~tests.unit.mocap.test_natnet_client.FakeMotive` on loopback (multicast and
unicast); the service runs in a thread with a stop event, and once as a real process.
"""

from __future__ import annotations

import itertools
import math
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus, Subscription
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import WaitTimeout
from arena_common.mocap.natnet import MessageId, ModelDefs, RigidBody
from arena_common.pipeline.ingest import body_key_name, encode_pose
from services import mocap_ingest
from tests.helpers import REPO, TESTS, Proc, service_argv, wait_for, write_config
from tests.unit.mocap.test_natnet_client import Body, FakeMotive

TAKE = TESTS / "data" / "motive_take.csv"


def make_config(
    tmp_path: Path, router: str, n_vehicles: int = 2, mocap: str = "", by_id: dict[str, int] | None = None
) -> ArenaConfig:
    """A test config (private ports) with extra ``[mocap]`` lines and some vehicles claimed by body id."""
    path = write_config(tmp_path, router, n_vehicles)
    text = path.read_text().replace("[mocap]\n", f"[mocap]\n{mocap}\n", 1)
    for vehicle, body_id in (by_id or {}).items():
        text = text.replace(f'rigid_body = "{vehicle}"', f"rigid_body = {body_id}")
    path.write_text(text)
    return config_mod.load(path)


def server_for(cfg: ArenaConfig, **kwargs: Any) -> FakeMotive:
    return FakeMotive(command_port=cfg.mocap.command_port, data_port=cfg.mocap.data_port, **kwargs)


@pytest.fixture
def service() -> Iterator[Callable[..., threading.Event]]:
    """Run ``mocap_ingest.main`` in threads; stopped and joined at the end of the test."""
    running: list[tuple[threading.Thread, threading.Event]] = []

    def start(cfg: ArenaConfig, **kwargs: Any) -> threading.Event:
        stop = threading.Event()
        thread = threading.Thread(
            target=mocap_ingest.main,
            args=(cfg,),
            kwargs={"stop": stop, "host": "test", **kwargs},
            daemon=True,
        )
        thread.start()
        running.append((thread, stop))
        return stop

    yield start
    for thread, stop in running:
        stop.set()
        thread.join(timeout=10)
        assert not thread.is_alive(), "the service did not stop"


def latest(sub: Subscription, seen: dict[str, Any]) -> dict[str, Any]:
    """Drain ``sub`` into ``seen`` (key → every decoded payload) and return it."""
    first = sub.get(0.01)  # wait a little, then take what is there: a live stream never runs dry
    for item in ([first] if first is not None else []) + sub.channel.drain():
        assert item.error is None, item.error
        seen.setdefault(item.key, []).append(item.payload)
    return seen


def feed(
    server: FakeMotive, sub: Subscription, seen: dict[str, Any], pred: Callable[[], bool], what: str
) -> None:
    """Stream frames every 10 ms until ``pred`` holds (bounded)."""
    deadline = time.monotonic() + 15.0
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}; got keys {sorted(seen)}")
        server.send_frame()
        time.sleep(0.01)
        latest(sub, seen)


def test_encode_pose_is_the_wire_encoding() -> None:
    cases = [
        (RigidBody(3, (0.1, 1.0, -0.5), (0.0, 0.6, 0.0, 0.8), 0.0004, True, 1), True),
        (RigidBody(3, (0.1, 1.0, -0.5), (0.0, 0.6, 0.0, 0.8), None, True, 1), True),
        (RigidBody(3, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), None, False, 0), False),
        (RigidBody(3, (0.2, 0.3, 0.4), (0.0, 0.0, 0.0, 0.0), 0.001, False, 0), False),
    ]
    for body, ok in cases:
        raw = encode_pose(123, 45, body, ok, "d1", 5_000_000, 1.5, "echo", 130)
        decoded = wire.MocapPose.decode(raw, "arena/d1/mocap")
        qx, qy, qz, qw = body.quat_xyzw
        finite = all(math.isfinite(v) for v in (*body.pos, *body.quat_xyzw))
        p, q = (body.pos, (qw, qx, qy, qz)) if finite else ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        expected = wire.MocapPose(
            t=123,
            fn=45,
            id=3,
            p=p,
            q=q,
            ok=ok,
            name="d1",
            err=math.nan if body.mean_error is None else body.mean_error,
            lat=5_000_000,
            mts=1.5,
            tsrc="echo",
            tp=130,
        )
        assert raw == expected.encode()
        assert decoded.ok is ok and decoded.p == pytest.approx(p)


def test_body_key_names() -> None:
    assert body_key_name("Rigid Body 4", 4) == "Rigid_Body_4"
    assert body_key_name("quad.7-b", 7) == "quad.7-b"
    assert body_key_name("", 12) == "id12"
    assert body_key_name("@bad", 3) == "_bad"
    assert body_key_name("x" * 80, 3) == "x" * 63


@pytest.mark.parametrize(("version", "multicast"), [("3.1", True), ("4.1", False)])
def test_bodies_reach_their_vehicles(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
    version: str,
    multicast: bool,
) -> None:
    cfg = make_config(
        tmp_path,
        router_endpoint,
        mocap=f"publish_unknown = true\nmulticast = {'true' if multicast else 'false'}",
        by_id={"d2": 2},
    )
    bodies = [
        Body(7, "d1", (0.5, 1.1, -0.2), (0.0, 0.6, 0.0, 0.8)),
        Body(2, "whatever", (1.0, 0.9, 0.3)),
        Body(9, "Rigid Body 9", (2.0, 0.5, 0.0)),
    ]
    server = server_for(cfg, version=version, multicast=multicast, bodies=bodies, latency_ns=6_000_000)
    bus = bus_factory()
    sub = bus.subscribe("arena/**", capacity=10_000, ring=False)
    seen: dict[str, Any] = {}
    try:
        service(cfg)
        d1, d2, stranger = keys.mocap("d1"), keys.mocap("d2"), keys.body("Rigid_Body_9")

        def echo_timed() -> bool:
            return any(p.tsrc == "echo" for p in seen.get(d1, [])) and d2 in seen and stranger in seen

        feed(server, sub, seen, echo_timed, "echo-timed poses on every key")
        pose = [p for p in seen[d1] if p.tsrc == "echo"][-1]
        assert isinstance(pose, wire.MocapPose)
        assert (pose.id, pose.name, pose.ok) == (7, "d1", True)
        assert pose.p == pytest.approx((0.5, 1.1, -0.2))
        assert pose.q == pytest.approx((0.8, 0.0, 0.6, 0.0))  # w, x, y, z
        assert pose.lat == pytest.approx(6_000_000, abs=200)
        # Mid-exposure, 6 ms before sending (lat, exact above), mapped onto this clock by the echo exchange:
        # before publication, by about 6 ms on an idle machine; a busy one blurs the echo's round trip.
        assert pose.tp - 50_000_000 < pose.t < pose.tp
        assert pose.mts == pytest.approx(pose.fn / 180.0)
        assert pose.err == pytest.approx(0.0002)
        assert seen[d2][-1].id == 2 and seen[d2][-1].name == "whatever"
        assert seen[stranger][-1].id == 9 and seen[stranger][-1].name == "Rigid Body 9"
        # One frame message carries every claimed body (not the stranger), as their per-vehicle poses say.
        by_fn = {f.fn: f for f in seen[keys.FRAMES]}
        frame = by_fn[pose.fn]
        assert [(b.v, b.id, b.name) for b in frame.b] == [("d1", 7, "d1"), ("d2", 2, "whatever")]
        assert frame.pose(frame.b[0]) == pose

        # d1 loses tracking: published, never silently valid.
        server.bodies[0].tracked = False
        feed(server, sub, seen, lambda: not seen[d1][-1].ok, "an untracked pose")
        assert seen[d1][-1].ok is False and seen[d2][-1].ok is True

        # Garbage on the wire is counted in the service's stats, the stream goes on.
        server.send_raw(b"\x01\x02")
        server.send_raw(b"\x63\x00\x00\x00")
        stats_key = keys.stats("test", "mocap")

        def rejected() -> dict[str, Any]:
            stats = seen.get(stats_key, [])
            return stats[-1].rejected if stats else {}

        feed(server, sub, seen, lambda: {"garbage", "unknown_message"} <= set(rejected()), "rejects in stats")
        counts = seen[stats_key][-1].counts
        assert counts["in"] > 0 and counts["out"] >= 3 and counts["unknown"] > 0
    finally:
        server.close()


def test_a_vehicles_mocap_key_is_published_only_while_someone_reads_it(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
) -> None:
    cfg = make_config(tmp_path, router_endpoint, n_vehicles=1)
    server = server_for(cfg, version="4.0", bodies=[Body(3, "d1", (0.1, 0.2, 0.3))])
    bus = bus_factory()
    sub = bus.subscribe(keys.FRAMES, capacity=10_000, ring=False)
    stats = bus.subscribe(keys.stats("test", "mocap"), capacity=100, ring=False)
    seen: dict[str, Any] = {}
    try:
        service(cfg)
        feed(server, sub, seen, lambda: len(seen.get(keys.FRAMES, [])) >= 10, "frames")

        def unwatched() -> float:
            last = [i.payload for i in stats.channel.drain() if isinstance(i.payload, wire.Stats)]
            return last[-1].counts.get("unwatched", 0) if last else 0

        feed(server, sub, seen, lambda: unwatched() > 0, "d1's poses counted as read by nobody")
        mocap = bus.subscribe(keys.mocap("d1"), capacity=10_000, ring=False)
        feed(server, mocap, seen, lambda: keys.mocap("d1") in seen, "d1's poses once someone reads them")
        assert seen[keys.mocap("d1")][-1].p == pytest.approx((0.1, 0.2, 0.3))
    finally:
        server.close()


def test_bodies_named_in_the_config_wait_for_the_model_definitions(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
) -> None:
    cfg = make_config(tmp_path, router_endpoint, n_vehicles=1)
    server = server_for(cfg, version="4.0", bodies=[Body(3, "d1", (0.1, 0.2, 0.3))])
    real_defs = server.model_defs
    server.model_defs = lambda: ModelDefs()  # type: ignore[method-assign]  # no bodies defined yet
    bus = bus_factory()
    sub = bus.subscribe("arena/**", capacity=10_000, ring=False)
    seen: dict[str, Any] = {}
    try:
        service(cfg)
        stats_key = keys.stats("test", "mocap")
        feed(
            server,
            sub,
            seen,
            lambda: bool(seen.get(stats_key)) and seen[stats_key][-1].counts.get("unknown", 0) > 0,
            "the unnamed body counted",
        )
        assert keys.mocap("d1") not in seen
        server.model_defs = real_defs  # type: ignore[method-assign]
        server.params = 0x02  # Motive: "the models changed"
        feed(server, sub, seen, lambda: keys.mocap("d1") in seen, "d1 once its name is known")
        assert seen[keys.mocap("d1")][-1].name == "d1"
    finally:
        server.close()


def test_the_service_survives_a_bad_interface(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
) -> None:
    cfg = make_config(tmp_path, router_endpoint, n_vehicles=1)
    cfg = cfg.replace(mocap=cfg.mocap.replace(interface="192.0.2.77"))
    bus = bus_factory()
    sub = bus.subscribe(keys.stats("test", "mocap"), capacity=100, ring=False)
    seen: dict[str, Any] = {}
    service(cfg)
    wait_for(
        lambda: latest(sub, seen) and seen[keys.stats("test", "mocap")][-1].rejected.get("setup", 0) >= 1,
        timeout=10,
        what="the setup failure in the stats",
    )


def long_take(tmp_path: Path, laps: int) -> Path:
    """The test take repeated ``laps`` times, frame numbers and times going on (a longer Motive export)."""
    lines = TAKE.read_text().splitlines()
    header, rows = lines[:7], lines[7:]
    out = list(header)
    for lap in range(laps):
        for row in rows:
            cells = row.split(",")
            number = int(cells[0]) + lap * len(rows)
            out.append(",".join([str(number), f"{number / 120:.6f}", *cells[2:]]))
    path = tmp_path / "long_take.csv"
    path.write_text("\n".join(out) + "\n")
    return path


def test_csv_take_replayed_through_the_service(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
) -> None:
    # 10 s of take: the subscriber may join the bus after the replay started, what it gets must be right.
    take = long_take(tmp_path, 50)
    cfg = make_config(tmp_path, router_endpoint, mocap=f'source = "csv"\ncsv_file = "{take.name}"')
    sub = bus_factory().subscribe("arena/*/mocap", capacity=10_000, ring=False)
    seen: dict[str, Any] = {}
    service(cfg)

    def enough() -> bool:
        got = latest(sub, seen)
        return len(got.get(keys.mocap("d1"), [])) >= 60 and any(
            not p.ok for p in got.get(keys.mocap("d2"), [])
        )

    wait_for(enough, timeout=15, what="a second of the take and an untracked d2")
    d1, d2 = seen[keys.mocap("d1")], seen[keys.mocap("d2")]
    for pose in d1:
        k = pose.fn % 24
        assert pose.ok and pose.id == 1 and pose.name == "d1" and pose.tsrc == "arrival"
        assert pose.p == pytest.approx((0.01 * k, 1.0, -0.5), abs=1e-6)
        assert pose.q == pytest.approx((math.cos(0.025 * k), 0.0, math.sin(0.025 * k), 0.0), abs=1e-6)
        assert pose.mts == pytest.approx(pose.fn / 120, abs=1e-6)
    assert all(p.ok is not (10 <= p.fn % 24 <= 12) for p in d2)
    for a, b in itertools.pairwise(d1):
        assert b.fn > a.fn
        assert (b.t - a.t) / 1e9 == pytest.approx((b.fn - a.fn) / 120, abs=2e-6)  # the take's own timing


def test_runs_as_a_process(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], processes: Callable[..., Proc]
) -> None:
    cfg = make_config(tmp_path, router_endpoint, n_vehicles=1, mocap="multicast = false")
    server = server_for(cfg, version="4.1", multicast=False, bodies=[Body(1, "d1", (0.3, 1.0, 0.2))])
    bus = bus_factory()
    sub = bus.subscribe(keys.mocap("d1"), capacity=1000, ring=False)
    seen: dict[str, Any] = {}
    proc = processes("mocap", service_argv("mocap_ingest", cfg.path, host="proc"))
    try:
        try:
            feed(server, sub, seen, lambda: keys.mocap("d1") in seen, "a pose from the service process")
            pose = seen[keys.mocap("d1")][-1]
            assert pose.ok and pose.p == pytest.approx((0.3, 1.0, 0.2))
        finally:
            code = proc.stop(10.0, signal.SIGTERM)
        assert code == 0, proc.tail()
        wait_for(lambda: server.count(MessageId.DISCONNECT) >= 1, what="DISCONNECT when the process stops")
    finally:
        server.close()


# ------------------------------------------------------------------------------------------------------------
# End to end with the Motive emulator (services/sim_mocap.py)
# ------------------------------------------------------------------------------------------------------------

_C45 = math.cos(math.pi / 4)
# True poses (arena NED, FRD): d1 yawed 90° to the east, d2 level facing north.
TRUTH = {"d1": ((1.0, -0.5, -1.2), (_C45, 0.0, 0.0, _C45)), "d2": ((-1.0, 0.5, -0.8), (1.0, 0.0, 0.0, 0.0))}
# The same in Motive's Y-up frame (brief §3 inverted: x = north, y = up, z = east).
MOTIVE = {"d1": ((1.0, 1.2, -0.5), (_C45, 0.0, -_C45, 0.0)), "d2": ((-1.0, 0.8, 0.5), (1.0, 0.0, 0.0, 0.0))}
EMULATOR_LATENCY_NS = 5_380_000  # sim_mocap's camera (4.57 ms) plus software (0.81 ms) latency


@pytest.fixture
def emulator(bus_factory: Callable[[], Bus]) -> Iterator[Callable[..., None]]:
    """Run the Motive emulator in a thread, fed with the true poses of :data:`TRUTH` at 50 Hz."""
    from services import sim_mocap

    stop = threading.Event()
    threads: list[threading.Thread] = []

    def start(cfg: ArenaConfig, **kwargs: Any) -> None:
        bus = bus_factory()

        def feed_truth() -> None:
            while not stop.wait(0.02):
                for vehicle, (p, q) in TRUTH.items():
                    bus.put(
                        keys.truth(vehicle), wire.Pose(t=time.time_ns(), p=p, q=q, ok=True), realtime=True
                    )

        threads.append(threading.Thread(target=feed_truth, daemon=True))
        threads.append(
            threading.Thread(
                target=sim_mocap.main,
                args=(cfg,),
                kwargs={"stop": stop, "host": "test", **kwargs},
                daemon=True,
            )
        )
        for thread in threads:
            thread.start()

    yield start
    stop.set()
    for thread in threads:
        thread.join(timeout=10)
        assert not thread.is_alive(), "the emulator did not stop"


def emulator_config(tmp_path: Path, router: str, version: str, multicast: bool) -> ArenaConfig:
    path = write_config(tmp_path, router, 2, natnet_version=version, noise_m=0.0)
    text = path.read_text().replace("[mocap]\n", f"[mocap]\nmulticast = {str(multicast).lower()}\n", 1)
    path.write_text(text.replace('rigid_body = "d2"', "rigid_body = 2"))  # d2 claimed by id
    return config_mod.load(path)


@pytest.mark.parametrize("multicast", [True, False], ids=["multicast", "unicast"])
@pytest.mark.parametrize("version", ["3.0", "3.1", "4.0", "4.1"])
def test_end_to_end_with_the_motive_emulator(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
    emulator: Callable[..., None],
    version: str,
    multicast: bool,
) -> None:
    cfg = emulator_config(tmp_path, router_endpoint, version, multicast)
    sub = bus_factory().subscribe("arena/*/mocap", capacity=100_000, ring=False)
    seen: dict[str, Any] = {}
    emulator(cfg)
    service(cfg)

    def good(vehicle: str) -> list[wire.MocapPose]:
        return [p for p in seen.get(keys.mocap(vehicle), []) if p.ok and p.tsrc == "echo"]

    def received() -> str:  # what had arrived when the wait gave up
        return ", ".join(
            f"{key}: {len(ps)} ({sum(x.ok for x in ps)} tracked, times {sorted({x.tsrc for x in ps})})"
            for key, ps in sorted(seen.items())
        )

    try:
        wait_for(lambda: latest(sub, seen) and len(good("d1")) >= 10 and len(good("d2")) >= 10, timeout=20)
    except WaitTimeout as exc:
        raise AssertionError(
            f"no 10 echo-timed, tracked poses of d1 and d2; received: {received() or 'none'}"
        ) from exc
    for vehicle, body_id in (("d1", 1), ("d2", 2)):
        poses = good(vehicle)
        pose = poses[-1]
        p, q = MOTIVE[vehicle]
        assert (pose.id, pose.name) == (body_id, vehicle)
        assert pose.p == pytest.approx(p, abs=1e-6)
        assert pose.q == pytest.approx(q, abs=1e-6)
        assert pose.lat == pytest.approx(EMULATOR_LATENCY_NS, abs=200)
        # t is the exposure on our clock: before publication (by the latency and the transport, which a
        # loaded machine stretches: bounded, not timed, here).
        assert all(0 < x.tp - x.t < 1_000_000_000 for x in poses), [x.tp - x.t for x in poses]
        numbers = [x.fn for x in poses]
        assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
    # Before the first true pose the emulator streams the bodies untracked: published with ok=False.
    first = seen[keys.mocap("d1")][0]
    assert first.ok or first.fn < good("d1")[0].fn


def test_probe_against_the_motive_emulator(
    tmp_path: Path, router_endpoint: str, emulator: Callable[..., None]
) -> None:
    cfg = emulator_config(tmp_path, router_endpoint, "4.1", True)
    emulator(cfg)
    args = [sys.executable, "-m", "arena_common.cli", "mocap", "probe", "--server", "127.0.0.1"]
    args += ["--interface", "127.0.0.1", "--command-port", str(cfg.mocap.command_port), "--duration", "1.5"]
    start = time.monotonic()
    result = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stdout + result.stderr
    assert time.monotonic() - start < 15
    out = result.stdout
    assert "NatNet 4.1.0.0" in out and "clock 10,000,000 Hz" in out
    assert f"multicast 239.255.42.99:{cfg.mocap.data_port}" in out
    assert "clock sync: echo" in out
    rows = {
        line.split()[1]: line.split() for line in out.splitlines() if line.strip().startswith(("1 ", "2 "))
    }
    assert set(rows) == {"d1", "d2"}
    for row in rows.values():
        assert float(row[2]) == pytest.approx(180.0, rel=0.1)  # sim.mocap_rate
        assert row[4] == "5.38"  # latency p50, ms


def test_probe_says_when_nothing_answers(tmp_path: Path) -> None:
    port = FakeMotive(answer_connect=False)
    try:
        args = [sys.executable, "-m", "arena_common.cli", "mocap", "probe", "--server", "127.0.0.1"]
        args += ["--command-port", str(port.command_port), "--duration", "0.8"]
        result = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=30)
    finally:
        port.close()
    assert result.returncode == 1
    assert "no answer from 127.0.0.1" in result.stderr and "firewall" in result.stderr


def test_probe_says_when_no_frame_arrives() -> None:
    server = FakeMotive("3.0")
    try:
        args = [sys.executable, "-m", "arena_common.cli", "mocap", "probe", "--server", "127.0.0.1"]
        args += ["--command-port", str(server.command_port), "--duration", "0.8"]
        result = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=30)
    finally:
        server.close()
    assert result.returncode == 1, result.stdout
    assert "Motive 3.1.0.0, NatNet 3.0.0.0" in result.stdout
    assert "no frame arrived" in result.stderr
