"""A part of a session that closes alone (:mod:`arena_common.bus.view`): what it declared goes, the
session and the rest stay, and its losses stay counted by its parent."""

from collections.abc import Callable

from arena_common.bus.session import Bus
from arena_common.bus.view import BusView
from arena_common.core import keys, wire
from tests.helpers import wait_for

POSE = wire.Pose(t=1, p=(0.0, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)


def _answers(bus: Bus, key: str) -> int:
    command = wire.Command(op="ping", args={}, src="test", timeout=2.0)
    return sum(1 for r in bus.session.get(key, payload=command.encode(), timeout=2.0) if r.ok is not None)


def test_a_view_closes_its_own_endpoints_and_keeps_its_losses_counted(bus_factory: Callable[[], Bus]) -> None:
    host, peer = bus_factory(), bus_factory()
    view = BusView(host)
    mine = view.subscribe(keys.pose("d1"), capacity=100, ring=False)
    kept = host.subscribe(keys.pose("d1"), capacity=100, ring=False)
    view.serve(keys.cmd("d1"), lambda key, c: wire.CommandResult(True, "ACCEPTED", "view"))
    pub = peer.stream_publisher(keys.pose("d1"), wire.Pose)
    wait_for(lambda: pub.matching, what="route to the subscribers")
    wait_for(lambda: _answers(peer, keys.cmd("d1")) == 1, what="the view's queryable")

    pub.put(POSE)
    wait_for(lambda: mine.get(0.1) is not None, what="the first pose through the view")
    pub.sent += 2  # two samples numbered, then shed before they left
    pub.put(POSE.replace(fn=9))
    wait_for(lambda: view.lost() == {keys.pose("d1"): 2}, what="the view's subscription counting the gap")
    assert host.lost() == {keys.pose("d1"): 2}  # the parent counts its views' losses

    view.close()
    assert _answers(peer, keys.cmd("d1")) == 0  # its queryable went with it
    assert mine.channel.closed and not kept.channel.closed
    assert host.lost() == {keys.pose("d1"): 2}  # a closed view's losses stay counted
    pub.put(POSE.replace(fn=10))
    wait_for(
        lambda: (item := kept.get(0.1)) is not None and getattr(item.payload, "fn", None) == 10,
        what="the session going on",
    )
    view.close()  # a second close is nothing
    host.close()  # the parent closes what is left; the closed view is not closed again
