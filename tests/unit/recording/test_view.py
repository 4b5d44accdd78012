"""``arena view``: the live scene over the Foxglove WebSocket protocol, read by a real WebSocket client."""

from __future__ import annotations

import base64
import json
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.recording.live import LiveView, serve
from tests.foxglove_decode import Frames, entity_points, message_class
from tests.helpers import wait_for

# The Foxglove SDK's server speaks the Foxglove WebSocket protocol (v1) under its current subprotocol
# name; the older name, foxglove.websocket.v1, names the same protocol: the viewer accepts both.
SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
LEGACY = Subprotocol("foxglove.websocket.v1")


@contextmanager
def view_thread(cfg: ArenaConfig) -> Iterator[LiveView]:
    """``arena view``'s server in a thread, on a free port of 127.0.0.1."""
    stop = threading.Event()
    ready: list[LiveView] = []
    th = threading.Thread(
        target=serve,
        args=(cfg,),
        kwargs={"address": "127.0.0.1", "port": 0, "host": "vt", "stop": stop, "on_ready": ready.append},
        daemon=True,
    )
    th.start()
    try:
        wait_for(lambda: ready, 20.0, 0.05, "the view server")
        yield ready[0]
    finally:
        stop.set()
        th.join(timeout=15)
        assert not th.is_alive(), "the view did not stop"


class Client:
    """A minimal Foxglove WebSocket (v1) client: advertisements, subscriptions, message frames."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}  # topic → advertised channel
        self.subs: dict[int, dict[str, Any]] = {}
        self.received: dict[str, list[tuple[int, Any]]] = {}

    def pump(self, seconds: float) -> None:
        """Read whatever arrives for ``seconds``."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    self.server_info = msg
                elif msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        self.channels[ch["topic"]] = ch
            elif frame[0] == 0x01:  # message data: opcode, subscription id, log time, payload
                sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                ch = self.subs[sub_id]
                payload = bytes(frame[13:])
                if ch["encoding"] == "protobuf":
                    cls = message_class(ch["schemaName"], base64.b64decode(ch["schema"]))
                    decoded: Any = cls.FromString(payload)
                else:
                    decoded = json.loads(payload)
                self.received.setdefault(ch["topic"], []).append((log_time, decoded))

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for i, topic in enumerate(topics, start=1):
            self.subs[i] = self.channels[topic]
            subs.append({"id": i, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


def test_view_streams_the_live_scene_to_a_websocket_client(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(n_vehicles=1)
    bus = bus_factory()
    pose_pub = bus.stream_publisher(keys.pose("d1"), wire.Pose)
    state_pub = bus.stream_publisher(keys.state("d1"), wire.State)
    event_pub = bus.command_publisher(keys.events("d1"), wire.Event)
    stop = threading.Event()
    sent = {"pose": 0}

    def publish() -> None:
        i = 0
        while not stop.is_set():
            now = wire.now_ns()
            pose_pub.put(wire.Pose(t=now, p=(1.0, 0.5, -1.2), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=i + 1))
            sent["pose"] += 1
            if i % 10 == 0:
                state_pub.put(
                    wire.State(t=now, p=(1.0, 0.5, -1.1), q=(1.0, 0.0, 0.0, 0.0), link=True, bat=0.9)
                )
                event_pub.put(wire.Event(t=now, kind="info", text=f"hello {i}", sev=6))
            i += 1
            time.sleep(0.02)

    with view_thread(cfg) as view:
        pub = threading.Thread(target=publish, daemon=True)
        pub.start()
        try:
            with connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:
                assert ws.subprotocol == SUBPROTOCOL
                client = Client(ws)
                wanted = [
                    "/arena/tf",
                    "/arena/scene/room",
                    "/arena/d1/tf",
                    "/arena/scene/vehicles",
                    "/arena/log",
                ]
                wanted.append("arena/d1/pose")  # the arena's own key, in the recordings' JSON form

                def advertised() -> bool:
                    client.pump(0.2)
                    return all(t in client.channels for t in wanted)

                wait_for(advertised, 20.0, 0.0, f"the server to advertise {wanted}")
                assert client.server_info.get("name") == "Flying Arena"
                assert client.channels["/arena/scene/room"]["schemaName"] == "foxglove.SceneUpdate"
                assert client.channels["/arena/d1/tf"]["encoding"] == "protobuf"
                assert client.channels["arena/d1/pose"]["schemaEncoding"] == "jsonschema"
                client.subscribe(wanted)

                def received() -> bool:
                    client.pump(0.2)
                    return all(client.received.get(t) for t in wanted)

                wait_for(received, 20.0, 0.0, "a message on every subscribed topic")
            # Issue 25: a client offering only the older name (older Lichtblick, PlotJuggler, roslibjs) is
            # served the same protocol under the name it asked for.
            with connect(f"ws://127.0.0.1:{view.port}", subprotocols=[LEGACY], open_timeout=10) as ws:
                assert ws.subprotocol == LEGACY
                legacy = Client(ws)

                def advertised() -> bool:
                    legacy.pump(0.2)
                    return "/arena/d1/tf" in legacy.channels

                wait_for(advertised, 20.0, 0.0, "advertised")
                assert legacy.server_info.get("name") == "Flying Arena"
                legacy.subscribe(["/arena/d1/tf"])

                def data() -> bool:
                    legacy.pump(0.2)
                    return bool(legacy.received.get("/arena/d1/tf"))

                wait_for(data, 20.0, 0.0, "data")
            with pytest.raises(InvalidStatus):  # a subprotocol that is no name of this protocol
                connect(f"ws://127.0.0.1:{view.port}", subprotocols=[Subprotocol("x.v1")], open_timeout=10)
        finally:
            stop.set()
            pub.join(timeout=5)
    assert sent["pose"] > 0
    frames = Frames()
    for topic in ("/arena/tf", "/arena/d1/tf"):
        for _, m in client.received[topic]:
            frames.add(m)
    # NED (1, 0.5, -1.2) is 0.5 m east, 1 m north, 1.2 m up in Foxglove's world
    assert np.allclose(frames.to_root("d1", (0, 0, 0)), (0.5, 1.0, 1.2))
    room = {e.id: e for e in client.received["/arena/scene/room"][-1][1].entities}
    walls = entity_points(room["room"], frames)
    n, e, h = cfg.arena.size
    assert np.allclose(walls.min(axis=0), (-e / 2, -n / 2, 0.0)) and np.allclose(
        walls.max(axis=0), (e / 2, n / 2, h)
    )
    vehicles = {e.id for _, m in client.received["/arena/scene/vehicles"] for e in m.entities}
    assert "d1" in vehicles
    logs = [m for _, m in client.received["/arena/log"]]
    assert all(m.name == "d1" and m.message.startswith("[info] hello ") for m in logs)
    pose = client.received["arena/d1/pose"][-1][1]
    assert pose["p"] == [1.0, 0.5, -1.2] and set(pose["t"]) == {"sec", "nsec"}
    assert view.samples > 0 and view.undecodable == 0
