"""``arena status`` and ``arena top`` show what the bus lost, per service, per vehicle and per key."""

import re
import threading
from collections.abc import Callable

from rich.console import Console

from arena_common.bus.session import Bus
from arena_common.cli._flight import Snapshot, lost_by_key, lost_by_vehicle
from arena_common.core import wire
from arena_common.runtime.service import running
from tests.helpers import wait_for


def _stats(service: str, lost: dict[str, int]) -> wire.Stats:
    return wire.Stats(t=1, service=service, host="h1", lost=lost)


def test_loss_per_key_counts_once_and_per_vehicle_sums_its_keys() -> None:
    stats = [
        _stats("transform", {"arena/sys/frames": 4}),
        _stats("gateway.d1", {"arena/d1/vision": 3, "arena/sys/fleet": 1}),
        _stats("recorder", {"arena/d1/vision": 5, "arena/d1/pose": 2, "arena/sys/frames": 1}),
    ]
    # Two subscribers of one key both miss what the bus shed before it: the larger count, not the sum.
    assert lost_by_key(stats) == {
        "arena/sys/frames": 4,
        "arena/d1/vision": 5,
        "arena/sys/fleet": 1,
        "arena/d1/pose": 2,
    }
    assert lost_by_vehicle(stats) == {"d1": 7}


def test_status_shows_the_loss_of_each_service_and_vehicle(bus_factory: Callable[[], Bus]) -> None:
    viewer = bus_factory()
    stop = threading.Event()
    started = threading.Event()

    def serve() -> None:
        with running("gateway", None, bus=bus_factory(), host="h1", vehicle="d1", stop=stop):
            started.set()
            stop.wait(10)

    t = threading.Thread(target=serve)
    t.start()
    try:
        started.wait(5)
        wait_for(lambda: viewer.alive("arena/sys/alive/**"), what="the service's token")
        snap = Snapshot(viewer)
        snap.stats["h1/gateway.d1"] = _stats("gateway.d1", {"arena/d1/vision": 17})
        snap.states["d1"] = wire.State(t=1, armed=False, mode="POSCTL", link=True)
        snap.state_time["d1"] = 0.0
        console = Console(width=400, record=True)
        console.print(snap.render())
        text = console.export_text()
        rows = [[c.strip() for c in re.split("[│┃]", line)[1:-1]] for line in text.splitlines()]
        services = next(r for r in rows if "service" in r and "lost" in r)
        gateway = next(r for r in rows if "gateway.d1" in r)
        assert gateway[services.index("lost")] == "17", (services, gateway)
        vehicles = next(r for r in rows if "vehicle" in r and "lost" in r)
        d1 = next(r for r in rows if r and r[0] == "d1")
        assert d1[vehicles.index("lost")] == "17", (vehicles, d1)
    finally:
        stop.set()
        t.join(5)
