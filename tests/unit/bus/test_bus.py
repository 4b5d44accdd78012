import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from arena_common.bus.hosts import host_bus_options
from arena_common.bus.session import Bus, BusOptions, Channel
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.runtime.service import running
from tests.helpers import free_port, wait_for, write_config

POSE = wire.Pose(t=1, p=(0.0, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)


def test_ring_keeps_latest_and_fifo_drops_newest() -> None:
    ring: Channel[int] = Channel(2, ring=True)
    fifo: Channel[int] = Channel(2, ring=False)
    for i in range(5):
        ring.put(i)
        fifo.put(i)
    assert ring.drain() == [3, 4] and ring.dropped == 3
    assert fifo.drain() == [0, 1] and fifo.dropped == 3
    fifo.close()
    assert fifo.get(5.0) is None  # closed and empty: returns at once


def test_channel_hands_every_item_to_parked_readers_and_close_wakes_them() -> None:
    ch: Channel[int] = Channel(100_000, ring=False)
    got: list[int] = []
    lock = threading.Lock()

    def reader() -> None:
        while True:
            item = ch.get(5.0)
            if item is None:
                return
            with lock:
                got.append(item)

    readers = [threading.Thread(target=reader) for _ in range(3)]
    for t in readers:
        t.start()

    # Producers race the readers parking and unparking: nothing may be lost or stranded.
    def produce(k: int) -> None:
        for i in range(5_000):
            ch.put(k * 10_000 + i)

    producers = [threading.Thread(target=produce, args=(k,)) for k in range(2)]
    for t in producers:
        t.start()
    for t in producers:
        t.join(5.0)
    wait_for(lambda: len(got) == 10_000, 5.0, what="every item read")
    ch.close()
    for t in readers:
        t.join(2.0)
        assert not t.is_alive(), "close() left a reader parked"
    assert sorted(got) == sorted(k * 10_000 + i for k in range(2) for i in range(5_000))
    assert ch.get(0.0) is None and ch.dropped == 0


def test_channel_get_times_out_empty() -> None:
    ch: Channel[int] = Channel(1)
    assert ch.get(0.05) is None
    ch.put(1)
    assert ch.get(0.05) == 1


def test_typed_publish_subscribe_and_bad_payload(bus_factory: Callable[[], Bus]) -> None:
    a, b = bus_factory(), bus_factory()
    sub = b.subscribe("arena/*/pose", capacity=100, ring=False)
    pub = a.stream_publisher(keys.pose("d1"), wire.Pose)
    raw = a.stream_publisher(keys.pose("d2"), wire.Pose)

    def got() -> list:
        items.extend(sub.channel.drain())
        return [i for i in items if i.payload is not None]

    items: list = []

    def sent_and_got() -> list:
        pub.put(POSE)
        return got()

    wait_for(sent_and_got, what="first pose")
    raw.put_raw(b"\x81\xa1t\xa3bad")
    pub.put(POSE.replace(fn=9))
    wait_for(lambda: any(i.payload and i.payload.fn == 9 for i in got()), what="pose after bad one")
    errors = [i for i in items if i.error is not None]
    assert errors and errors[0].key == "arena/d2/pose" and "field=t" in str(errors[0].error)


def test_request_reply_and_no_server(bus_factory: Callable[[], Bus]) -> None:
    a, b = bus_factory(), bus_factory()
    b.serve("arena/d1/cmd", lambda key, c: wire.CommandResult(True, "ACCEPTED", reason=f"{c.op} on {key}"))
    res = wait_for(
        lambda: (r := a.request("arena/d1/cmd", wire.Command(op="ping"), 2.0)).ok and r, what="reply"
    )
    assert res.reason == "ping on arena/d1/cmd"
    none = a.request("arena/d9/cmd", wire.Command(op="ping"), 1.0)
    assert not none.ok and none.result == "TIMEOUT"


def test_service_presence_and_stats(bus_factory: Callable[[], Bus]) -> None:
    watcher = bus_factory()
    stop = threading.Event()
    stats_sub = watcher.subscribe("arena/sys/stats/**", capacity=10)
    started = threading.Event()

    def serve() -> None:
        with running(
            "demo", None, bus=bus_factory(), host="h1", vehicle="d1", stop=stop, stats_period=0.1
        ) as svc:
            svc.stats.count("in", 3)
            svc.reject("bad_payload", "test")
            started.set()
            stop.wait(10)

    t = threading.Thread(target=serve)
    t.start()
    try:
        started.wait(5)
        wait_for(lambda: watcher.alive("arena/sys/alive/**") == ["arena/sys/alive/h1/demo.d1"], what="token")
        item = wait_for(lambda: stats_sub.get(0.5), what="stats")
        assert item.key == "arena/sys/stats/h1/demo.d1"
        assert item.payload.counts == {"in": 3} and item.payload.rejected == {"bad_payload": 1}
    finally:
        stop.set()
        t.join(5)
    wait_for(lambda: watcher.alive("arena/sys/alive/**") == [], what="token gone")


def test_matching_follows_subscribers_across_sessions(bus_factory: Callable[[], Bus]) -> None:
    a, b = bus_factory(), bus_factory()
    pub = a.stream_publisher(keys.pose("d1"), wire.Pose)
    assert pub.matching is False  # nobody yet (and from now on Zenoh tells the publisher)
    sub = b.subscribe(keys.pose("d1"), capacity=10, ring=True)
    wait_for(lambda: pub.matching, what="the other session's subscriber")
    sub.close()
    wait_for(lambda: not pub.matching, what="the subscriber gone")
    local = a.subscribe("arena/*/pose", capacity=10, ring=True)
    wait_for(lambda: pub.matching, what="a subscriber of the same session, by a wildcard")
    local.close()
    pub.close()
    assert pub.matching is False  # closed: nothing matches, nothing raises


def test_a_vehicles_process_joins_as_a_client_when_the_config_says(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]
) -> None:
    """``zenoh.vehicle_mode = "client"``: a vehicle's own process is a client of the router (listens on
    nothing), and still meets the peers through it; other processes and an explicit ``--mode`` keep theirs."""
    path = write_config(tmp_path, router_endpoint)
    path.write_text(
        path.read_text().replace('mode = "peer"\n', 'mode = "peer"\nvehicle_mode = "client"\n', 1)
    )
    cfg = config_mod.load(path)
    assert host_bus_options(cfg, "test", None, vehicle="d1") == BusOptions(mode="client")
    assert host_bus_options(cfg, "test", BusOptions(listen=("tcp/127.0.0.1:0",)), vehicle="d1").listen == ()
    assert host_bus_options(cfg, "test", None).mode is None  # not a vehicle's process: zenoh.mode
    assert host_bus_options(cfg, "test", BusOptions(mode="peer"), vehicle="d1").mode == "peer"
    peer = bus_factory()
    stats = peer.subscribe(keys.stats("test", "gateway.d1"), capacity=8)
    with running("gateway", cfg, vehicle="d1", host="test", clock=False, stats_period=0.2) as svc:
        assert svc.id == "gateway.d1"
        routers = list(svc.bus.session.info.routers_zid())
        peers = list(svc.bus.session.info.peers_zid())
        assert len(routers) == 1 and peers == []  # one link: the router
        first = stats.get(timeout=10.0)
        assert first is not None and isinstance(first.payload, wire.Stats)


def _zenoh_threads(pid: int) -> list[str]:
    """The names of a process's Zenoh runtime threads (``net-0``, ``app-0``, ...)."""
    names = []
    for comm in Path(f"/proc/{pid}/task").glob("*/comm"):
        try:
            names.append(comm.read_text().strip())
        except OSError:
            pass
    return [n for n in names if n.startswith(("net-", "app-"))]


def test_ctrl_c_stops_a_client_still_waiting_for_its_router(tmp_path: Path) -> None:
    """A client waits up to 10 s for its router inside ``zenoh.open``: Ctrl-C must stop it at once anyway."""
    path = write_config(tmp_path, f"tcp/127.0.0.1:{free_port()}")  # nobody listens there
    path.write_text(
        path.read_text().replace('mode = "peer"\n', 'mode = "peer"\nvehicle_mode = "client"\n', 1)
    )
    arena = str(Path(sys.executable).with_name("arena"))
    proc = subprocess.Popen(
        [arena, "run", "gateway", "--vehicle", "d1", "-c", str(path)],
        cwd=tmp_path,
        # Ctrl-C as a terminal delivers it: a test run started in the background inherits SIGINT ignored.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        # Zenoh's runtime threads exist once ``zenoh.open`` runs: then it is waiting for the router (a Ctrl-C
        # during the imports before, on a slow machine, ends the process by the signal itself, as Python does).
        deadline = time.monotonic() + 60.0
        while not _zenoh_threads(proc.pid) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert _zenoh_threads(proc.pid), "the client never started opening its Zenoh session"
        time.sleep(0.5)
        assert proc.poll() is None
        started = time.monotonic()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130
        assert time.monotonic() - started < 6.0  # not the 10 s of the router wait
    finally:
        proc.kill()
