"""The mocap ingest service: rigid bodies from a NatNet server (or a CSV take) to ``arena/<drone>/mocap``.

The server is the test's own :class:`~tests.test_natnet_client.FakeMotive` on loopback (multicast and
unicast); the service runs in a thread with a stop event, and once as a real process.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common import config as config_mod
from arena_common import keys, wire
from arena_common.bus import Bus, Subscription
from arena_common.config import ArenaConfig
from arena_common.natnet import MessageId, ModelDefs, RigidBody
from services import mocap_ingest
from services.mocap_ingest import body_key_name, encode_pose
from tests.conftest import REPO, wait_for, write_config
from tests.test_natnet_client import Body, FakeMotive

TAKE = Path(__file__).parent / "data" / "motive_take.csv"


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
    while (item := sub.get(0.01)) is not None:
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
        assert pose.tp - 50_000_000 < pose.t < pose.tp - 5_000_000  # mid-exposure, 6 ms before sending
        assert pose.mts == pytest.approx(pose.fn / 180.0)
        assert pose.err == pytest.approx(0.0002)
        assert seen[d2][-1].id == 2 and seen[d2][-1].name == "whatever"
        assert seen[stranger][-1].id == 9 and seen[stranger][-1].name == "Rigid Body 9"

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
    cfg = cfg.replace(mocap=dataclasses.replace(cfg.mocap, interface="192.0.2.77"))
    bus = bus_factory()
    sub = bus.subscribe(keys.stats("test", "mocap"), capacity=100, ring=False)
    seen: dict[str, Any] = {}
    service(cfg)
    wait_for(
        lambda: latest(sub, seen) and seen[keys.stats("test", "mocap")][-1].rejected.get("setup", 0) >= 1,
        timeout=10,
        what="the setup failure in the stats",
    )


def test_csv_take_replayed_through_the_service(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    service: Callable[..., threading.Event],
) -> None:
    cfg = make_config(tmp_path, router_endpoint, mocap=f'source = "csv"\ncsv_file = "{TAKE}"')
    bus = bus_factory()
    sub = bus.subscribe("arena/*/mocap", capacity=10_000, ring=False)
    seen: dict[str, Any] = {}
    time.sleep(0.3)  # let the subscriber's declaration reach the router before the take starts
    service(cfg)
    wait_for(
        lambda: len(latest(sub, seen).get(keys.mocap("d1"), [])) >= 24, timeout=10, what="the whole take"
    )
    d1, d2 = seen[keys.mocap("d1")], seen[keys.mocap("d2")]
    assert [p.fn for p in d1] == list(range(24))
    assert d1[3].p == pytest.approx((0.03, 1.0, -0.5))
    assert d1[3].q == pytest.approx((math.cos(0.075), 0.0, math.sin(0.075), 0.0), abs=1e-6)
    assert [p.fn for p in d2 if not p.ok] == [10, 11, 12]
    span = (d1[-1].t - d1[0].t) / 1e9
    assert span == pytest.approx(23 / 120, abs=0.002)  # the take's own timing
    assert all(p.tsrc == "arrival" for p in d1)


def test_runs_as_a_process(tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]) -> None:
    cfg = make_config(tmp_path, router_endpoint, n_vehicles=1, mocap="multicast = false")
    server = server_for(cfg, version="4.1", multicast=False, bodies=[Body(1, "d1", (0.3, 1.0, 0.2))])
    bus = bus_factory()
    sub = bus.subscribe(keys.mocap("d1"), capacity=1000, ring=False)
    seen: dict[str, Any] = {}
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.mocap_ingest", "--config", cfg.path, "--host", "proc"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        try:
            feed(server, sub, seen, lambda: keys.mocap("d1") in seen, "a pose from the service process")
            pose = seen[keys.mocap("d1")][-1]
            assert pose.ok and pose.p == pytest.approx((0.3, 1.0, 0.2))
        finally:
            proc.terminate()
            try:
                _, err = proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
        assert proc.returncode == 0, err.decode()[-2000:]
        wait_for(lambda: server.count(MessageId.DISCONNECT) >= 1, what="DISCONNECT when the process stops")
    finally:
        server.close()
