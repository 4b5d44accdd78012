"""The gateway's MAVLink side on real sockets: framing, system-id filtering, vision messages, time sync,
the command protocol with retries, ground-station forwarding, TCP, and link loss with reconnection."""

from __future__ import annotations

import math
import os
import random
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from arena_common.core import wire
from arena_common.gateway.events import EventSink
from arena_common.gateway.gateway import GatewayOptions
from arena_common.gateway.state import VehicleState
from arena_common.gateway.timesync import TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink import px4
from arena_common.mavlink.link import (
    MSG,
    FrameSplitter,
    GcsForwarder,
    MavlinkLink,
    MavlinkLinkError,
    mavlink2,
)
from arena_common.mavlink.protocols import MavCommander
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot
from tests.helpers import free_port, wait_for
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)


def udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


def encoder(sysid: int, compid: int = 1) -> Any:
    return mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def frame(mav: Any, msg: Any) -> bytes:
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


class Pump:
    """Reads a link in a thread and hands decoded messages to handlers by message id."""

    def __init__(self, link: MavlinkLink, handlers: dict[int, Callable[[Any, float], None]]) -> None:
        self.link = link
        self.handlers = handlers
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for f in self.link.read(0.05):
                h = self.handlers.get(f.msgid)
                msg = self.link.decode(f) if h is not None else None
                if h is not None and msg is not None:
                    h(msg, time.monotonic())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


@pytest.fixture
def link_pair() -> Iterator[tuple[MavlinkLink, Any]]:
    """A gateway link listening on UDP and a pymavlink 'vehicle' (system 1) sending to it."""
    port = udp_port()
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1)
    link.open()
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    vehicle.mav.heartbeat_send(2, 12, 1, 0, 3)
    wait_for(lambda: link.read(0.05), 2.0, what="first frame")
    try:
        yield link, vehicle
    finally:
        link.close()
        vehicle.close()


def recv(conn: Any, kind: str, timeout: float = 2.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        select.select([conn.port], [], [], 0.02)
        msg = conn.recv_match(type=kind, blocking=False)
        if msg is not None:
            return msg
    raise AssertionError(f"no {kind} within {timeout} s")


def drain(conn: Any, kind: str | None, wait: float = 0.3) -> list[Any]:
    out = []
    end = time.monotonic() + wait
    while time.monotonic() < end:
        select.select([conn.port], [], [], 0.02)
        while (msg := conn.recv_match(type=kind, blocking=False)) is not None:
            out.append(msg)
    return out


# ------------------------------------------------------------------------------------------ framing
def test_frame_splitter_stream_resyncs_and_checks_crc() -> None:
    v2, v1 = encoder(1), mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    signed = encoder(4)
    signed.signing.secret_key = bytes(range(32))
    signed.signing.sign_outgoing = True
    signed.signing.link_id = 0
    signed.signing.timestamp = 1
    frames = [
        frame(v2, v2.heartbeat_encode(2, 12, 1, 0, 3)),
        frame(v2, v2.odometry_encode(**px4.odometry_args(123, (1, 2, 3), (1, 0, 0, 0)))),
        frame(v2, v2.statustext_encode(6, b"hello")),
        frame(signed, signed.heartbeat_encode(2, 12, 1, 0, 3)),
        bytes(v1.heartbeat_encode(2, 12, 1, 0, 3).pack(v1, force_mavlink1=True)),
    ]
    assert frames[0][0] == 0xFD and frames[4][0] == 0xFE and len(frames[3]) == len(frames[0]) + 13
    corrupt = bytearray(frames[2])
    corrupt[12] ^= 0xFF
    stream = b"\x00garbage\xfd" + frames[0] + frames[1] + bytes(corrupt) + frames[2] + frames[3] + frames[4]
    rng = random.Random(1)
    for _ in range(20):
        splitter = FrameSplitter(stream=True)
        out = []
        i = 0
        while i < len(stream):
            n = rng.randint(1, 40)
            out += splitter.feed(stream[i : i + n])
            i += n
        assert [f.raw for f in out] == [frames[0], frames[1], frames[2], frames[3], frames[4]]
        assert [(f.msgid, f.sysid) for f in out] == [(0, 1), (331, 1), (253, 1), (0, 4), (0, 3)]
        assert splitter.bad_crc >= 1 and splitter.garbage >= 8
    # A datagram is parsed on its own: a truncated tail is dropped, not kept.
    dgram = FrameSplitter(stream=False)
    assert [f.raw for f in dgram.feed(frames[0] + frames[1][:20])] == [frames[0]]
    assert [f.raw for f in dgram.feed(frames[2])] == [frames[2]]


def test_bad_connection_strings_raise_clear_errors() -> None:
    for url in ("", "udpin:127.0.0.1", "udpin:127.0.0.1:notaport", "tcp::5760"):
        with pytest.raises(MavlinkLinkError, match="MAVLink connection"):
            MavlinkLink(url, 1).open()
    with pytest.raises(MavlinkLinkError, match="system id"):
        MavlinkLink("udpin:127.0.0.1:1", 0)
    with pytest.raises(MavlinkLinkError, match="differ"):
        MavlinkLink("udpin:127.0.0.1:1", 7, source_system=7)


def test_udp_link_keeps_only_its_vehicle_and_answers_only_it(link_pair: tuple[MavlinkLink, Any]) -> None:
    link, vehicle = link_pair
    port = int(link.url.rsplit(":", 1)[1])
    intruder = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2, source_component=1)
    try:
        for _ in range(5):
            intruder.mav.heartbeat_send(2, 12, 1, 0, 3)
            vehicle.mav.sys_status_send(0, 0, 0, 0, 12000, 0, 50, 0, 0, 0, 0, 0, 0)
        got: list[Any] = []

        def five() -> bool:
            got.extend(link.read(0.05))
            return len(got) >= 5

        wait_for(five, 2.0, what="vehicle frames")
        assert {f.sysid for f in got} == {1} and link.foreign >= 1
        intruder.mav.heartbeat_send(2, 12, 1, 0, 3)  # the last datagram came from the intruder
        wait_for(lambda: link.read(0.05) == [] and link.foreign >= 5, 2.0, what="intruder frames dropped")
        assert link.send(link.mav.timesync_encode(0, 42))
        assert recv(vehicle, "TIMESYNC").ts1 == 42
        assert drain(intruder, "TIMESYNC") == []
        msg = link.decode(got[0])
        assert msg.get_type() in ("HEARTBEAT", "SYS_STATUS") and msg.get_srcSystem() == 1
    finally:
        intruder.close()


# ------------------------------------------------------------------------------------------- vision
def test_vision_sender_odometry_fields_and_rules(link_pair: tuple[MavlinkLink, Any]) -> None:
    link, vehicle = link_pair
    sender = VisionSender(link, max_pose_age=0.1)
    now = time.time_ns()
    q = (math.cos(0.25), 0.0, 0.0, math.sin(0.25))  # yaw 0.5 rad
    pose = wire.Pose(t=now - 5_000_000, p=(1.0, -0.5, -1.2), q=q, ok=True, v=(0.5, 0.0, 0.0), vok=True)
    assert sender.offer(pose) is None
    odo = recv(vehicle, "ODOMETRY")
    assert odo.time_usec == pose.t // 1000
    assert (odo.frame_id, odo.child_frame_id, odo.estimator_type) == (1, 12, 2)  # LOCAL_NED, BODY_FRD, VISION
    assert (odo.x, odo.y, odo.z) == pytest.approx((1.0, -0.5, -1.2))
    assert odo.q == pytest.approx(list(q), abs=1e-6)
    vb = (odo.vx, odo.vy, odo.vz)  # body-frame velocity: 0.5 m/s north seen from a body yawed 0.5 rad
    assert vb == pytest.approx((0.5 * math.cos(0.5), -0.5 * math.sin(0.5), 0.0), abs=1e-6)
    assert all(math.isnan(c) for c in odo.pose_covariance) and all(
        math.isnan(c) for c in odo.velocity_covariance
    )
    assert odo.reset_counter == 0
    # Never sent: a resend, an older pose, an untracked pose, a stale pose.
    assert sender.offer(pose) == "not newer than the last pose sent"
    assert sender.offer(pose.replace(t=pose.t - 1)) == "not newer than the last pose sent"
    assert sender.offer(pose.replace(t=now, ok=False)) == "not tracked"
    assert sender.offer(pose.replace(t=time.time_ns() - 150_000_000)) == "stale"
    assert drain(vehicle, "ODOMETRY") == []
    # Reset counter: bumped by a new rc, by a jump, by a calibration change.
    t = time.time_ns()
    sender.offer(pose.replace(t=t, rc=1))
    assert recv(vehicle, "ODOMETRY").reset_counter == 1
    sender.offer(pose.replace(t=t + 10_000_000, rc=1, p=(1.01, -0.5, -1.2)))
    assert recv(vehicle, "ODOMETRY").reset_counter == 1
    sender.offer(pose.replace(t=t + 20_000_000, rc=1, p=(2.5, -0.5, -1.2)))  # 1.5 m in 10 ms
    assert recv(vehicle, "ODOMETRY").reset_counter == 2
    sender.bump_reset()
    sender.offer(pose.replace(t=t + 30_000_000, rc=1, p=(2.5, -0.5, -1.2)))
    assert recv(vehicle, "ODOMETRY").reset_counter == 3
    assert sender.sent == 5 and sender.rate(time.monotonic()) == 5.0
    # VISION_POSITION_ESTIMATE when the vehicle is configured for it.
    vpe = VisionSender(link, message="vision_position_estimate")
    vpe.offer(pose.replace(t=time.time_ns()))
    msg = recv(vehicle, "VISION_POSITION_ESTIMATE")
    assert (msg.x, msg.y, msg.z) == pytest.approx((1.0, -0.5, -1.2)) and msg.yaw == pytest.approx(0.5)
    assert math.isnan(msg.covariance[0])


def test_timesync_measures_the_link_then_answers_on_the_autopilots_clock(
    link_pair: tuple[MavlinkLink, Any],
) -> None:
    link, vehicle = link_pair
    clock = [1_000_000_000_000]
    ts = TimeSync(link, clock_ns=lambda: clock[0])
    pump = Pump(link, {MSG["TIMESYNC"]: ts.on_timesync})
    try:
        vehicle.mav.timesync_send(0, 777_000)  # the autopilot asks: not answered yet, but asked back
        request = recv(vehicle, "TIMESYNC")
        assert request.tc1 == 0 and request.ts1 == clock[0]
        wait_for(lambda: ts.unanswered == 1, 2.0, what="the request counted unanswered")
        for k in range(3):  # the vehicle answers with its own clock, 4 ms later on ours
            if k:
                ts.request()
                request = recv(vehicle, "TIMESYNC")
            clock[0] += 4_000_000
            vehicle.mav.timesync_send(5_000_000_000 + k * 104_000_000, request.ts1)
            wait_for(lambda: ts.measured == k + 1, 2.0, what=f"round trip {k} measured")  # noqa: B023
            clock[0] += 100_000_000
        assert ts.rtt_s == pytest.approx(0.004) and ts.locked
        # Its clock runs as ours (104 ms a round trip on both): the offset is its clock minus ours.
        assert ts.autopilot.skew == pytest.approx(0.0, abs=1e-9)
        assert ts.offset_s == pytest.approx((5_000_000_000 - (1_000_000_000_000 + 2_000_000)) * 1e-9)
        vehicle.mav.timesync_send(0, 888_000)  # asked again: answered with its clock, as we know it
        answer = recv(vehicle, "TIMESYNC")
        assert ts.offset_s is not None
        assert answer.ts1 == 888_000 and answer.tc1 == clock[0] + round(ts.offset_s * 1e9)
        vehicle.mav.timesync_send(9, 123)  # an answer to someone else: ignored
        time.sleep(0.2)
        assert ts.rtt_s == pytest.approx(0.004) and ts.answered == 1 and ts.unanswered == 1
    finally:
        pump.close()


# ------------------------------------------------------------------------------------------ commands
def test_command_retries_with_confirmation_in_progress_and_timeout(
    link_pair: tuple[MavlinkLink, Any],
) -> None:
    link, vehicle = link_pair
    commander = MavCommander(link, 1, ack_timeout=0.3, attempts=3)
    pump = Pump(link, {MSG["COMMAND_ACK"]: commander.on_ack})
    results: list[str] = []

    def run(cmd: int) -> threading.Thread:
        t = threading.Thread(target=lambda: results.append(commander.command(cmd, (1.0,))), daemon=True)
        t.start()
        return t

    try:
        # The first attempt is lost; the retry (confirmation 1) is acknowledged.
        t = run(400)
        first = recv(vehicle, "COMMAND_LONG")
        assert (first.target_system, first.target_component, first.command, first.confirmation) == (
            1,
            1,
            400,
            0,
        )
        second = recv(vehicle, "COMMAND_LONG")
        assert second.confirmation == 1
        vehicle.mav.command_ack_send(400, 0, 0, 0, 255, 190)  # to a ground station: not ours
        time.sleep(0.05)
        vehicle.mav.command_ack_send(400, 0, 0, 0, 245, 191)
        t.join(3.0)
        assert results == ["ACCEPTED"]
        # IN_PROGRESS, then the final answer, without resending.
        t = run(246)
        recv(vehicle, "COMMAND_LONG")
        vehicle.mav.command_ack_send(246, px4.MAV_RESULT_IN_PROGRESS, 50, 0, 245, 191)
        time.sleep(0.5)
        vehicle.mav.command_ack_send(246, px4.MAV_RESULT_DENIED, 0, 0, 245, 191)
        t.join(3.0)
        assert results[-1] == "DENIED" and drain(vehicle, "COMMAND_LONG", 0.1) == []
        # Never answered: three attempts (confirmation 0, 1, 2), then TIMEOUT.
        t = run(21)
        sent = drain(vehicle, "COMMAND_LONG", 1.3)
        t.join(3.0)
        assert results[-1] == "TIMEOUT" and [m.confirmation for m in sent] == [0, 1, 2]
    finally:
        pump.close()


# ----------------------------------------------------------------------------------- ground station
@pytest.mark.parametrize("allow_manual", [False, True])
def test_gcs_forwarding_is_raw_and_blocks_manual_control(allow_manual: bool) -> None:
    vport, gport = udp_port(), udp_port()
    link = MavlinkLink(f"udpin:127.0.0.1:{vport}", 1)
    link.open()
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{vport}", source_system=1, source_component=1)
    gcs_conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gport}", source_system=255, source_component=190)
    fwd = GcsForwarder(f"udpout:127.0.0.1:{gport}", link, allow_manual=allow_manual)
    fwd.open()
    stop = threading.Event()

    def vehicle_to_gcs() -> None:
        while not stop.is_set():
            fwd.forward_to_gcs(link.read(0.05))

    def gcs_to_vehicle() -> None:
        while not stop.is_set():
            fwd.pump(0.05)

    threads = [threading.Thread(target=f, daemon=True) for f in (vehicle_to_gcs, gcs_to_vehicle)]
    for t in threads:
        t.start()
    try:
        raw = frame(encoder(1), encoder(1).heartbeat_encode(2, 12, 1, 0, 3))
        vehicle.write(raw)
        hb = recv(gcs_conn, "HEARTBEAT")
        assert hb.get_srcSystem() == 1 and bytes(hb.get_msgbuf()) == raw  # the very bytes
        gcs_conn.mav.param_request_read_send(1, 1, b"MPC_XY_P", -1)
        gcs_conn.mav.manual_control_send(1, 0, 0, 500, 0, 0)
        gcs_conn.mav.rc_channels_override_send(1, 1, *([1500] * 8))
        gcs_conn.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        got = {m.get_type(): m for m in drain(vehicle, None, 0.5)}
        assert got["PARAM_REQUEST_READ"].get_srcSystem() == 255 and got["COMMAND_LONG"].command == 400
        manual = {"MANUAL_CONTROL", "RC_CHANNELS_OVERRIDE"} & set(got)
        if allow_manual:
            assert len(manual) == 2 and fwd.blocked == 0
        else:
            assert manual == set() and fwd.blocked == 2
    finally:
        stop.set()
        for t in threads:
            t.join(2.0)
        fwd.close()
        link.close()
        vehicle.close()
        gcs_conn.close()


def test_gateway_forwards_a_ground_station_to_the_simulated_vehicle(make_rig: Callable[..., Rig]) -> None:
    gport = udp_port()
    gcs_conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gport}", source_system=255, source_component=190)
    try:
        rig = make_rig(vehicle={"gcs": f"udpout:127.0.0.1:{gport}"})
        hb = recv(gcs_conn, "HEARTBEAT", 5.0)
        assert hb.get_srcSystem() == 1 and hb.autopilot == px4.MAV_AUTOPILOT_PX4
        gcs_conn.mav.param_request_read_send(1, 1, b"EKF2_EV_CTRL", -1)
        value = recv(gcs_conn, "PARAM_VALUE", 3.0)
        assert px4.param_float_to_int(value.param_value) == 15
        # The gateway ignored the answer meant for the ground station and kept working.
        assert rig.cmd("d1", "ping").ok
    finally:
        gcs_conn.close()


# ---------------------------------------------------------------------------------- TCP, link loss
def test_tcp_link_to_a_vehicle_listening_on_tcp() -> None:
    port = free_port()
    ap = SimAutopilot(f"tcpin:127.0.0.1:{port}", 1)
    loop = AutopilotLoop([ap]).start()
    link = MavlinkLink(f"tcp:127.0.0.1:{port}", 1)
    try:
        link.open()
        link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))  # a TCP vehicle waits for us to speak first
        got: list[Any] = []

        def heartbeat() -> bool:
            got.extend(link.read(0.05))
            return any(f.msgid == 0 for f in got)

        wait_for(heartbeat, 5.0, what="heartbeat")
        hb = link.decode(next(f for f in got if f.msgid == 0))
        assert hb.autopilot == px4.MAV_AUTOPILOT_PX4
    finally:
        link.close()
        loop.stop()
        ap.close()


def test_link_loss_is_reported_and_the_link_comes_back(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(options=GatewayOptions(link_timeout=1.0))
    rig.wait_state("d1", lambda s: s.setup_ok, 10.0, "checked")
    assert rig.loop is not None
    rig.loop.stop()
    rig.aps["d1"].close()  # the radio goes silent
    rig.wait_event("d1", lambda e: e.kind == "link" and "link lost" in e.text, 5.0, "link lost")
    s = rig.wait_state("d1", lambda s: not s.link, 2.0, "link false")
    assert "link_lost" in s.fs
    res = rig.cmd("d1", "arm")
    assert res.result == "REFUSED" and "no heartbeat" in res.reason
    n_up = len([e for e in rig.event_list("d1") if "link up" in e.text])
    v = rig.cfg.vehicle("d1")
    ap = SimAutopilot(v.sim_mavlink(), v.system_id, clock=rig.clock, name="d1", position=(*v.sim.start, 0.0))
    rig.aps["d1"] = ap
    rig.loop = AutopilotLoop([ap]).start()
    rig.wait_event(
        "d1",
        lambda e: (
            "link up" in e.text and len([x for x in rig.event_list("d1") if "link up" in x.text]) > n_up
        ),
        10.0,
        "link back",
    )
    rig.wait_state("d1", lambda s: s.link and s.hb_age is not None and s.hb_age < 1.5, 5.0, "link true")
    # The new vehicle has PX4's defaults: the re-check on reconnection says so.
    rig.wait_event("d1", lambda e: e.kind == "setup" and "not set" in e.text, 10.0, "re-checked")
    assert rig.wait_state("d1", lambda s: not s.setup_ok, 5.0, "setup not ok").link


def test_event_sink_rate_limits_by_text() -> None:
    published: list[wire.Event] = []
    import logging

    sink = EventSink(published.append, logging.getLogger("test"))
    for _ in range(5):
        sink.emit("safety", "same", 4, every=10.0)
    sink.emit("safety", "other", 4, every=10.0)
    stop = threading.Event()
    t = threading.Thread(target=sink.run, args=(stop,), daemon=True)
    t.start()
    wait_for(lambda: len(published) == 2, 2.0, what="two events")
    stop.set()
    t.join(2.0)
    assert [e.text for e in published] == ["same", "other"]


def test_statustext_chunks_are_joined_as_px4_sends_them() -> None:
    """PX4 v1.16 splits a long text into 50-character STATUSTEXTs with id 0; MAVLink's way is a shared id."""
    import logging

    events = EventSink(None, logging.getLogger("test"))
    state = VehicleState(1, events)
    v2 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)

    def text(t: str, sev: int = 2, chunk_id: int = 0, seq: int = 0) -> Any:
        return v2.statustext_encode(sev, t.encode(), chunk_id, seq)

    long = "Arming denied: Resolve system health failures first\t"
    state.on_statustext(text(long[:50]), 1.0)
    state.on_statustext(text(long[50:]), 1.01)
    state.on_statustext(text("Preflight Fail: horizontal position unstable", 3), 1.02)
    state.on_statustext(text("x" * 50, 4, chunk_id=7, seq=0), 1.03)
    state.on_statustext(text("y" * 10, 4, chunk_id=7, seq=1), 1.04)
    state.on_statustext(text("z" * 50, 5), 1.05)  # its end never comes: flushed after 1 s
    assert [e.text for e in events.recent] == [
        "Arming denied: Resolve system health failures first",
        "Preflight Fail: horizontal position unstable",
        "x" * 50 + "y" * 10,
    ]
    state.supervise(2.5)
    assert events.recent[-1].text == "z" * 50 and events.recent[-1].sev == 5


def test_reboots_are_told_from_the_boot_clock() -> None:
    """A clock back by over a second is a reboot; back at all after a silence too; a few ms of jitter not."""
    import logging

    state = VehicleState(1, EventSink(None, logging.getLogger("test")))
    v2 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)

    def at(boot_ms: int, now: float) -> None:
        state.on_local_position(v2.local_position_ned_encode(boot_ms, 0, 0, 0, 0, 0, 0), now)

    at(5000, 1.0)
    at(4990, 1.01)  # another message type, sampled 10 ms earlier
    assert state.reboots == 0
    at(100, 1.02)  # back 4.9 s: rebooted
    assert state.reboots == 1
    at(600, 1.5)
    at(50, 2.0)  # back only 0.55 s, but after 0.5 s of silence: rebooted again, soon after the last
    assert state.reboots == 2
    at(40, 2.01)
    assert state.reboots == 2
    at(700, 2.02)
    at(30, 2.03)  # back 0.67 s to a clock under a second, read without a gap (a busy host): rebooted
    assert state.reboots == 3
    at(1500, 2.04)
    at(1460, 2.05)  # 40 ms back after the first second: sampling spread, not a reboot
    assert state.reboots == 3
    at(1600, 3.0)  # a second of silence, the clock on: not a reboot
    assert state.reboots == 3
    state.expect_reboot(10.0)  # we asked for one, and it was accepted
    at(1700, 3.01)
    at(1750, 3.6)  # silent, and its new clock already past the old one: the reboot we asked for
    assert state.reboots == 4
    at(2900, 4.5)  # silent again, but no reboot is expected any more
    assert state.reboots == 4
