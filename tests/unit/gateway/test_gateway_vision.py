"""A refusal to arm for stale vision names why it went stale: no pose arrived (ever, or for how long), or
poses arrived and were refused — how many, for what, by how much.

The rig of ``test_gateway`` (a simulated vehicle over UDP on 127.0.0.1, the gateway in a thread, a private
router); here its vision feeder stops and the test publishes each pose itself, one at a time, waiting for the
gateway to have counted it: the counts in the refusal are then exact, whatever the machine's load.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable

from arena_common.core import keys, wire
from arena_common.gateway.gateway import Gateway
from tests.helpers import wait_for
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (make_rig)

LATE_NS = 300_000_000  # 300 ms: three times the age a pose may have (max_pose_age 0.1 s)


def refusal(rig: Rig) -> str:
    res = rig.cmd("d1", "arm")
    assert res.result == "REFUSED", res
    return res.reason


def stop_feeding(rig: Rig) -> Gateway:
    """Stop the rig's vision feeder; return once its last pose is long gone (nothing of it in flight):
    0.5 s after the feeder put it, and 0.5 s after the gateway last saw a pose."""
    gw = rig.gateways["d1"]
    rig.stop_feed("d1")
    stopped = time.monotonic()
    wait_for(
        lambda: min(time.monotonic() - gw.vision.last_arrival_mono, time.monotonic() - stopped) > 0.5,
        10.0,
        0.02,
        "the feed silent",
    )
    return gw


def test_before_any_pose_it_says_none_arrived(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(start=False)
    rig.feeding["d1"] = False
    rig.start_gateway("d1")
    rig.wait_ready("d1")
    reason = refusal(rig)
    assert reason.startswith(
        "no vision pose sent to the autopilot yet: no pose has arrived on arena/d1/vision ("
    ), reason
    assert "the body not tracked" in reason and "arena top" in reason, reason


def test_when_the_poses_stop_it_says_for_how_long(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.wait_state("d1", lambda s: s.vis_fused, 10.0, "vision fused")
    stop_feeding(rig)
    reason = refusal(rig)
    m = re.match(r"vision stale: last pose sent ([\d.]+) s ago: (.*)", reason)
    assert m, reason
    silent = re.search(r"no pose has arrived on arena/d1/vision for ([\d.]+) s \(the mocap stopped", m[2])
    assert silent, reason
    assert float(silent[1]) >= 0.5 and float(m[1]) >= float(silent[1]), reason
    # An event said it once, as the vision went stale, with what became of the poses.
    said = [e.text for e in rig.event_list("d1") if e.text.startswith("vision stale: ")]
    assert len(said) == 1, [e.text for e in rig.event_list("d1")]
    gone = re.match(r"vision stale: no pose has arrived on arena/d1/vision for ([\d.]+) s", said[0])
    assert gone and float(gone[1]) >= 0.4, said  # px4.EV_TIMEOUT_S
    rig.feeding["d1"] = True
    rig.wait_event("d1", lambda e: e.text == "vision reaching the autopilot again", 10.0, "vision again")


def test_poses_refused_are_counted_by_reason_with_their_figures(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.wait_state("d1", lambda s: s.vis_fused, 10.0, "vision fused")
    gw = stop_feeding(rig)
    pub = rig.bus.stream_publisher(keys.vision("d1"), wire.Pose)

    def deliver(offset_ns: int, ok: bool = True) -> None:
        arrived = gw.vision.arrived
        pub.put(wire.Pose(t=time.time_ns() + offset_ns, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=ok))
        wait_for(lambda: gw.vision.arrived > arrived, 10.0, 0.005, "the pose counted by the gateway")

    for _ in range(5):
        deliver(-LATE_NS)  # measured 300 ms ago: too old
    for _ in range(3):
        deliver(0, ok=False)  # Motive lost the body
    for _ in range(2):
        deliver(LATE_NS)  # stamped 300 ms ahead: the clocks disagree
    reason = refusal(rig)
    assert reason.startswith("vision stale: last pose sent "), reason
    said = reason.split(": ", 1)[1]
    assert "10 poses arrived since, none sent: 5 too old (" in said, reason
    late = re.search(
        r"5 too old \((\d+)(?:–(\d+))? ms after their measurement, more than the 100 ms allowed", said
    )
    assert late, reason
    assert LATE_NS * 1e-6 <= int(late[1]) <= int(late[2] or late[1]), reason
    ahead = re.search(r"2 stamped up to (\d+) ms ahead of this host's clock \(the clocks disagree\)", said)
    assert ahead and int(ahead[1]) <= LATE_NS * 1e-6, reason  # measured after it was stamped: less ahead
    # By count, the most first.
    assert said.index("5 too old") < said.index("3 not tracked") < said.index("2 stamped up to"), reason
    # A fresh pose is sent: the count starts again, and arming is the autopilot's to decide.
    rig.feeding["d1"] = True
    rig.wait_state("d1", lambda s: s.vis_age is not None and s.vis_age < 0.1, 10.0, "vision fresh")
    assert gw.vision.problem(time.monotonic(), 1.0) is None


def test_a_stale_refusal_names_where_the_poses_ran_late(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.wait_state("d1", lambda s: s.vis_fused, 10.0, "vision fused")
    gw = stop_feeding(rig)
    pub = rig.bus.stream_publisher(keys.vision("d1"), wire.Pose)

    def deliver(published_late_ns: int) -> str:
        """A pose measured 300 ms ago and published ``published_late_ns`` after; the refusal it leaves."""
        arrived = gw.vision.arrived
        now = time.time_ns()
        t = now - LATE_NS
        pub.put(wire.Pose(t=t, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, tp=t + published_late_ns))
        wait_for(lambda: gw.vision.arrived > arrived, 10.0, 0.005, "the pose counted by the gateway")
        return refusal(rig)

    # Published 20 ms after its measurement, then 280 ms on its way: the bus or the gateway ran late.
    said = deliver(20_000_000)
    m = re.search(r"the bus or this gateway runs late: the oldest was published (\d+) ms after its "
                  r"measurement and arrived here (\d+) ms after that", said)  # fmt: skip
    assert m, said
    assert int(m[1]) == 20 and int(m[2]) >= LATE_NS * 1e-6 - 20, said
    # An older one, published 290 ms after it was measured: the stages before the bus ran late; the oldest
    # pose refused is the one named.
    arrived = gw.vision.arrived
    t = time.time_ns() - 2 * LATE_NS
    pub.put(wire.Pose(t=t, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, tp=t + 590_000_000))
    wait_for(lambda: gw.vision.arrived > arrived, 10.0, 0.005, "the pose counted by the gateway")
    said = refusal(rig)
    m = re.search(r"2 too old \(\d+–\d+ ms after their measurement, more than the 100 ms allowed: the "
                  r"stages before the bus run late: the oldest was published (\d+) ms after", said)  # fmt: skip
    assert m and int(m[1]) == 590, said
