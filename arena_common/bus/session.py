"""Zenoh bus helpers: sessions from the config, typed publishers, channel subscribers, requests, presence.

The idioms (see the project brief): real-time streams drop on congestion, commands block and are
reliable; nothing heavy runs inside a Zenoh callback — samples go to a :class:`Channel` (a ring that
keeps the latest, for controllers, or a bounded FIFO, for recorders) that your own thread drains;
requests are queries on queryables with a timeout; presence is a liveliness token; sessions are always
closed.  Every command takes the same ``--mode/--connect/--listen/--zconfig`` overrides
(:class:`BusOptions`).
"""

from __future__ import annotations

import collections
import enum
import json
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh

from arena_common.bus.sequence import STAMP, GapCounter, new_publisher_id
from arena_common.core import wire
from arena_common.core.config import ZenohSpec
from arena_common.core.errors import BusError, PayloadError

P = TypeVar("P", bound=wire.Payload)
DISCOVERY_S = 2.0  # how long a new session may take to learn routes and tokens
T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class BusOptions:
    """Command-line overrides of the config's Zenoh section (the same on every command)."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zconfig: str | None = None  # a Zenoh JSON5 config file, applied first
    address: str = ""  # this host's address: a peer with no listen endpoint listens there (else loopback)
    settings: dict[str, Any] = field(default_factory=dict)  # raw "path": value overrides, applied last


def zenoh_config(spec: ZenohSpec | None = None, options: BusOptions | None = None) -> zenoh.Config:
    """Build a Zenoh config: config file section, then command-line overrides.

    Multicast scouting is off unless asked for (explicit endpoints and gossip are more predictable on a
    lab network); send batching is limited to ``batching_ms`` so that latency comes from batching, not
    from ``express`` (which doubles the CPU cost per message).
    """
    spec = spec or ZenohSpec()
    options = options or BusOptions()
    conf = zenoh.Config.from_file(options.zconfig) if options.zconfig else zenoh.Config()
    mode = options.mode or spec.mode
    connect = list(options.connect or spec.connect)
    listen = list(options.listen or spec.listen)
    if mode == "router" and not listen:
        listen = list(spec.router_listen)
    if mode == "peer" and not listen:
        # Peers on different hosts only talk over direct links, so a peer listens on its host's address
        # (hosts.<name>.address); with none, on loopback only — never on every interface unasked.
        addr = options.address or "127.0.0.1"
        listen = [f"tcp/[{addr}]:0" if ":" in addr else f"tcp/{addr}:0"]
    settings: dict[str, Any] = {
        "mode": mode,
        "scouting/multicast/enabled": spec.multicast_scouting,
        "transport/link/tx/lease": spec.lease_ms,
        "transport/link/tx/keep_alive": 4,
        "transport/link/tx/queue/batching/time_limit": spec.batching_ms,
        "transport/link/tx/queue/batching/enabled": spec.batching_ms > 0,
    }
    if connect:
        settings["connect/endpoints"] = connect
        # Services may start before the router (keep trying); a client gives up after 10 s, with an error.
        settings["connect/timeout_ms"] = -1 if mode != "client" else 10000
        settings["connect/exit_on_failure"] = False
        # Retry soon and often (Zenoh's default starts at 1 s and doubles): a router restarted on the
        # same host is back in well under a second.
        settings["connect/retry"] = {
            "period_init_ms": 200,
            "period_max_ms": 2000,
            "period_increase_factor": 1.5,
        }
    if listen:
        settings["listen/endpoints"] = listen
    settings.update(dict(spec.extra))
    settings.update(options.settings)
    for path, value in settings.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as exc:
            raise BusError(f"zenoh setting {path} = {value!r} refused: {exc}") from None
    return conf


class Channel(Generic[T]):
    """A bounded hand-off from a Zenoh callback to your own thread.

    ``ring=True`` keeps the newest ``capacity`` items (older ones are overwritten); otherwise it is a
    FIFO that drops (and counts) what arrives while it is full.  ``put`` never blocks.

    Items wait in a deque (appends and pops are atomic under the GIL); a reader with nothing to read
    parks on a ``SimpleQueue`` (implemented in C) that ``put`` wakes only when a reader is parked.  This
    costs a third less CPU per message than a ``threading.Condition`` and cuts the tail of the hand-off.
    """

    def __init__(self, capacity: int = 1, ring: bool = True) -> None:
        if capacity < 1:
            raise ValueError("channel capacity must be at least 1")
        self.capacity = capacity
        self.ring = ring
        self._items: collections.deque[T] = collections.deque(maxlen=capacity if ring else None)
        self._wake: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._parked = 0  # readers waiting for a wake-up
        self._closed = False
        self.dropped = 0

    def put(self, item: T) -> None:
        """Add an item; never blocks."""
        if self._closed:
            return
        if len(self._items) >= self.capacity:
            self.dropped += 1
            if not self.ring:
                return
        self._items.append(item)
        if self._parked:
            with self._lock:
                if self._parked:
                    self._parked -= 1
                    self._wake.put(None)

    def get(self, timeout: float | None = None) -> T | None:
        """The next item, or ``None`` after ``timeout`` seconds or once closed and empty."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                return self._items.popleft()
            except IndexError:
                pass
            if self._closed:
                return None
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            # Park, then look again: an item put between the first look and parking is not missed.
            with self._lock:
                self._parked += 1
            if self._items or self._closed:
                self._unpark()
                continue
            try:
                self._wake.get(timeout=left)
            except queue.Empty:
                self._unpark()
                return None

    def _unpark(self) -> None:
        # Still counted as parked: no wake-up was sent for this reader.  Otherwise its token stays
        # queued and only costs the next parked reader one extra look.
        with self._lock:
            if self._parked:
                self._parked -= 1

    def drain(self) -> list[T]:
        """Every item waiting, without blocking."""
        items: list[T] = []
        while True:
            try:
                items.append(self._items.popleft())
            except IndexError:
                return items

    def close(self) -> None:
        """Wake every waiter; later ``put`` calls are ignored."""
        self._closed = True
        with self._lock:
            for _ in range(self._parked):
                self._wake.put(None)
            self._parked = 0

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        return len(self._items)


@dataclass(slots=True)
class Received(Generic[P]):
    """A decoded sample: its key, payload, receive time, or the error that made it undecodable."""

    key: str
    payload: P | None
    t_recv: int
    error: PayloadError | None = None
    raw: bytes = b""
    encoding: str = ""


def typed(item: Received[Any], ptype: type[P], reject: Callable[[str, str], None]) -> P | None:
    """``item``'s payload when it is a ``ptype``; else ``reject(kind, detail)`` and None.

    ``kind`` is ``"bad_payload"`` (undecodable: the wire contract refused it) or ``"wrong_type"`` (a valid
    payload of another type on this key): the one place a typed reader tells the two apart.
    """
    if item.error is not None or item.payload is None:
        reject("bad_payload", str(item.error))
        return None
    if not isinstance(item.payload, ptype):
        reject("wrong_type", f"{item.key} carried {type(item.payload).__name__}, not {ptype.__name__}")
        return None
    return item.payload


class Handler(Channel[Received[Any]]):
    """A :class:`Channel`'s stand-in that hands each sample to a function on the Zenoh thread at once.

    For work that is short, bounded and never blocks (the gateway's vision: a decode, a few checks, one
    non-blocking write): it saves the hand-off to a thread, about a third of a message's CPU.  Calls are
    serialised; an exception is given to ``on_error``, never to Zenoh.
    """

    def __init__(
        self, fn: Callable[[Received[Any]], None], on_error: Callable[[BaseException], None]
    ) -> None:
        super().__init__(1, ring=False)
        self._fn = fn
        self._on_error = on_error
        self._call_lock = threading.Lock()

    def put(self, item: Received[Any]) -> None:
        if self._closed:
            return
        with self._call_lock:
            try:
                self._fn(item)
            except Exception as exc:  # one sample must never end the subscription
                self._on_error(exc)

    def get(self, timeout: float | None = None) -> Received[Any] | None:
        """Nothing waits here (samples went to the function): ``None`` at once."""
        return None


class Subscription:
    """A subscriber whose samples wait in a :class:`Channel` for your thread.  Iterate or call ``get``.

    Its :attr:`gaps` count, per key, the samples its publishers numbered that never arrived
    (:mod:`~arena_common.bus.sequence`).
    """

    def __init__(
        self,
        bus: Bus,
        keyexpr: str,
        decode: Callable[[str, bytes, str], Any] | None,
        channel: Channel[Received[Any]],
        keep_raw: bool,
    ) -> None:
        self.keyexpr = keyexpr
        self.channel = channel
        self._dropped_seen = 0
        self._decode = decode
        self._keep_raw = keep_raw
        self._bus = bus
        self.gaps = GapCounter()
        self._sub = bus.session.declare_subscriber(keyexpr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: decode (cheap, bounded) and hand over; never block here.
        key = str(sample.key_expr)
        att = sample.attachment
        self.gaps.observe(key, None if att is None else att.to_bytes())
        raw = sample.payload.to_bytes()
        enc = str(sample.encoding)
        item: Received[Any] = Received(key, None, time.time_ns(), None, raw if self._keep_raw else b"", enc)
        if self._decode is not None:
            try:
                item.payload = self._decode(key, raw, enc)
            except PayloadError as exc:
                item.error = exc
        else:
            item.raw = raw
        self.channel.put(item)

    def newly_dropped(self) -> int:
        """Samples the channel dropped (it was full) since the last call: for a ``dropped`` counter."""
        total = self.channel.dropped
        new, self._dropped_seen = total - self._dropped_seen, total
        return new

    def get(self, timeout: float | None = None) -> Received[Any] | None:
        """The next sample, or ``None`` on timeout."""
        return self.channel.get(timeout)

    def __iter__(self) -> Iterator[Received[Any]]:
        while not self.channel.closed:
            item = self.channel.get(0.2)
            if item is not None:
                yield item

    def close(self) -> None:
        """Undeclare and wake readers."""
        try:
            self._sub.undeclare()
        except Exception:  # already gone with its session
            pass
        self.channel.close()
        self._bus._retire(self)


class Lane(enum.Enum):
    """How much a real-time stream matters when a link or a computer cannot carry everything.

    Zenoh serves higher priorities first and, for streams that drop rather than wait, sheds the lower ones
    when their queues fill: vision (what keeps a vehicle in the air) first; then poses and setpoints;
    state, telemetry, statistics and clock reports last.  Not *express*: an express message is a batch
    of its own, and a priority's queue holds two batches, so a burst of vision on a busy computer would
    be dropped where batched it travels.
    """

    VISION = zenoh.Priority.REAL_TIME
    CONTROL = zenoh.Priority.DATA_HIGH
    DATA = zenoh.Priority.DATA
    REPORT = zenoh.Priority.DATA_LOW


class Publisher(Generic[P]):
    """Typed publisher on one key: sets the schema encoding, counts what it sent and numbers it (its id
    and the sample's number in the attachment, :mod:`~arena_common.bus.sequence`)."""

    def __init__(self, bus: Bus, key: str, ptype: type[P], realtime: bool, lane: Lane = Lane.DATA) -> None:
        self.key = key
        self.ptype = ptype
        self.sent = 0
        self.id = new_publisher_id()
        self._matching: bool | None = None  # None until first asked (see :attr:`matching`)
        self._listener: Any = None
        self._enc = zenoh.Encoding(ptype.encoding())
        self._pub = bus.session.declare_publisher(
            key,
            encoding=self._enc,
            congestion_control=zenoh.CongestionControl.DROP if realtime else zenoh.CongestionControl.BLOCK,
            priority=lane.value if realtime else zenoh.Priority.INTERACTIVE_HIGH,
            reliability=zenoh.Reliability.BEST_EFFORT if realtime else zenoh.Reliability.RELIABLE,
        )

    def put(self, payload: P) -> None:
        """Encode and publish one payload."""
        self.sent += 1
        self._pub.put(payload.encode(), attachment=STAMP.pack(self.id, self.sent))

    @property
    def matching(self) -> bool:
        """Whether any subscriber (here or on any computer of the bus) takes this key now.

        From the first question on, Zenoh tells this publisher when the answer changes (a matching
        listener), so asking is an attribute read: fit for a per-sample path.
        """
        if self._matching is None:
            try:
                # On Zenoh's own thread (no Python thread of its own): it only stores a flag.
                handler: Any = zenoh.handlers.Callback(self._on_matching, indirect=False)
                self._listener = self._pub.declare_matching_listener(handler)
                # Typed as a bool by zenoh's stubs; a MatchingStatus at run time.
                status: Any = self._pub.matching_status
                self._matching = bool(status.matching)
            except Exception:  # undeclared with its session
                self._matching = False
        return self._matching

    def _on_matching(self, status: Any) -> None:
        self._matching = bool(status.matching)

    def put_raw(self, data: bytes) -> None:
        """Publish bytes as they are (replay, tests of bad input), numbered as every sample."""
        self.sent += 1
        self._pub.put(data, attachment=STAMP.pack(self.id, self.sent))

    def close(self) -> None:
        try:
            if self._listener is not None:
                self._listener.undeclare()
            self._pub.undeclare()
        except Exception:
            pass
        self._matching = False  # after the listener: nothing sets it again


class Bus:
    """An open Zenoh session with the arena's idioms.  Use as a context manager."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.opened = time.monotonic()
        self._closables: list[Any] = []
        self._subscriptions: list[Subscription] = []
        self._retired_lost: dict[str, int] = {}
        self._put_id = new_publisher_id()
        self._put_seq: dict[str, int] = {}
        self._views: list[Bus] = []  # parts of this session that close alone (bus.view.BusView)
        self._lock = threading.Lock()

    # -- publishing -------------------------------------------------------------------------------
    def stream_publisher(self, key: str, ptype: type[P], lane: Lane = Lane.DATA) -> Publisher[P]:
        """Publisher for real-time streams (poses, state): drops rather than waits when congested."""
        return self._keep(Publisher(self, key, ptype, realtime=True, lane=lane))

    def command_publisher(self, key: str, ptype: type[P]) -> Publisher[P]:
        """Publisher for things that must arrive (events, estop): reliable, blocks when congested."""
        return self._keep(Publisher(self, key, ptype, realtime=False))

    def put(self, key: str, payload: wire.Payload, realtime: bool = False) -> None:
        """One-off publication, numbered per key as a publisher's samples are (this session's own id)."""
        with self._lock:
            seq = self._put_seq[key] = self._put_seq.get(key, 0) + 1
        self.session.put(
            key,
            payload.encode(),
            encoding=zenoh.Encoding(payload.encoding()),
            congestion_control=zenoh.CongestionControl.DROP if realtime else zenoh.CongestionControl.BLOCK,
            attachment=STAMP.pack(self._put_id, seq),
        )

    # -- subscribing ------------------------------------------------------------------------------
    def subscribe(
        self,
        keyexpr: str,
        *,
        capacity: int = 1,
        ring: bool = True,
        typed: bool = True,
        keep_raw: bool = False,
        channel: Channel[Received[Any]] | None = None,
    ) -> Subscription:
        """Subscribe; samples are decoded (``typed``) and queued in a ring (latest) or FIFO channel.

        Undecodable samples arrive with ``payload=None`` and ``error`` set, so the caller can count and
        report them without losing the rest of the stream.  Pass ``channel`` to let several
        subscriptions feed one channel (one thread then serves them all), or a :class:`Handler` to
        handle each sample on the Zenoh thread.
        """
        ch: Channel[Received[Any]] = channel if channel is not None else Channel(capacity, ring)
        sub = Subscription(self, keyexpr, wire.decode_any if typed else None, ch, keep_raw)
        with self._lock:
            self._subscriptions.append(sub)
        return self._keep(sub)

    def lost(self) -> dict[str, int]:
        """Samples lost on the bus so far, per key, as this session's subscriptions counted them (gaps in
        their publishers' numbers; a key two subscriptions take counts once, the larger)."""
        with self._lock:
            subs = list(self._subscriptions)
            views = list(self._views)
            out = dict(self._retired_lost)
        counted = [sub.gaps.lost() for sub in subs] + [view.lost() for view in views]
        for lost in counted:
            for key, n in lost.items():
                out[key] = max(out.get(key, 0), n)
        return out

    def _retire(self, sub: Subscription) -> None:
        # A closed subscription's losses stay counted; the subscription itself is let go.
        with self._lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)
                for key, n in sub.gaps.lost().items():
                    self._retired_lost[key] = max(self._retired_lost.get(key, 0), n)

    # -- request / response -------------------------------------------------------------------------
    def serve(
        self, key: str, handler: Callable[[str, wire.Command], wire.CommandResult], *, workers: int = 1
    ) -> Queryable:
        """Answer :class:`~arena_common.core.wire.Command` queries on ``key`` with ``handler`` in own threads."""
        return self._keep(Queryable(self, key, handler, workers))

    def request(
        self, key: str, command: wire.Command, timeout: float | None = None, *, discovery: float = 2.0
    ) -> wire.CommandResult:
        """Send a command and wait for its :class:`~arena_common.core.wire.CommandResult`.

        A query that no queryable matches ends at once.  A session that has just opened may not yet know
        the routes to a server that exists, so such an empty answer is retried for up to ``discovery``
        seconds; a query that reached a server is never sent twice.  ``TIMEOUT`` then means nobody
        answered: callers tell an absent vehicle from a slow one by its presence token.
        """
        timeout = command.timeout if timeout is None else timeout
        start = time.monotonic()
        payload = command.encode()
        while True:
            sent = time.monotonic()
            replies = self.session.get(
                key,
                payload=payload,
                encoding=zenoh.Encoding(command.encoding()),
                timeout=max(timeout - (sent - start), 0.05) + 0.5,
                target=zenoh.QueryTarget.BEST_MATCHING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for reply in replies:
                if reply.ok is not None:
                    try:
                        return wire.CommandResult.decode(reply.ok.payload.to_bytes(), key)
                    except PayloadError as exc:
                        return wire.CommandResult(False, "ERROR", f"bad reply: {exc}")
                err = reply.err
                text = err.payload.to_string() if err is not None else "unknown error"
                return wire.CommandResult(False, "ERROR", text)
            now = time.monotonic()
            unrouted = now - sent < 0.25
            if not unrouted or now - start >= min(discovery, timeout):
                return wire.CommandResult(False, "TIMEOUT", f"no answer on {key} within {now - start:.1f} s")
            time.sleep(0.1)

    # -- presence -----------------------------------------------------------------------------------
    def token(self, key: str) -> zenoh.LivelinessToken:
        """Declare a liveliness token: present while this session lives."""
        return self._keep(self.session.liveliness().declare_token(key))

    def alive(self, keyexpr: str, timeout: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens alive now that match ``keyexpr``.

        In its first seconds a session may not have learnt the tokens yet: an empty answer is then
        asked again until the session is ``DISCOVERY_S`` old.
        """
        while True:
            out = [
                str(r.ok.key_expr)
                for r in self.session.liveliness().get(keyexpr, timeout=timeout)
                if r.ok is not None
            ]
            if out or time.monotonic() - self.opened > DISCOVERY_S:
                return sorted(out)
            time.sleep(0.1)

    def watch_alive(self, keyexpr: str, callback: Callable[[str, bool], None]) -> Any:
        """Call ``callback(key, alive)`` when a matching token appears or vanishes (also for current ones)."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        return self._keep(self.session.liveliness().declare_subscriber(keyexpr, on_sample, history=True))

    # -- lifetime -----------------------------------------------------------------------------------
    def _keep(self, obj: Any) -> Any:
        with self._lock:
            self._closables.append(obj)
        return obj

    def _undeclare_all(self) -> None:
        with self._lock:
            items, self._closables = self._closables, []
        for obj in reversed(items):
            try:
                (obj.close if hasattr(obj, "close") else obj.undeclare)()
            except Exception:
                pass

    def close(self) -> None:
        """Undeclare everything and close the session."""
        self._undeclare_all()
        try:
            self.session.close()
        except Exception:
            pass

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Queryable:
    """Serves commands on a key: queries are queued and answered by worker threads, never in callbacks."""

    def __init__(
        self, bus: Bus, key: str, handler: Callable[[str, wire.Command], wire.CommandResult], workers: int
    ) -> None:
        self.key = key
        self.handler = handler
        self.channel: Channel[zenoh.Query] = Channel(64, ring=False)
        self._q = bus.session.declare_queryable(key, self.channel.put)
        self._threads = [
            threading.Thread(target=self._work, name=f"serve:{key}", daemon=True) for _ in range(workers)
        ]
        for t in self._threads:
            t.start()

    def _work(self) -> None:
        while not self.channel.closed:
            query = self.channel.get(0.5)
            if query is None:
                continue
            key = str(query.key_expr)
            try:
                raw = query.payload.to_bytes() if query.payload is not None else b""
                encoding = str(query.encoding) if query.encoding is not None else ""
                try:
                    if encoding and wire.type_for_encoding(encoding) is not wire.Command:
                        raise PayloadError(
                            f"a query must carry {wire.Command.encoding()}, not {encoding!r}",
                            key=key,
                            type_name="Command",
                        )
                    command = wire.Command.decode(raw, key)
                except PayloadError as exc:
                    result = wire.CommandResult(False, "ERROR", str(exc))
                else:
                    try:
                        result = self.handler(key, command)
                    except Exception as exc:  # a handler bug must not kill the server
                        result = wire.CommandResult(False, "ERROR", f"{type(exc).__name__}: {exc}")
                # Reply on our own key when concrete, so a wildcard query learns who answered.
                query.reply(
                    key if "*" in self.key else self.key,
                    result.replace(t=wire.now_ns()).encode(),
                    encoding=zenoh.Encoding(wire.CommandResult.encoding()),
                )
            except Exception:
                pass  # the querier went away; nothing to answer
            finally:
                query.drop()

    def close(self) -> None:
        self.channel.close()
        try:
            self._q.undeclare()
        except Exception:
            pass


def _open_session(conf: zenoh.Config) -> zenoh.Session:
    """``zenoh.open`` in a thread of its own: a client waits up to 10 s for its router inside it, and the
    caller's thread stays where a signal reaches it (Ctrl-C stops the process at once, not after that wait)."""
    opened: list[zenoh.Session] = []
    failed: list[Exception] = []

    def run() -> None:
        try:
            opened.append(zenoh.open(conf))
        except Exception as exc:
            failed.append(exc)

    thread = threading.Thread(target=run, name="zenoh-open", daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(0.1)
    if failed or not opened:
        raise BusError(f"cannot open the Zenoh session: {failed[0] if failed else 'no session'}") from None
    return opened[0]


def open_bus(
    spec: ZenohSpec | None = None, options: BusOptions | None = None, *, connect_wait: float = 2.0
) -> Bus:
    """Open a Zenoh session from the config's Zenoh section and command-line overrides.

    When it has endpoints to connect to, wait up to ``connect_wait`` seconds for the first link (it
    keeps trying in the background after that: services may start before the router).
    """
    session = _open_session(zenoh_config(spec, options))
    # A session that will connect somewhere is useful once linked: give it a moment (bounded), so that a
    # first query or presence look-up does not run before the first link is up.
    if (options and options.connect) or (spec and spec.connect):
        deadline = time.monotonic() + connect_wait
        while time.monotonic() < deadline:
            info = session.info
            if list(info.routers_zid()) or list(info.peers_zid()):
                break
            time.sleep(0.01)
    return Bus(session)
