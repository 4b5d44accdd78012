"""Per-publisher sequence numbers: every sample a subscriber never got is counted, per key."""

import re
import threading
import time
from collections.abc import Callable

from arena_common.bus.sequence import STAMP, GapCounter
from arena_common.bus.session import Bus, Handler, Received
from arena_common.core import keys, wire
from arena_common.runtime.service import running
from tests.helpers import REPO, wait_for

POSE = wire.Pose(t=1, p=(0.0, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)


def test_gaps_per_key_and_publisher_late_and_unnumbered_apart() -> None:
    g = GapCounter()
    for seq in (1, 2, 5, 6):  # 3 and 4 lost
        g.observe("arena/d1/pose", STAMP.pack(7, seq))
    for seq in (10, 11, 14):  # another publisher on the same key, seen from its 10th: 12, 13 lost
        g.observe("arena/d1/pose", STAMP.pack(8, seq))
    assert g.observe("arena/d1/pose", STAMP.pack(7, 4)) == 0  # late: counted apart, the loss stays
    g.observe("arena/d2/pose", STAMP.pack(9, 100))  # first sample of a publisher: no loss before it
    assert g.observe("arena/d2/pose", STAMP.pack(9, 102)) == 1
    g.observe("arena/d2/pose", None)
    g.observe("arena/d2/pose", b"\x01\x02")  # not a stamp of ours
    assert g.lost() == {"arena/d1/pose": 4, "arena/d2/pose": 1} and sum(g.lost().values()) == 5
    d1, d2 = g.keys["arena/d1/pose"], g.keys["arena/d2/pose"]
    assert (d1.received, d1.late, d1.unnumbered) == (8, 1, 0)
    assert (d2.received, d2.late, d2.unnumbered) == (4, 0, 2)


def test_a_service_reports_what_its_subscriptions_missed_per_key(bus_factory: Callable[[], Bus]) -> None:
    a, watcher = bus_factory(), bus_factory()
    stats = watcher.subscribe(keys.STATS_ALL, capacity=64, ring=True)
    pub = a.stream_publisher(keys.pose("d1"), wire.Pose)
    stop = threading.Event()
    ready = threading.Event()
    got: list[int] = []

    def serve() -> None:
        with running("demo", None, bus=bus_factory(), host="h1", stop=stop, stats_period=0.1) as svc:
            sub = svc.bus.subscribe(keys.pose("d1"), capacity=100, ring=False)
            ready.set()
            while not stop.is_set():
                item = svc.read(sub, 0.1)
                if item is not None and item.payload is not None:
                    got.append(item.payload.fn)

    t = threading.Thread(target=serve)
    t.start()
    try:
        ready.wait(5)

        def first() -> list[int]:
            pub.put(POSE)
            return got

        wait_for(first, what="first pose")
        pub.sent += 3  # three samples numbered, then shed before they left (what DROP does under congestion)
        pub.put(POSE.replace(fn=99))
        wait_for(lambda: 99 in got, what="the pose after the gap")

        def lost() -> dict | None:
            item = stats.get(0.5)
            st = item.payload if item is not None else None
            if isinstance(st, wire.Stats) and st.service == "demo" and st.lost:
                return dict(st.lost)
            return None

        assert wait_for(lost, what="stats with the loss") == {"arena/d1/pose": 3}
    finally:
        stop.set()
        t.join(5)


def test_a_flood_a_slow_subscriber_cannot_carry_is_counted_to_the_sample(
    bus_factory: Callable[[], Bus],
) -> None:
    """Real loss: a stream publisher floods a subscriber that takes 1 ms a sample; Zenoh sheds what its
    queues cannot hold, and every sample published is either received or counted lost."""
    a, b = bus_factory(), bus_factory()
    seen: list[Received] = []

    def take_1_ms(item: Received) -> None:
        seen.append(item)
        time.sleep(0.001)

    slow = Handler(take_1_ms, on_error=lambda exc: None)
    sub = b.subscribe(keys.pose("d1"), channel=slow)
    pub = a.stream_publisher(keys.pose("d1"), wire.Pose)
    wait_for(lambda: pub.matching, what="route to the subscriber")
    pub.put(POSE)  # number 1, on a quiet link: the count starts there
    wait_for(lambda: seen, what="the first sample")
    blob = bytes(32_000)  # large samples, so that the link's buffers fill within the flood
    for _ in range(3_000):
        pub.put_raw(blob)
    key = sub.gaps.keys[keys.pose("d1")]

    # The flood's tail may be shed too: publish, paced, until the subscriber has the last one published.
    def has_the_last() -> bool:
        if key.received + key.lost == pub.sent:
            return True
        pub.put(POSE)
        return False

    wait_for(has_the_last, 30.0, what="the last sample")
    assert key.received == len(seen) and key.late == 0 and key.unnumbered == 0
    print(f"published {pub.sent}, received {key.received}, lost (counted) {key.lost}")


def test_one_off_puts_are_numbered_per_key(bus_factory: Callable[[], Bus]) -> None:
    a, b = bus_factory(), bus_factory()
    sub = b.subscribe(keys.ESTOP, capacity=100, ring=False)
    estop = wire.Estop(t=1, reason="test")

    def got() -> bool:
        a.put(keys.ESTOP, estop)
        return len(sub.channel) > 0

    wait_for(got, what="an estop")
    for _ in range(3):
        a.put(keys.ESTOP, estop)
    wait_for(lambda: sub.gaps.keys[keys.ESTOP].received >= 4, what="the three after it")
    loss = sub.gaps.keys[keys.ESTOP]
    assert loss.unnumbered == 0 and loss.lost == 0 and loss.late == 0, loss


# Where a Zenoh publication may be declared: the bus (numbered), the ROS 2 node (rmw_zenoh's own numbered
# attachment) and `arena rec replay` (a recording's bytes as they were: unnumbered, docs/wire.md).
PUBLISHERS_ALLOWED = {"arena_common/bus/session.py", "arena_common/ros2/node.py", "arena_common/cli/_rec.py"}


def test_no_module_publishes_around_the_numbered_publisher() -> None:
    found = set()
    for path in [*REPO.joinpath("arena_common").rglob("*.py"), *REPO.joinpath("services").rglob("*.py")]:
        text = path.read_text()
        if re.search(r"declare_publisher\(|session\.put\(", text):
            found.add(str(path.relative_to(REPO)))
    assert found <= PUBLISHERS_ALLOWED, sorted(found - PUBLISHERS_ALLOWED)
    assert "arena_common/bus/session.py" in found  # the scan sees the one that must be there
