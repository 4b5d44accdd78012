"""Several vehicles' gateways in one process (:mod:`arena_common.gateway.host`), their vision one message
per mocap frame, against simulated autopilots over real UDP: every vehicle fuses, and one vehicle's fault
(its sender failing, a frame that is no VisionFrame) stays that vehicle's or is counted by every one."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from arena_common.core import keys, wire
from arena_common.gateway.gateway import Gateway
from arena_common.gateway.host import GatewayHost
from arena_common.gateway.options import GatewayOptions
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


def _start(
    rig: Rig, options: GatewayOptions | None = None
) -> tuple[GatewayHost, threading.Event, threading.Thread]:
    for name in rig.feeding:
        rig.feeding[name] = False  # only the frames feed the gateways
    stop = threading.Event()
    host = GatewayHost(rig.cfg, NAMES, stop, options=options).__enter__()
    thread = threading.Thread(target=host.run, daemon=True)
    thread.start()
    for name in NAMES:
        rig.wait_ready(name)
    return host, stop, thread


@contextmanager
def _serving(
    rig: Rig, options: GatewayOptions | None = None, extra: tuple[str, ...] = ()
) -> Iterator[GatewayHost]:
    """The host serving :data:`NAMES`, fed one VisionFrame per 50 Hz frame, every vehicle fused; stopped
    and closed after, its threads gone."""
    host, stop, thread = _start(rig, options)
    feeder = FrameFeeder(rig, extra)
    try:
        for name in NAMES:
            _fused(rig, name)
        assert host.dispatch is not None
        yield host
    finally:
        feeder.close()
        stop.set()
        thread.join(10.0)
        host.__exit__(None, None, None)
    assert not thread.is_alive()


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
    with _serving(rig, extra=("d9",)) as host:  # d9: a vehicle served elsewhere
        assert host.dispatch is not None and set(host.gateways) == set(NAMES)
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


def test_a_sample_on_the_frames_key_that_is_no_vision_frame_is_every_vehicles_counted_reject(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(n_vehicles=3, start=False, extra=DECIMATING)
    with _serving(rig) as host:
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


def _answers(rig: Rig, name: str) -> int:
    """How many queryables answer a ping on ``name``'s command key (one gateway: exactly one)."""
    command = wire.Command(op="ping", args={}, src="test", timeout=2.0)
    replies = rig.bus.session.get(keys.cmd(name), payload=command.encode(), timeout=2.0)
    return sum(1 for r in replies if r.ok is not None)


def test_a_vehicle_whose_gateway_fails_restarts_alone_while_the_others_keep_every_frame(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(n_vehicles=3, start=False, extra=DECIMATING)
    with _serving(rig) as host:
        assert host.dispatch is not None
        first, others = host.gateways["d2"], {n: host.gateways[n] for n in ("d1", "d3")}
        sent = {n: gw.vision.sent for n, gw in others.items()}
        frames = host.dispatch.frames

        def broken(now: float) -> None:
            raise RuntimeError("d2's supervisor broke")

        first.linkwatch.supervise = broken  # type: ignore[method-assign]
        hosted = host.hosted["d2"]
        wait_for(
            lambda: hosted.restarts == 1 and host.gateways.get("d2") is not None, 15.0, what="d2 restarted"
        )
        second = host.gateways["d2"]
        assert second is not first and first._stop.is_set()
        rig.wait_ready("d2")
        _fused(rig, "d2")
        time.sleep(1.0)  # the seconds after: d2 stays up, nothing restarts again
        assert hosted.restarts == 1 and host.gateways["d2"] is second
        stats = hosted.svc.stats
        assert stats.rejected.get("supervisor: error") == 1, stats.rejected
        assert stats.counts.get("restarts") == 1, stats.counts
        # d2's poses while it was down were counted, not lost silently
        assert host.dispatch.missed.get("d2", 0) >= 1
        assert stats.rejected.get("vision: gateway restarting") == host.dispatch.missed["d2"]
        # the failed gateway's endpoints are gone: one queryable answers d2's commands
        assert _answers(rig, "d2") == 1
        for name, gw in others.items():
            assert host.gateways[name] is gw  # d1 and d3 were never touched
            assert gw.vision.sent - sent[name] >= host.dispatch.frames - frames - 1  # and had every frame
            _fused(rig, name, 2.0)
        assert host.hosted["d1"].restarts == host.hosted["d3"].restarts == 0


# A flood on one UDP port, from a process of its own: HEARTBEATs of another system, FLOOD_RATE a second
# (twenty times the link's budget; paced, so that the flood does not take a core from the tests beside it).
FLOODER = """
import socket, sys, time
from pymavlink.dialects.v20 import common
mav = common.MAVLink(None, srcSystem=99, srcComponent=1)
frame = mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav)
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
target, rate, seconds = (sys.argv[1], int(sys.argv[2])), float(sys.argv[3]), float(sys.argv[4])
start, sent = time.monotonic(), 0
while (now := time.monotonic()) < start + seconds:
    if sent > (now - start) * rate:
        time.sleep(0.001)
        continue
    for _ in range(100):
        sock.sendto(frame, target)
    sent += 100
print(sent)
"""
FLOOD_S, FLOOD_RATE = 2.0, 100_000
#: The flooded link's reader may take at most this share of the flood's duration in CPU. With the budget
#: (5000 datagrams/s) it reads 5,000-10,000 a second; without (link_budget = 0) it reads all, ≈ 3.5 µs of
#: CPU a datagram (1.46 s of 3 s for a flood as fast as Python sends).
READER_CPU_SHARE = 0.2


def _thread_cpu_s(name: str) -> float:
    """CPU seconds (user + system) of this process's thread called ``name``."""
    thread = next(t for t in threading.enumerate() if t.name == name)
    with open(f"/proc/self/task/{thread.native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_a_flood_on_one_vehicles_link_costs_its_reader_its_budget_and_the_others_nothing(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(n_vehicles=3, start=False, extra=DECIMATING)
    with _serving(rig) as host:
        assert host.dispatch is not None
        d2: Gateway = host.gateways["d2"]
        url = rig.cfg.vehicle("d2").mavlink
        assert url.startswith("udpin:"), url
        ip, port = url.split(":")[1:3]
        seen_before = d2.link.datagrams_in + d2.link.kernel_drops()
        sent = {n: host.gateways[n].vision.sent for n in ("d1", "d3")}
        frames = host.dispatch.frames
        cpu = _thread_cpu_s("gw-d2-mavlink")
        flood = subprocess.run(
            [sys.executable, "-c", FLOODER, ip, port, str(FLOOD_RATE), str(FLOOD_S)],
            capture_output=True,
            text=True,
            check=True,
        )
        flooded, reader_cpu = int(flood.stdout), _thread_cpu_s("gw-d2-mavlink") - cpu
        time.sleep(0.5)  # what waited in the socket is read or dropped by now
        # every flooded datagram was read (within the budget, or past it: dropped unparsed) or dropped by
        # the system, and counted so
        assert d2.link.datagrams_in + d2.link.kernel_drops() - seen_before >= flooded
        assert d2.link.over_budget + d2.link.kernel_drops() > 0
        assert reader_cpu <= READER_CPU_SHARE * FLOOD_S, (reader_cpu, flooded, d2.link.over_budget)
        wait_for(
            lambda: (
                d2.stats.rejected.get("mavlink: over budget", 0) == d2.link.over_budget
                and d2.stats.rejected.get("mavlink: dropped by the system", 0) == d2.link.kernel_drops()
            ),
            5.0,
            what="d2's flood counted in its stats",
        )
        rig.wait_event("d2", lambda e: "flooded" in e.text, 5.0)
        for name in ("d1", "d3"):  # the others had every frame, and fuse
            gw = host.gateways[name]
            assert gw.vision.sent - sent[name] >= host.dispatch.frames - frames - 1
            assert not gw.stats.rejected.get("mavlink: over budget")
            _fused(rig, name, 2.0)
