"""The live 3D view: the bus as a Foxglove scene, served over the Foxglove WebSocket protocol.

:class:`LiveView` runs the Foxglove SDK's WebSocket server (subprotocol ``foxglove.sdk.v1``, and the same
protocol's older name ``foxglove.websocket.v1`` through :mod:`arena_common.recording.ws_subprotocol`) and
publishes on it what a recording holds: the 3D scene of :mod:`arena_common.recording.scene` (protobuf)
and, beside it, every arena key in the recordings' JSON form (so that the same Foxglove layout plots
live data and recordings).  Foxglove (the desktop app or app.foxglove.dev) connects to
``ws://<address>:<port>``.  :func:`serve` feeds it from the bus (``arena view``).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import foxglove

from arena_common.bus.session import BusOptions, Channel, Received, Subscription
from arena_common.core import wire
from arena_common.core.config import ArenaConfig, ArenaSpec
from arena_common.core.errors import PayloadError
from arena_common.recording.codec import JSON, SCHEMA_ENCODING, decode_sample, encode_json, record_schema
from arena_common.recording.scene import ENCODING, Scene, SceneMessage, schemas
from arena_common.recording.ws_subprotocol import SubprotocolBridge
from arena_common.runtime.service import running

DEFAULT_PORT = 8765
QUEUE_CAPACITY = 20_000  # samples; a viewer wants the newest, so the oldest are dropped beyond this
TICK_S = 0.05


class LiveView:
    """A Foxglove WebSocket server showing the arena's scene; feed it samples with :meth:`add`.

    Thread-safe.  ``port`` 0 picks a free port (see :attr:`port`).
    """

    def __init__(
        self,
        arena: ArenaSpec | None = None,
        *,
        address: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        name: str = "Flying Arena",
        forward_keys: bool = True,
    ) -> None:
        self.context = foxglove.Context()
        self.scene = Scene(arena)
        self.forward_keys = forward_keys
        self.samples = 0
        self.undecodable = 0
        self._lock = threading.Lock()
        self._scene_channels: dict[str, foxglove.Channel] = {}
        self._key_channels: dict[tuple[str, type[wire.Payload]], foxglove.Channel] = {}
        # The SDK's server on a loopback port of its own; clients reach it through the bridge, which
        # also accepts the protocol's older subprotocol name (older Lichtblick, PlotJuggler, roslibjs).
        self.server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=self.context)
        try:
            self.bridge = SubprotocolBridge(address, port, int(self.server.port))
        except BaseException:
            self.server.stop()
            raise

    @property
    def port(self) -> int:
        """The TCP port the viewer listens on."""
        return self.bridge.port

    def add(self, key: str, raw: bytes, encoding: str, t_recv: int) -> bool:
        """Show one sample; ``False`` when it does not decode (it is then only counted)."""
        try:
            decoded = decode_sample(key, raw, encoding)
        except PayloadError:
            with self._lock:
                self.undecodable += 1
            return False
        with self._lock:
            self.samples += 1
            if self.forward_keys:
                ch = self._key_channels.get((key, decoded.cls))
                if ch is None:
                    schema = foxglove.Schema(
                        name=f"arena.{decoded.cls.SCHEMA}",
                        encoding=SCHEMA_ENCODING,
                        data=json.dumps(record_schema(decoded.cls, JSON)).encode(),
                    )
                    ch = self._key_channels[(key, decoded.cls)] = foxglove.Channel(
                        key, schema=schema, message_encoding=JSON, context=self.context
                    )
                if ch.has_sinks():  # JSON only for a subscribed viewer
                    ch.log(encode_json(decoded.cls, decoded.wire_map, raw), log_time=t_recv)
            self._publish(self.scene.add(key, decoded.payload, t_recv))
        return True

    def tick(self, now: int | None = None) -> None:
        """Publish what is due (static scene every second, trails, labels, setpoints)."""
        with self._lock:
            self._publish(self.scene.tick(time.time_ns() if now is None else now))

    def _publish(self, messages: Sequence[SceneMessage]) -> None:
        for m in messages:
            ch = self._scene_channels.get(m.topic)
            if ch is None:
                ch = self._scene_channels[m.topic] = foxglove.Channel(
                    m.topic, schema=schemas()[m.schema], message_encoding=ENCODING, context=self.context
                )
            ch.log(m.data, log_time=m.log_time)

    def close(self) -> None:
        """Stop the server (clients are disconnected)."""
        self.bridge.close()
        self.server.stop()


def serve(
    cfg: ArenaConfig | None,
    options: BusOptions | None = None,
    *,
    address: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    key_exprs: Sequence[str] = ("arena/**",),
    host: str | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[LiveView], None] | None = None,
) -> None:
    """Subscribe to ``key_exprs`` on the bus and serve the scene until ``stop`` (or SIGINT/SIGTERM)."""
    with running("viewer", cfg, options, host=host, stop=stop) as svc:
        view = LiveView(cfg.arena if cfg else None, address=address, port=port)
        queue: Channel[Received[Any]] = Channel(QUEUE_CAPACITY, ring=True)
        subs = [Subscription(svc.bus, expr, None, queue, keep_raw=False) for expr in key_exprs]
        svc.log.info("serving the live 3D scene on ws://%s:%d", address, view.port)
        try:
            if on_ready is not None:
                on_ready(view)
            while not svc.stopped:
                item = queue.get(TICK_S)
                for it in [item, *queue.drain()] if item is not None else []:
                    if view.add(it.key, it.raw, it.encoding, it.t_recv):
                        svc.stats.count("in")
                    else:
                        svc.reject("undecodable", f"{it.key}: not a valid payload ({it.encoding})")
                view.tick()
        finally:
            for s in subs:
                s.close()
            view.close()
