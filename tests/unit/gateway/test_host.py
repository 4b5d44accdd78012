"""Several vehicles' gateways in one process (:mod:`arena_common.gateway.host`), their vision one message
per mocap frame, against simulated autopilots over real UDP: every vehicle fuses, and one vehicle's fault
(its sender failing, a frame that is no VisionFrame) stays that vehicle's or is counted by every one."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from arena_common.core import keys, wire
from arena_common.gateway.host import GatewayHost
from tests.helpers import wait_for
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the fixture)

NAMES = ("d1", "d2", "d3")
DECIMATING = '[pipeline]\ndecimate = "transform"'


class FrameFeeder:
    """Publishes every simulated vehicle's true pose as one VisionFrame on ``arena/sys/vision`` at 50 Hz,
    as the decimating transform does (the Rig's own per-vehicle feed is stopped: nothing else feeds)."""

    def __init__(self, rig: Rig, extra: tuple[str, ...] = ()) -> None:
        self.rig, self.extra = rig, extra
        self.pub = rig.bus.stream_publisher(keys.VISIONS, wire.VisionFrame)
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            bodies = []
            for name in (*self.rig.aps, *self.extra):
                tp = self.rig.aps[name if name in self.rig.aps else "d1"].true_pose()
                pose = wire.Pose(time.time_ns(), tp.position, tp.q, True, v=tp.velocity, w=tp.rates, vok=True)
                bodies.append(wire.VisionBody.of(name, pose))
            self.frames += 1
            self.pub.put(wire.VisionFrame(self.frames, tuple(bodies), time.time_ns()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def _start(rig: Rig) -> tuple[GatewayHost, threading.Event, threading.Thread]:
    for name in rig.feeding:
        rig.feeding[name] = False  # only the frames feed the gateways
    stop = threading.Event()
    host = GatewayHost(rig.cfg, NAMES, stop).__enter__()
    thread = threading.Thread(target=host.run, daemon=True)
    thread.start()
    for name in NAMES:
        rig.wait_ready(name)
    return host, stop, thread


def _fused(rig: Rig, name: str, timeout: float = 15.0) -> wire.State:
    return rig.wait_state(
        name,
        lambda s: s.vis_fused and s.vis_age is not None and s.vis_age < 0.1 and s.vis_rate >= 30.0,
        timeout,
        "vision fused at 30 Hz or more",
    )


def test_one_process_serves_three_vehicles_from_one_frame_each_and_isolates_a_failing_sender(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(n_vehicles=3, start=False, extra=DECIMATING)
    host, stop, thread = _start(rig)
    feeder = FrameFeeder(rig, extra=("d9",))  # d9: a vehicle served elsewhere
    try:
        assert host.dispatch is not None and set(host.gateways) == set(NAMES)
        for name in NAMES:
            _fused(rig, name)
        assert host.dispatch.others > 0  # d9's bodies skipped, counted
        assert not any(gw.own_vision for gw in host.gateways.values())

        # d2's sender fails on every pose: d2's counted failure; d1 and d3 go on fusing, every frame.
        d2 = host.gateways["d2"]
        healthy = d2.vision.offer

        def boom(pose: wire.Pose, now_ns: int | None = None) -> str | None:
            raise RuntimeError("d2's sender broke")

        d2.vision.offer = boom  # type: ignore[method-assign]
        wait_for(lambda: d2.stats.rejected.get("vision: error", 0) >= 50, 10.0, what="d2's failures counted")
        sent = {n: host.gateways[n].vision.sent for n in NAMES}
        frames = host.dispatch.frames
        time.sleep(1.0)
        for name in ("d1", "d3"):
            _fused(rig, name, 2.0)
            # every frame that arrived went out to d1 and d3 (bounded below: a busy machine delays frames)
            assert host.gateways[name].vision.sent - sent[name] >= host.dispatch.frames - frames - 1
        assert d2.vision.sent == sent["d2"]  # nothing of d2's went out while its sender was broken
        rig.wait_state("d2", lambda s: s.vis_age is None or s.vis_age > 0.3, 5.0, "d2's vision stopped")
        d2.vision.offer = healthy  # type: ignore[method-assign]
        _fused(rig, "d2")
    finally:
        feeder.close()
        stop.set()
        thread.join(10.0)
        host.__exit__(None, None, None)
    assert not thread.is_alive()


def test_a_sample_on_the_frames_key_that_is_no_vision_frame_is_every_vehicles_counted_reject(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(n_vehicles=3, start=False, extra=DECIMATING)
    host, stop, thread = _start(rig)
    feeder = FrameFeeder(rig)
    try:
        for name in NAMES:
            _fused(rig, name)
        wrong: Any = rig.bus.stream_publisher(keys.VISIONS, wire.Pose)
        rejects = {name: host.gateways[name].stats.rejected for name in NAMES}

        def counted() -> bool:
            wrong.put(wire.Pose(time.time_ns(), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), True))
            return sum(n for r, n in rejects["d1"].items() if r != "vision: error") >= 5

        wait_for(counted, 10.0, 0.05, "wrong samples on arena/sys/vision counted")
        wrong.close()
        time.sleep(0.3)
        # the same samples reached the one dispatch: each vehicle counted each of them
        got = {name: dict(r) for name, r in rejects.items()}
        assert got["d1"] == got["d2"] == got["d3"], got
        assert set(got["d1"]) <= {"vision: undecodable", "vision: not a VisionFrame"}, got
        for name in NAMES:
            _fused(rig, name, 2.0)  # the frames around them still reach every vehicle
    finally:
        feeder.close()
        stop.set()
        thread.join(10.0)
        host.__exit__(None, None, None)
