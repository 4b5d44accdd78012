"""What keeps the arena safe: setpoint leases and refusals, vision silence, estop, a killed gateway,
a dead router, and gateways that only ever talk to their own vehicle."""

from __future__ import annotations

import math
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import msgpack

from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ZenohSpec
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot, SimClock
from tests.helpers import Proc, free_port, service_argv, wait_for, write_config
from tests.unit.gateway.test_gateway import ARENA_PARAMS, SPEED, MavPeer, Rig, rig_factory  # noqa: F401  (make_rig)


class SetpointStream:
    """A user program streaming one setpoint at 20 Hz until stopped."""

    def __init__(self, bus: Bus, drone: str, stream: str = "test-stream", **fields: object) -> None:
        self.pub = bus.stream_publisher(keys.setpoint(drone), wire.Setpoint)
        self.fields = fields
        self.stream = stream
        self.seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self.seq += 1
            sp = wire.Setpoint(t=wire.now_ns(), src="test", stream=self.stream, seq=self.seq, **self.fields)  # type: ignore[arg-type]
            self.pub.put(sp)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def test_user_setpoints_lease_expiry_lands_and_offboard_never_reengages(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    ap = rig.aps["d1"]
    n, e, _ = ap.true_pose().position
    rig.fly("d1", 0.8)
    user = SetpointStream(rig.bus, "d1", stream="prog-1", p=(n, e, -1.0), yaw=0.0, lease=0.5)
    try:
        wait_for(
            lambda: rig.gateways["d1"].forwarder.held >= 3, 5.0, what="the stream held back until its engage"
        )
        rig.ok("d1", "mode", mode="OFFBOARD", stream="prog-1")  # accepted: the stream is live
        rig.wait_state(
            "d1", lambda s: s.p is not None and abs(s.p[2] + 1.0) < 0.1, 10.0, "offboard climb to 1 m"
        )
        assert ap.mode_name == "OFFBOARD"
        assert rig.state("d1").auth == "stream prog-1 (test)"  # type: ignore[union-attr]
    finally:
        user.stop()  # the user program dies mid-air
    rig.wait_event("d1", lambda e: e.kind == "safety" and "lease expired" in e.text, 3.0, "lease expiry")
    assert not rig.wait_state("d1", lambda s: not s.ofb, 2.0, "stream stopped").ofb
    rig.wait_event(
        "d1", lambda e: e.kind == "failsafe" and "no offboard signal" in e.text, 5.0, "PX4 failsafe"
    )
    rig.wait_state("d1", lambda s: s.mode == "AUTO.LAND", 5.0, "landing by itself")
    # The user program comes back while the vehicle lands: its stream has ended (dropped, counted), a new
    # stream is refused (landing), and offboard stays off.
    late = SetpointStream(rig.bus, "d1", stream="prog-1", p=(n, e, -1.5), lease=0.5)
    late.seq = user.seq
    fresh = SetpointStream(rig.bus, "d1", stream="prog-2", p=(n, e, -1.5), lease=0.5)
    try:
        rig.wait_event("d1", lambda e: e.kind == "authority" and "prog-1 ended" in e.text, 3.0, "dropped")
        rig.wait_event(
            "d1", lambda e: e.kind == "safety" and "landing: take off first" in e.text, 3.0, "refused"
        )
        res = rig.cmd("d1", "mode", mode="OFFBOARD", stream="prog-2")
        assert res.result == "REFUSED" and "landing: take off first" in res.reason
        rig.wait_state("d1", lambda s: s.landed == "on_ground" and not s.armed, 15.0, "landed and disarmed")
        assert not rig.state("d1").ofb  # type: ignore[union-attr]
    finally:
        late.stop()
        fresh.stop()
    assert rig.gateways["d1"].forwarder.dropped >= 1
    # Between the failsafe landing and the disarm, the vehicle never went back to OFFBOARD (after the
    # disarm PX4 reports the user's mode again, harmlessly).
    seq = [e.data.get("mode", e.text) for e in rig.event_list("d1") if e.kind in ("mode", "armed")]
    landing = seq[seq.index("AUTO.LAND") : seq.index("disarmed")]
    assert "OFFBOARD" not in landing, seq
    assert ap.true_pose().position[2] == 0.0


def test_refused_setpoints_never_reach_the_vehicle(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(simulate=False, start=False)
    port = int(rig.cfg.vehicle("d1").mavlink.rsplit(":", 1)[1])
    rig.start_gateway("d1")
    wait_for(lambda: rig.cmd("d1", "ping", timeout=1.0).ok, 10.0, what="gateway answers")
    res = rig.cmd("d1", "land")
    assert res.result == "REFUSED" and "no link to the autopilot (nothing heard yet)" in res.reason
    vehicle = MavPeer(f"udpout:127.0.0.1:{port}", 1, airborne=True)  # records every byte the gateway sends
    try:
        rig.wait_ready("d1")
        wait_for(lambda: rig.gateways["d1"].state.flight_problem() is None, 5.0, what="armed, in the air")
        # Engaged as a mode OFFBOARD command naming it would (the peer answers no command).
        assert rig.gateways["d1"].forwarder.engage("s1", "test") is None
        pub = rig.bus.stream_publisher(keys.setpoint("d1"), wire.Setpoint)
        now = wire.now_ns
        bad = (
            (wire.Setpoint(t=now(), p=(10.0, 0.0, -1.0), stream="s1", seq=1), "north 10.00 m outside"),
            (wire.Setpoint(t=now(), p=(0.0, 0.0, -2.4), stream="s1", seq=2), "down -2.40 m outside"),
            (
                wire.Setpoint(t=now(), v=(3.0, 0.0, 0.0), stream="s1", seq=3),
                "horizontal speed 3.00 m/s above max_speed",
            ),
            (
                wire.Setpoint(t=now(), v=(0.0, 0.0, -1.5), stream="s1", seq=4),
                "vertical speed 1.50 m/s above max_climb",
            ),
            (wire.Setpoint(t=now(), p=(1.0, 0.5, -1.0)), "no stream identity"),
        )
        for sp, reason in bad:
            pub.put(sp)
            rig.wait_event("d1", lambda e, r=reason: e.kind == "safety" and r in e.text, 3.0, reason)  # type: ignore[misc]
        pub.put_raw(msgpack.packb({"t": now(), "p": [math.nan, 0.0, -1.0]}))
        rig.wait_event("d1", lambda e: e.kind == "safety" and "not a finite number" in e.text, 3.0, "NaN")
        time.sleep(0.5)
        assert vehicle.of("SET_POSITION_TARGET_LOCAL_NED") == []
        # A valid one goes out at once, is repeated at 20 Hz for its lease, then never again.
        pub.put(wire.Setpoint(t=now(), p=(1.0, 0.5, -1.0), lease=0.5, stream="s1", seq=5))
        time.sleep(1.2)
        sent = vehicle.of("SET_POSITION_TARGET_LOCAL_NED")
        assert 8 <= len(sent) <= 14, len(sent)
        assert all((m.x, m.y, m.z) == (1.0, 0.5, -1.0) for m in sent)
        assert all(m.target_system == 1 and m.target_component == 1 and m.coordinate_frame == 1 for m in sent)
        assert {m.type_mask for m in sent} == {3576}  # position only: velocity, acceleration, yaw ignored
        span = (sent[-1]._timestamp - sent[0]._timestamp) if len(sent) > 1 else 0.0
        assert 0.35 <= span <= 0.65, span
        rig.wait_event("d1", lambda e: "lease expired" in e.text, 2.0, "lease expiry")
        time.sleep(0.5)
        assert len(vehicle.of("SET_POSITION_TARGET_LOCAL_NED")) == len(sent)
        # The vehicle also never heard anything addressed to another system.
        assert {m.target_system for m in vehicle.of("COMMAND_LONG")} <= {1}
    finally:
        vehicle.close()


def test_vision_stops_gateway_goes_silent_and_vehicle_descends(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    ap = rig.aps["d1"]
    gw = rig.gateways["d1"]
    rig.fly("d1")
    rig.feeding["d1"] = False  # the motion capture stops
    time.sleep(0.2)
    sent, last = gw.vision.sent, ap.last_vision_sample_us
    rig.wait_event(
        "d1", lambda e: e.kind == "failsafe" and "no position estimate" in e.text, 5.0, "position loss"
    )
    assert rig.wait_state("d1", lambda s: "vision_stale" in s.fs, 2.0, "stale flag").vis_age > 0.4  # type: ignore[operator]
    rig.wait_state("d1", lambda s: s.mode == "AUTO.LAND", 3.0, "descend (AUTO.LAND)")
    wait_for(lambda: ap.true_pose().position[2] == 0.0, 10.0, what="touchdown")
    rig.wait_state("d1", lambda s: not s.armed, 10.0, "disarmed")
    # Not one ODOMETRY reached the vehicle after the poses stopped.
    assert gw.vision.sent == sent and ap.last_vision_sample_us == last


def test_estop_lands_and_estop_kill_stops_the_motors(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    ap = rig.aps["d1"]
    estop = rig.bus.command_publisher(keys.ESTOP, wire.Estop)
    rig.fly("d1")
    estop.put(wire.Estop(t=wire.now_ns(), reason="test", src="pytest"))
    rig.wait_event(
        "d1", lambda e: e.kind == "safety" and "estop (test) from pytest: land → ACCEPTED" in e.text
    )
    rig.wait_state("d1", lambda s: s.mode == "AUTO.LAND", 3.0, "landing")
    rig.wait_state("d1", lambda s: s.landed == "on_ground" and not s.armed, 15.0, "landed, disarmed")
    assert ap.sim.body.last_impact_speed < 1.5  # landed, did not fall
    rig.fly("d1")
    estop.put(wire.Estop(t=wire.now_ns(), kill=True, reason="test", src="pytest"))
    rig.wait_event("d1", lambda e: "kill → ACCEPTED" in e.text, 5.0, "kill")
    wait_for(lambda: ap.true_pose().position[2] == 0.0, 5.0, what="fall")
    assert ap.sim.body.last_impact_speed > 2.0  # motors off: it fell
    rig.wait_state("d1", lambda s: not s.armed, 3.0, "disarmed")
    # The kill command does the same on demand (here on the ground).
    rig.ok("d1", "arm")
    rig.ok("d1", "kill")
    rig.wait_state("d1", lambda s: not s.armed, 3.0, "killed")


def test_gateway_killed_mid_air_vehicle_lands_by_itself(
    arena_config: Callable[..., config_mod.ArenaConfig],
    bus_factory: Callable[[], Bus],
    processes: Callable[..., Proc],
) -> None:
    # The rig feeds vision itself: no mocap ingest, so no time reference on the bus to judge clocks by.
    # Real time: at 2x a busy machine's starved vision stream reaches PX4's 1 s no-aid timeout in 0.3 s.
    cfg = arena_config(speed=1.0, extra="[clock]\nrequire = false")
    rig = Rig(cfg, bus_factory(), speed=1.0, params=ARENA_PARAMS)
    proc = processes("gateway", service_argv("mavlink_gateway", cfg.path, "--vehicle", "d1", host=None))
    try:
        ap = rig.aps["d1"]
        rig.wait_ready("d1", 60.0)
        rig.fly("d1")
        rig.ok("d1", "goto", p=[-0.5, 0.5, -1.2], wait=True, timeout=15.0)
        assert ap.mode_name == "OFFBOARD"
        proc.signal(signal.SIGKILL)  # kill -9: no goodbye, no land command
        proc.wait(10.0)
        wait_for(lambda: ap.mode_name == "AUTO.LAND", 5.0, what="a failsafe landing")
        wait_for(lambda: ap.true_pose().position[2] == 0.0, 15.0, what="touchdown")
        wait_for(lambda: not ap.armed, 10.0, what="disarmed")
        assert ap.sim.body.last_impact_speed < 1.5
        texts = " | ".join(t for _, t in ap.statustexts)
        assert "no position estimate" in texts or "no offboard signal" in texts, texts
    finally:
        proc.stop()
        rig.close()


def test_dead_router_does_not_stop_the_vision_stream(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_bus(
        ZenohSpec(mode="router", connect=(), router_listen=(endpoint,)),
        BusOptions(settings={"connect/endpoints": []}),
    )
    bus = open_bus(ZenohSpec(mode="peer", connect=(endpoint,)))
    cfg = config_mod.load(write_config(tmp_path, endpoint, 1, speed=SPEED))
    rig = Rig(cfg, bus, params=ARENA_PARAMS)
    try:
        gw = rig.start_gateway("d1")
        rig.wait_ready("d1")
        rig.wait_state("d1", lambda s: s.vis_fused, 10.0, "fused")
        router.close()  # the router process dies; the feeder and the gateway are peers on this host
        time.sleep(0.5)
        sent, fused_before = gw.vision.sent, rig.aps["d1"].sim.estimator.vision_fusing
        # ~50 Hz, straight peer to peer: 70 more poses in 1.4 s on an idle machine, later on a busy one.
        wait_for(lambda: gw.vision.sent - sent >= 70, 10.0, what="vision flowing without the router")
        assert fused_before and rig.aps["d1"].sim.estimator.vision_fusing
    finally:
        rig.close()
        bus.close()
        router.close()


def test_two_vehicles_each_gateway_talks_only_to_its_own(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(n_vehicles=2)
    ap1, ap2 = rig.aps["d1"], rig.aps["d2"]
    # An intruder claiming d2's system id sends to d1's port.
    port1 = int(rig.cfg.vehicle("d1").mavlink.rsplit(":", 1)[1])
    intruder = SimAutopilot(
        f"udpout:127.0.0.1:{port1}", 2, clock=SimClock(SPEED), position=(2.0, 1.0, 0.0), params=ARENA_PARAMS
    )
    loop = AutopilotLoop([intruder]).start()
    try:
        for name in ("d1", "d2"):
            rig.wait_state(name, lambda s: s.vis_fused and s.setup_ok, 10.0, "ready")
        rig.ok("d1", "arm")
        wait_for(lambda: ap1.armed, 3.0, what="d1 armed")
        rig.wait_state("d1", lambda s: s.armed, 3.0, "armed")
        samples: list[tuple[str, wire.State]] = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            samples += [(n, s) for n in ("d1", "d2") if (s := rig.state(n)) is not None]
            time.sleep(0.02)
        assert [s for n, s in samples if n == "d1" and (s.sysid != 1 or not s.armed)] == []
        assert [s for n, s in samples if n == "d2" and (s.sysid != 2 or s.armed)] == []
        assert not ap2.armed and not intruder.armed
        assert intruder.messages_in == 0 and intruder.last_vision_sample_us == -1
        assert rig.gateways["d1"].link.foreign > 10  # its frames were seen and dropped
        assert ap2.sim.estimator.vision_fusing
        rig.ok("d1", "disarm")
    finally:
        loop.stop()
        intruder.close()


def test_without_a_time_reference_arming_is_refused_naming_the_clock(
    arena_config: Callable[..., config_mod.ArenaConfig],
    bus_factory: Callable[[], Bus],
    processes: Callable[..., Proc],
) -> None:
    cfg = arena_config(speed=SPEED)  # clock.require defaults to true; no mocap ingest answers the time
    assert cfg.clock.require
    rig = Rig(cfg, bus_factory(), params=ARENA_PARAMS)
    proc = processes("gateway", service_argv("mavlink_gateway", cfg.path, "--vehicle", "d1", host=None))
    try:
        rig.wait_ready("d1", 60.0)
        rig.wait_state("d1", lambda s: "clock_unknown" in s.fs, 15.0, "the clock flagged unknown")
        result = rig.cmd("d1", "arm", 5.0)
        assert result.result == "REFUSED" and result.reason.startswith("clock:"), result
        assert not rig.aps["d1"].armed
    finally:
        proc.stop()
        rig.close()


class _Link:
    """Just enough of a MAVLink link for the forwarder: encodes with pymavlink, records what is sent."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import common as mavlink2

        self.mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        self.sent: list[object] = []

    def send(self, msg: object) -> bool:
        self.sent.append(msg)
        return True


def test_an_offboard_block_after_a_hold_is_no_held_back_warning(tmp_path: Path) -> None:
    """Issue 25: a block opened after a Hold streams, then commands OFFBOARD itself 0.3 s later; the
    setpoints of that moment are held back by the latch, which is no reason for a WARNING.  A stream held
    back for longer (no one commands OFFBOARD) still is."""
    import logging

    from arena_common.gateway.events import EventSink
    from arena_common.gateway.setpoints import HELD_BACK_GRACE, SetpointForwarder

    cfg = config_mod.load(write_config(tmp_path, "tcp/127.0.0.1:7447", n_vehicles=1))
    events = EventSink(None, logging.getLogger("test"))
    link = _Link()
    fwd = SetpointForwarder(link, 1, cfg.arena, events)  # type: ignore[arg-type]
    seq = iter(range(1, 10_000))

    def sp() -> wire.Setpoint:
        return wire.Setpoint(t=1, p=(0.0, 0.0, -1.0), yaw=0.0, lease=0.5, stream="s1", seq=next(seq))

    fwd.latch("mode AUTO.LOITER")  # a Hold left offboard
    t = 100.0
    for _ in range(6):  # the block's 0.3 s of stream before its mode command (20 Hz)
        assert fwd.offer(sp(), t) is None
        t += 0.05
    assert fwd.engage("s1", "test", t) is None  # the block's mode OFFBOARD
    fwd.offer(sp(), t)
    assert [e.text for e in events.recent if "held back" in e.text] == []
    assert link.sent  # streaming once released
    # A stream nobody switches to OFFBOARD: warned about after the grace.
    fwd.latch("mode AUTO.LOITER")
    t += 5.0
    for _ in range(int(HELD_BACK_GRACE / 0.05) + 2):
        fwd.offer(sp(), t)
        t += 0.05
    assert [e.sev for e in events.recent if "held back" in e.text] == [4]
