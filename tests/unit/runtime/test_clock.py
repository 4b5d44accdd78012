"""The clock offset to the mocap host: the estimator's bounds, and real exchanges over a real bus."""

from __future__ import annotations

import random
import socket
import time
from collections.abc import Callable

import pytest
from rich.console import Console

from arena_common.bus.session import Bus
from arena_common.cli._flight import clock_table
from arena_common.core import keys, wire
from arena_common.core.config import ClockSpec
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink.link import FrameSplitter, MavlinkLink, mavlink2
from arena_common.runtime.clock import ClockSync, OffsetEstimator, describe_offset
from tests.helpers import free_port, wait_for

MS = 1_000_000


def exchange(theta: int, t1: int, up: int, server: int, down: int) -> tuple[int, int, int, int]:
    """Times of one exchange when the reference clock reads ours + ``theta`` (all ns)."""
    t2 = t1 + up + theta
    t3 = t2 + server
    t4 = t3 - theta + down
    return t1, t2, t3, t4


@pytest.mark.parametrize("theta", [0, 300 * MS, -300 * MS, 2000 * MS, -2000 * MS])
def test_the_true_offset_always_lies_within_the_bound(theta: int) -> None:
    rng = random.Random(theta)
    est = OffsetEstimator(window=16, drift_ppm=0.0)
    t = 1_700_000_000 * 10**9
    for i in range(40):
        # Very asymmetric ways (Wi-Fi): 0.1..20 ms up, 0.1..3 ms down, up to 1 ms in the reference.
        up, down = rng.randint(100_000, 20 * MS), rng.randint(100_000, 3 * MS)
        assert est.add(*exchange(theta, t, up, rng.randint(0, MS), down), mono=float(i)) is None
        e = est.estimate(float(i))
        assert e is not None
        assert abs(e.offset_ns - theta) <= e.unc_ns, (i, e, theta)
        assert e.unc_ns <= (up + down) // 2 + 1  # never worse than the last exchange alone
        t += 10**9
    e = est.estimate(39.0)
    assert e is not None and e.samples == 16 and e.unc_ns < 3 * MS  # the intersection narrows it


def test_symmetric_ways_give_the_offset_exactly() -> None:
    est = OffsetEstimator(drift_ppm=0.0)
    est.add(*exchange(300 * MS, 10**18, 2 * MS, 0, 2 * MS), mono=0.0)
    e = est.estimate(0.0)
    assert e is not None and e.offset_ns == 300 * MS and e.unc_ns == 2 * MS and e.rtt_ns == 4 * MS
    assert e.offset == pytest.approx(0.3) and e.unc == pytest.approx(0.002)


def test_the_bound_widens_with_time_by_the_drift() -> None:
    est = OffsetEstimator(drift_ppm=100.0)
    est.add(*exchange(0, 10**18, MS, 0, MS), mono=10.0)
    fresh, later = est.estimate(10.0), est.estimate(20.0)
    assert fresh is not None and later is not None
    assert later.unc_ns - fresh.unc_ns == 1 * MS  # 100 ppm over 10 s
    assert later.offset_ns == fresh.offset_ns


def test_a_stepped_clock_starts_the_estimate_again() -> None:
    est = OffsetEstimator(drift_ppm=0.0)
    t = 10**18
    for i in range(5):
        est.add(*exchange(0, t + i * 10**9, MS, 0, MS), mono=float(i))
    est.add(*exchange(500 * MS, t + 5 * 10**9, MS, 0, MS), mono=5.0)  # NTP stepped the clock by 0.5 s
    e = est.estimate(5.0)
    assert est.steps == 1 and e is not None and e.samples == 1
    assert abs(e.offset_ns - 500 * MS) <= e.unc_ns


@pytest.mark.parametrize(
    ("times", "reason"),
    [
        ((100, 50, 60, 90), "our clock went back"),
        ((100, 200, 150, 300), "the reference's clock went back"),
        ((100, 200, 500, 150), "longer to answer"),
    ],
)
def test_impossible_exchanges_are_refused_with_the_reason(
    times: tuple[int, int, int, int], reason: str
) -> None:
    est = OffsetEstimator()
    refused = est.add(*times, mono=0.0)
    assert refused is not None and reason in refused
    assert est.rejected == 1 and est.estimate(0.0) is None


def test_describe_offset_says_which_way() -> None:
    assert (
        describe_offset(-0.3, "cc1", "ground")
        == "the clock of cc1 is 0.300 s ahead of the mocap host's (ground)"
    )
    assert "2.000 s behind" in describe_offset(2.0, "cc1", "ground")


def _skewed(seconds: float) -> Callable[[], int]:
    offset = int(seconds * 1e9)
    return lambda: time.time_ns() + offset


def test_offsets_measured_over_the_bus(bus_factory: Callable[[], Bus]) -> None:
    """A reference and two hosts whose clocks are 0.3 s ahead and 2 s behind, on a real router."""
    spec = ClockSpec(period=0.1, max_offset=0.01, max_uncertainty=0.01)
    ref_bus, bus_a, bus_b, watch = bus_factory(), bus_factory(), bus_factory(), bus_factory()
    seen = watch.subscribe(keys.CLOCK_ALL, capacity=256, ring=False)
    ref = ClockSync(ref_bus, "ground", "mocap", spec, reference=True).start()
    ahead = ClockSync(bus_a, "cc1", "gateway.d1", spec, clock_ns=_skewed(0.3)).start()
    behind = ClockSync(bus_b, "cc2", "gateway.d2", spec, clock_ns=_skewed(-2.0)).start()
    try:
        wait_for(lambda: ahead.status().state == "ok" and behind.status().state == "ok", 10.0, what="ok")
        for sync, theta in ((ahead, -0.3), (behind, 2.0)):
            st = sync.status()
            assert st.estimate is not None and st.ref == "ground" and st.problem is None
            assert abs(st.estimate.offset - theta) <= st.estimate.unc + 2e-6  # the clocks are read µs apart
            assert st.estimate.unc < spec.max_uncertainty
            assert st.warning is not None and "chrony" in st.warning
        assert "ahead of the mocap host's (ground)" in str(ahead.status().warning)
        assert "behind the mocap host's (ground)" in str(behind.status().warning)
        assert ref.status().state == "reference" and ref.status().offset_ns == 0 and ref.offset_ns() == 0
        est = ahead.status().estimate
        off = ahead.offset_ns()
        assert est is not None and off is not None and abs(off + 300_000_000) <= est.unc_ns + 2_000

        def published() -> dict[str, wire.ClockOffset]:
            out = {}
            for item in seen.channel.drain():
                if isinstance(item.payload, wire.ClockOffset):
                    out[item.key] = item.payload
            return out

        got: dict[str, wire.ClockOffset] = {}
        # Each host publishes its offset once a period: the one after its status turned ok may still be on
        # its way, so wait for the publications to say what the statuses say (older ones drained on the way).
        key = keys.clock("cc1", "gateway.d1")
        wait_for(
            lambda: got.update(published()) or (len(got) == 3 and got[key].state == "ok"),
            5.0,
            what="three ClockOffset keys, cc1's ok",
        )
        cc1 = got[key]
        assert cc1.state == "ok" and cc1.ref == "ground" and cc1.off is not None and cc1.unc is not None
        assert abs(cc1.off + 0.3) <= cc1.unc + 2e-6 and cc1.n >= 1
        assert got[keys.clock("ground", "mocap")].state == "reference"
    finally:
        for s in (ahead, behind, ref):
            s.close()


def test_without_a_reference_the_offset_is_unknown_and_says_why(bus_factory: Callable[[], Bus]) -> None:
    sync = ClockSync(bus_factory(), "cc1", "gateway.d1", ClockSpec(period=0.1)).start()
    try:
        wait_for(lambda: sync.unanswered >= 2, 5.0, what="two unanswered exchanges")
        st = sync.status()
        assert st.state == "no_reference" and st.offset_ns is None
        assert st.problem is not None and "no mocap time reference answers on arena/sys/time" in st.problem
    finally:
        sync.close()


def test_an_uncertain_offset_is_a_problem_naming_the_clock(bus_factory: Callable[[], Bus]) -> None:
    # No exchange over a real network answers within 1 µs: the bound is always above it.
    spec = ClockSpec(period=0.1, max_uncertainty=1e-6)
    ref = ClockSync(bus_factory(), "ground", "mocap", spec, reference=True).start()
    sync = ClockSync(bus_factory(), "cc1", "gateway.d1", spec, machine="another computer").start()
    try:
        wait_for(lambda: sync.answered >= 2, 5.0, what="two answers")
        st = sync.status()
        assert st.state == "uncertain"
        assert st.problem is not None and "clock: the offset of the clock of cc1" in st.problem
        assert "clock.max_uncertainty" in st.problem
    finally:
        sync.close()
        ref.close()


def test_on_the_mocap_host_itself_the_offset_is_exactly_zero(bus_factory: Callable[[], Bus]) -> None:
    """A service on the reference's own host reads the same wall clock: offset 0 ± 0, however slow the
    exchanges (the uncertainty limit that fails cc1 above does not apply)."""
    spec = ClockSpec(period=0.1, max_uncertainty=1e-6)
    ref = ClockSync(bus_factory(), "ground", "mocap", spec, reference=True).start()
    local = ClockSync(bus_factory(), "ground", "gateway.d1", spec)
    # Nothing known before the first answer names the host (asked before it starts: an answer may come at once).
    assert local.offset_ns() is None
    local.start()
    try:
        wait_for(lambda: local.answered >= 2, 15.0, what="two answers")
        st = local.status()
        assert st.state == "ok" and st.problem is None and st.warning is None and st.ref == "ground"
        assert st.estimate is not None and st.estimate.offset_ns == 0 and st.estimate.unc_ns == 0
        assert local.offset_ns() == 0 and local.same_host
    finally:
        local.close()
        ref.close()


def test_one_computer_is_one_clock_whatever_its_hosts_are_called(bus_factory: Callable[[], Bus]) -> None:
    """Every process of a one-computer arena reads one wall clock, even where the config names the hosts
    apart ("vm", "ground"): offset 0 ± 0 and no problem, however slow the exchanges (the limit of 1 µs
    fails any measured offset); a process whose clock is faked on the same computer is measured."""
    spec = ClockSpec(period=0.1, max_uncertainty=1e-6)
    ref = ClockSync(bus_factory(), "ground", "mocap", spec, reference=True).start()
    here = ClockSync(bus_factory(), "vm", "gateway.d1", spec).start()
    faked = ClockSync(bus_factory(), "vm", "gateway.d2", ClockSpec(period=0.1), clock_ns=_skewed(5.0)).start()
    try:
        wait_for(lambda: here.answered >= 3 and faked.answered >= 3, 5.0, what="three answers each")
        st = here.status()
        assert here.same_host and st.state == "ok" and st.problem is None and st.warning is None
        assert st.estimate is not None and st.estimate.offset_ns == 0 and st.estimate.unc_ns == 0
        assert here.offset_ns() == 0 and here.payload().state == "ok"
        fst = faked.status()
        assert not faked.same_host and fst.estimate is not None
        assert abs(fst.estimate.offset + 5.0) <= fst.estimate.unc + 2e-6
    finally:
        for s in (here, faked, ref):
            s.close()


def test_the_reference_refuses_other_ops(bus_factory: Callable[[], Bus]) -> None:
    ref = ClockSync(bus_factory(), "ground", "mocap", reference=True)
    client = bus_factory()
    result = client.request(keys.TIME, wire.Command(op="ping", timeout=2.0), 2.0)
    assert result.result == "ERROR" and "op 'time' only" in result.reason
    ok = client.request(keys.TIME, wire.Command(op="time", timeout=2.0), 2.0)
    assert ok.ok and ok.value["host"] == "ground" and ok.value["t3"] >= ok.value["t2"]
    ref.close()


def test_vision_times_are_corrected_by_the_offset() -> None:
    """A pose stamped on a mocap clock 2 s ahead: sent (not "from the future"), ODOMETRY on our clock."""
    port = free_port(socket.SOCK_DGRAM)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", port))
    rx.settimeout(2.0)
    link = MavlinkLink(f"udpout:127.0.0.1:{port}", 1)
    link.open()
    theta = 2 * 10**9  # the mocap host's clock minus ours
    known: list[int | None] = [None]
    sender = VisionSender(link, max_pose_age=0.1, offset_ns=lambda: known[0])
    try:
        now = time.time_ns()
        pose = wire.Pose(t=now + theta, p=(1.0, 2.0, -0.5), q=(1.0, 0.0, 0.0, 0.0), ok=True)
        assert sender.offer(pose, now) == "from the future"  # offset unknown: taken as our clock
        known[0] = theta
        assert sender.offer(pose, now) is None
        stale = wire.Pose(t=now + theta - 150 * MS, p=(1.0, 2.0, -0.5), q=(1.0, 0.0, 0.0, 0.0), ok=True)
        assert sender.offer(stale, now) == "stale"  # 150 ms old on the mocap clock
        frames = FrameSplitter(stream=False).feed(rx.recv(4096))
        msg = mavlink2.MAVLink(None).decode(bytearray(frames[0].raw))
        assert msg.get_type() == "ODOMETRY" and msg.time_usec == now // 1000  # our clock, for TIMESYNC
        assert sender.correction() == theta
    finally:
        link.close()
        rx.close()


def test_status_shows_one_row_per_host_with_its_best_estimate() -> None:
    def offset(host: str, service: str, state: str, off: float | None, unc: float | None) -> wire.ClockOffset:
        return wire.ClockOffset(t=1, host=host, service=service, state=state, ref="ground", off=off, unc=unc)

    clocks = {
        "ground/mocap": offset("ground", "mocap", "reference", 0.0, 0.0),
        "cc1/downsampler.d1": offset("cc1", "downsampler.d1", "ok", -0.3004, 0.004),
        "cc1/gateway.d1": offset("cc1", "gateway.d1", "ok", -0.3001, 0.0007),
        "cc2/gateway.d2": offset("cc2", "gateway.d2", "unknown", None, None),
    }
    console = Console(width=160, record=True)
    console.print(clock_table(clocks))
    text = console.export_text()
    rows = [line for line in text.splitlines() if line.startswith(("│ ground", "│ cc1", "│ cc2"))]
    assert len(rows) == 3, text
    cc1 = next(r for r in rows if r.startswith("│ cc1"))
    assert "-300.10" in cc1 and "0.70" in cc1 and "gateway.d1" in cc1 and "chrony!" in cc1
    assert "unknown" in next(r for r in rows if r.startswith("│ cc2"))
    assert "reference" in next(r for r in rows if r.startswith("│ ground"))
