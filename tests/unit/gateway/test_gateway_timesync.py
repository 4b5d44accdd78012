"""The gateway's TIMESYNC answers as PX4 v1.16 sees them: frames built and read byte by byte on a real UDP
socket, and PX4's own filter (``src/lib/timesync/Timesync.cpp``, as :class:`~arena_common.sim.time.TimesyncFilter`
runs it) on the answers."""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import pytest
from pymavlink.generator.mavcrc import x25crc

from arena_common.gateway.evdelay import WATCH_PERIOD as EV_WATCH_PERIOD
from arena_common.gateway.evdelay import tolerance_ms
from arena_common.gateway.timesync import PX4_CONVERGENCE_WINDOW, TimeSync
from arena_common.mavlink.link import MSG, MavlinkLink
from arena_common.sim.time import TimesyncFilter
from tests.conftest import free_port
from tests.helpers import wait_for
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)
from tests.unit.gateway.test_gateway_link import Pump

TIMESYNC_ID = 111
TIMESYNC_CRC_EXTRA = 34  # the same with or without the v1.16 target fields (extensions do not count)
PX4_SYSID, PX4_COMPID = 1, 1
WALL_OFFSET_NS = 1_795_708_455_000_000_000  # the gateway's clock minus PX4's boot clock, as in the SITL logs


def px4_frame(seq: int, tc1: int, ts1: int, target_system: int = 0, target_component: int = 0) -> bytes:
    """A MAVLink 2 TIMESYNC frame as PX4 v1.16 packs it: tc1, ts1 (int64 ns) and the extension fields
    target_system, target_component, with MAVLink 2's trailing zero bytes dropped."""
    payload = struct.pack("<qqBB", tc1, ts1, target_system, target_component).rstrip(b"\0") or b"\0"
    header = struct.pack("<BBBBBB", len(payload), 0, 0, seq & 0xFF, PX4_SYSID, PX4_COMPID)
    header += TIMESYNC_ID.to_bytes(3, "little")
    crc = x25crc(header + payload)
    crc.accumulate(bytes([TIMESYNC_CRC_EXTRA]))
    return b"\xfd" + header + payload + struct.pack("<H", crc.crc)


def read_timesync(data: bytes) -> tuple[int, int, int, int]:
    """(tc1, ts1, target_system, target_component) of a MAVLink 2 TIMESYNC frame, CRC checked."""
    assert data[0] == 0xFD, data[:1]
    length = data[1]
    assert int.from_bytes(data[7:10], "little") == TIMESYNC_ID
    payload = data[10 : 10 + length]
    crc = x25crc(data[1 : 10 + length])
    crc.accumulate(bytes([TIMESYNC_CRC_EXTRA]))
    assert struct.unpack("<H", data[10 + length : 12 + length])[0] == crc.crc
    tc1, ts1, target_system, target_component = struct.unpack("<qqBB", payload.ljust(18, b"\0"))
    return tc1, ts1, target_system, target_component


@pytest.fixture
def px4_socket() -> Iterator[tuple[MavlinkLink, socket.socket]]:
    """A gateway link (system 1) listening on UDP, and a raw UDP socket playing PX4."""
    port = free_port(socket.SOCK_DGRAM)
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", PX4_SYSID)
    link.open()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(("127.0.0.1", port))
    sock.settimeout(2.0)
    try:
        yield link, sock
    finally:
        link.close()
        sock.close()


def answer_to(
    sock: socket.socket, ts1: int, px4_ns: Callable[[], int] | None = None, wait: float = 2.0
) -> tuple[int, int, int, int] | None:
    """The gateway's TIMESYNC answer echoing ``ts1`` (other frames skipped); the gateway's own requests
    met on the way are answered with ``px4_ns()`` when given, as PX4 answers them.  None when no answer
    came within ``wait`` (then only with a ``px4_ns``: an answer is otherwise always expected)."""
    deadline = time.monotonic() + wait
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            data = sock.recv(512)
        except TimeoutError:
            break
        if int.from_bytes(data[7:10], "little") != TIMESYNC_ID:
            continue
        fields = read_timesync(data)
        if fields[0] == 0 and px4_ns is not None:
            sock.send(px4_frame(0, px4_ns(), fields[1]))
        elif fields[0] != 0 and fields[1] == ts1:
            return fields
    if px4_ns is None:
        raise AssertionError(f"no TIMESYNC answer to ts1={ts1}")
    return None


def ask(sock: socket.socket, seq: int, px4_ns: Callable[[], int]) -> tuple[int, int, int] | None:
    """PX4 asks (ts1 its clock) and plays along until answered: (its time asked, tc1, its time now)."""
    ts1 = px4_ns()
    sock.send(px4_frame(seq, 0, ts1))
    got = answer_to(sock, ts1, px4_ns, wait=0.3)
    return None if got is None else (ts1, got[0], px4_ns())


def test_px4_v116_requests_answered_in_ns_and_echoed_exactly(
    px4_socket: tuple[MavlinkLink, socket.socket],
) -> None:
    """PX4's first requests are not answered (each is asked back); once three round trips were measured,
    every request is answered with PX4's own clock as the gateway knows it, ``ts1`` echoed bit for bit."""
    link, sock = px4_socket
    boot = time.monotonic_ns() - 2_896_000_000

    def px4_ns() -> int:  # PX4's hrt in ns, 2.9 s after its boot
        return time.monotonic_ns() - boot

    ts = TimeSync(link)
    pump = Pump(link, {MSG["TIMESYNC"]: ts.on_timesync})
    try:
        seq, answered = 0, None
        while answered is None:
            assert seq < 10, "never answered"
            answered = ask(sock, seq, px4_ns)
            seq += 1
        assert ts.unanswered == seq - 1 >= 1 and ts.measured >= 3 and ts.locked
        # PX4 asks with tc1 0 and ts1 its boot clock in ns; the target fields (extensions) 0 are dropped
        # from the frame, others travel: both are answered.
        for k, (target_system, target_component) in enumerate(((0, 0), (255, 190))):
            ts1 = px4_ns()
            request = px4_frame(seq + k, 0, ts1, target_system, target_component)
            assert (request[1] < 16) if target_system == 0 else (request[1] == 18)  # payload length
            sock.send(request)
            got = answer_to(sock, ts1, px4_ns)
            assert got is not None
            tc1, echoed, answer_target_system, answer_target_component = got
            # ns of PX4's own clock as we know it (PX4 divides by 1000): known within the round trips it
            # was measured by, a few ms at most on a busy machine.
            assert ts1 - 5_000_000 <= tc1 <= px4_ns() + 5_000_000, (tc1 - ts1, ts.rtt_min_s)
            assert echoed == ts1  # bit for bit: PX4 computes the round trip from it
            assert (answer_target_system, answer_target_component) == (0, 0)  # broadcast: PX4 accepts it
        assert ts.answered == ts.answered_since_reset == 3
        fields = ts.fields()
        assert fields["answered"] == 3 and fields["unanswered"] == seq - 1
        assert fields["autopilot_converged"] is False and abs(fields["skew"]) < 0.05  # telemetry
    finally:
        pump.close()


@dataclass
class SitlClock:
    """PX4 SITL's lockstep clock as measured: it runs at ``rate`` of the wall clock (1–3 % slow, changing
    with the machine's load) and stops now and then (:meth:`pause`); it never catches up."""

    rate: float = 1.0
    start: int = field(default_factory=time.monotonic_ns)
    base: int = 1_000_000_000

    def __call__(self) -> int:
        return self.base + int((time.monotonic_ns() - self.start) * self.rate)

    def set_rate(self, rate: float) -> None:
        self.base, self.start, self.rate = self(), time.monotonic_ns(), rate

    def pause(self, ns: int) -> None:
        self.base -= ns


def fly_px4_filter(
    sock: socket.socket, ts: TimeSync, clock: SitlClock, px4: TimesyncFilter, requests: int, seq: int = 0
) -> int:
    """``requests`` requests of PX4 on ``clock``, answers run through its filter ``px4``; the next seq."""
    for _ in range(requests):
        got = ask(sock, seq, clock)
        seq += 1
        if got is not None:
            px4.update(got[2] // 1000, got[1] // 1000, got[0] // 1000)
    return seq


def test_px4_filter_converges_on_the_answers_and_maps_our_stamps(
    px4_socket: tuple[MavlinkLink, socket.socket],
) -> None:
    """500 round trips over loopback run through PX4's own filter: it converges.  Then SITL's clock
    wanders as measured, in time lapse (slower by 10 %, then by half, stopped for 150 ms): PX4's filter never starts
    over (answered with the host's clock it does: "time jump detected"), and a vision sample stamped by
    the gateway lands on PX4's clock within a few milliseconds."""
    link, sock = px4_socket
    ts = TimeSync(link)
    pump = Pump(link, {MSG["TIMESYNC"]: ts.on_timesync})
    px4, clock = TimesyncFilter(), SitlClock(rate=0.98)  # PX4's own filter, as the simulation runs it
    try:
        seq = 0
        while not px4.converged:
            assert seq < 3 * PX4_CONVERGENCE_WINDOW, px4  # a loaded machine may see a slow round trip
            seq = fly_px4_filter(sock, ts, clock, px4, 1, seq)
            assert ts.autopilot_converged is (ts.accepted_since_reset >= PX4_CONVERGENCE_WINDOW)
        assert px4.sequence == PX4_CONVERGENCE_WINDOW and px4.resets == 0, px4
        # The gateway counts PX4's acceptances by its own round trips, which a busy machine may see slower
        # than PX4 saw its own: it says "converged" within a few more requests (a CI run: not at once).
        more = 0
        while ts.fields()["autopilot_converged"] is not True:
            assert more < 100, (ts.accepted_since_reset, ts.answered_since_reset)
            seq = fly_px4_filter(sock, ts, clock, px4, 1, seq)
            more += 1
        unanswered = ts.unanswered
        # A test's round trips come every few ms, not every 100 ms: the wander is as much larger.
        for wander in (
            lambda: clock.set_rate(0.9),
            lambda: clock.set_rate(0.5),
            lambda: clock.pause(150_000_000),
        ):
            wander()
            seq = fly_px4_filter(sock, ts, clock, px4, 100, seq)
            assert px4.resets == 0 and px4.converged, px4
            assert ts.unanswered == unanswered and ts.locked  # a step of its clock is followed, not relearnt
            # The gateway stamps a vision sample on PX4's clock (µs); PX4 maps it with its ~0 offset.
            wall, px4_now = time.time_ns(), clock() // 1000
            stamp = ts.autopilot_us(wall)
            assert stamp is not None
            assert abs(px4.sync_stamp(stamp, px4_now) - px4_now) < 10_000, (stamp, px4_now, px4)
        assert ts.fields()["steps"] >= 1  # the stop was seen as one
        ts.reset()  # PX4 rebooted: its filter starts over, and so does our estimate
        assert not ts.autopilot_converged and ts.answered_since_reset == 0 and not ts.locked
        assert ts.autopilot_us(time.time_ns()) is None
    finally:
        pump.close()


def our_request(sock: socket.socket) -> int:
    """The ``ts1`` of the gateway's own TIMESYNC request (tc1 0), as PX4 receives it."""
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        data = sock.recv(512)
        if int.from_bytes(data[7:10], "little") == TIMESYNC_ID:
            tc1, ts1, _, _ = read_timesync(data)
            if tc1 == 0:
                return ts1
    raise AssertionError("no TIMESYNC request from the gateway")


def test_a_slow_link_is_measured_and_px4_then_stamps_on_arrival(
    px4_socket: tuple[MavlinkLink, socket.socket],
) -> None:
    """PX4 answers our requests 15–25 ms late (a radio): the round trip and its jitter are measured, PX4's
    own requests over that link cannot converge its filter (it drops round trips of 10 ms or more), and
    the gateway says vision is then stamped on arrival; a fast link again lets the count start."""
    link, sock = px4_socket
    ts = TimeSync(link)
    pump = Pump(link, {MSG["TIMESYNC"]: ts.on_timesync})
    delays = (0.015, 0.025, 0.015, 0.025, 0.020, 0.015)
    try:
        assert ts.stamps == "" and ts.jitter_s is None
        sock.send(px4_frame(0, 0, 1_000_000_000))  # PX4 speaks first: the link learns where it is
        our_request(sock)  # not answered (nothing measured yet) but asked back: that answer is lost
        wait_for(lambda: ts.unanswered == 1, 2.0, what="PX4's request counted unanswered")
        for seq, delay in enumerate(delays):
            ts.request()
            ts1 = our_request(sock)
            time.sleep(delay)  # the link's delay, both ways together
            sock.send(px4_frame(seq, time.monotonic_ns(), ts1))
            wait_for(lambda: ts.measured == seq + 1, 2.0, 0.002, what=f"answer {seq} measured")  # noqa: B023
        assert (
            ts.rtt_s is not None and ts.rtt_s >= 0.015 and ts.rtt_min_s is not None and ts.rtt_min_s >= 0.015
        )
        # Round trips alternating 15 and 25 ms: a jitter of some ms (more on a busy machine, never none).
        assert ts.jitter_s is not None and 0.001 < ts.jitter_s < 0.1, ts.jitter_s
        # PX4's requests: every one answered, none counted as one PX4 could take.
        for seq in range(PX4_CONVERGENCE_WINDOW + 5):
            ts1 = 2_000_000_000 + seq
            sock.send(px4_frame(seq, 0, ts1))
            answer_to(sock, ts1)
        assert ts.answered_since_reset == PX4_CONVERGENCE_WINDOW + 5 and ts.accepted_since_reset == 0
        assert not ts.autopilot_converged and ts.stamps == "arrival"
        assert ts.fields()["jitter"] == ts.jitter_s and ts.fields()["autopilot_converged"] is False
    finally:
        pump.close()


def test_over_a_slow_link_setup_sets_ekf2_ev_delay_from_the_measured_delay_and_drift_is_told(
    make_rig: Callable[..., Rig],
) -> None:
    """A simulated vehicle behind a radio of 30 ± 5 ms each way (the relay of ``sim.link_delay_ms``): the
    gateway measures the round trip, finds PX4 cannot take its clock (stamps on arrival), and the check
    then wants EKF2_EV_DELAY at the link's delay (advice: a reason to fly worse, never to refuse arming);
    setup writes it and says why.  When the link gets fast again, the gateway warns, once, that the
    parameter no longer fits."""
    rig = make_rig(link_delay_ms=(30.0, 5.0))
    gw, ap = rig.gateways["d1"], rig.aps["d1"]
    wait_for(lambda: gw.timesync.px4_can_converge is False, 30.0, what="the slow link judged")
    s = rig.wait_state("d1", lambda s: s.rtt is not None and s.stamps == "arrival")
    assert s.rtt is not None and s.rtt >= 0.050, s.rtt  # 2 × (30 - 5) ms at least
    check = rig.cmd("d1", "check")
    row = check.value["params"]["EKF2_EV_DELAY"]
    assert check.result == "FAILED" and row["have"] == 0.0 and not row["ok"]
    assert 25.0 <= row["want"] <= 60.0, row  # half a round trip of 50–70 ms, plus a pose's few ms
    assert "stamps vision on arrival" in check.reason and "EKF2_EV_DELAY" in check.reason
    assert check.value["advice"] == ["EKF2_EV_DELAY"] and check.value["ok"]  # told, but arming is not refused
    setup = rig.ok("d1", "setup", timeout=20.0)
    assert "EKF2_EV_DELAY" in setup.reason and "round trip" in setup.reason, setup.reason
    written = float(ap.param("EKF2_EV_DELAY"))
    assert 25.0 <= written <= 60.0 and abs(written - row["want"]) <= tolerance_ms(row["want"])
    # The radio is replaced by a cable: the delay the link needs is 0 again, the gateway says so once.
    assert ap.relay is not None
    ap.relay.delay_s, ap.relay.jitter_s = 0.0, 0.0
    drift = rig.wait_event("d1", lambda e: "the link's delay drifted" in e.text, 40.0, "the drift told")
    assert f"EKF2_EV_DELAY is {written:g} ms, this link needs 0 ms" in drift.text, drift.text
    assert (
        "arena px4 setup d1" in drift.text and drift.sev == 4 and drift.data == {"have": written, "want": 0.0}
    )
    time.sleep(EV_WATCH_PERIOD + 1.0)  # the seconds after: told once, not again
    assert len([e for e in rig.event_list("d1") if "the link's delay drifted" in e.text]) == 1
