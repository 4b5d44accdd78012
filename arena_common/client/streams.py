"""Streams and callbacks: every new item of one source, in order.

A :class:`Topic` is one source of a vehicle (its mocap poses, vision, state, events, a telemetry
message…).  The arena's client thread publishes each item to it as it arrives: the topic keeps the
latest, appends it to every open :class:`Stream` and calls every callback, in arrival order.

- ``for pose in d1.poses():`` — a :class:`Stream` is an iterator with its own bounded queue: a slow
  reader loses the oldest items (counted in :attr:`Stream.dropped`), never the newest.
- ``d1.on_pose(fn)`` — callbacks run on the arena's client thread, one after the other: keep them short
  (hand work to your own thread).  An exception in a callback is logged and counted
  (:attr:`Topic.errors`); the callback stays registered and the stream goes on.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterator
from types import TracebackType
from typing import Generic, TypeVar

from arena_common.core.errors import ArenaError

__all__ = ["Callback", "Stream", "StreamClosed", "StreamTimeout", "Topic"]

T = TypeVar("T")
log = logging.getLogger("arena_common.client")


class StreamTimeout(ArenaError, TimeoutError):
    """Nothing new arrived on a stream within its timeout."""


class StreamClosed(ArenaError):
    """A stream read after its arena (or the stream itself) was closed."""


class Stream(Generic[T]):
    """An iterator over the items of one :class:`Topic` that arrive after it was opened.

    ``timeout`` (seconds, None = wait forever) bounds the wait for each item: iteration raises
    :class:`StreamTimeout` naming the source when nothing arrives in time.  Iteration ends when the
    stream or its arena is closed.  Use it as a context manager (or call :meth:`close`) to stop receiving.
    """

    def __init__(self, topic: Topic[T], capacity: int = 1024, timeout: float | None = None) -> None:
        if capacity < 1:
            raise ValueError("stream capacity must be at least 1")
        self.topic = topic
        self.capacity = capacity
        self.timeout = timeout
        self.dropped = 0
        self.received = 0
        self._items: collections.deque[T] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False

    def _put(self, item: T) -> None:
        with self._cond:
            if self._closed:
                return
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self.received += 1
            self._cond.notify()

    def get(self, timeout: float | None = None) -> T | None:
        """The next item, or None after ``timeout`` seconds or once closed with nothing left."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._items:
                if self._closed:
                    return None
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left if left is not None else 0.5)
            return self._items.popleft()

    def drain(self) -> list[T]:
        """Every item waiting now, without blocking."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        item = self.get(self.timeout)
        if item is not None:
            return item
        if self._closed:
            raise StopIteration
        raise StreamTimeout(f"{self.topic.name}: nothing new within {self.timeout:.1f} s")

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop receiving; a reader waiting in :meth:`get` wakes up."""
        self.topic._remove(self)
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __enter__(self) -> Stream[T]:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<Stream {self.topic.name} waiting={len(self._items)} dropped={self.dropped}>"


class Callback:
    """A registered callback; :meth:`cancel` removes it."""

    def __init__(self, topic: Topic[object], fn: Callable[[object], object]) -> None:
        self.topic = topic
        self.fn = fn

    def cancel(self) -> None:
        self.topic._remove_callback(self)


class Topic(Generic[T]):
    """One source of items: the latest, its arrival time, open streams and callbacks."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.latest: T | None = None
        self.received = 0.0  # time.monotonic() of the latest
        self.count = 0
        self.errors = 0
        self._streams: list[Stream[T]] = []
        self._callbacks: list[Callback] = []
        self._close_hooks: list[Callable[[], object]] = []
        self._cond = threading.Condition()
        self._closed = False

    def publish(self, item: T) -> None:
        """Record ``item`` as the latest, queue it on every stream, call every callback (in that order)."""
        with self._cond:
            self.latest = item
            self.received = time.monotonic()
            self.count += 1
            streams = list(self._streams)
            callbacks = list(self._callbacks)
            self._cond.notify_all()
        for s in streams:
            s._put(item)
        for cb in callbacks:
            try:
                cb.fn(item)
            except Exception:
                self.errors += 1
                log.exception("%s: callback %r failed (it stays registered)", self.name, cb.fn)

    def stream(self, capacity: int = 1024, timeout: float | None = None) -> Stream[T]:
        """A new :class:`Stream` of the items arriving from now on."""
        s: Stream[T] = Stream(self, capacity, timeout)
        with self._cond:
            if self._closed:
                s._closed = True
            else:
                self._streams.append(s)
        return s

    def on(self, fn: Callable[[T], object]) -> Callback:
        """Call ``fn(item)`` for every new item (on the arena's client thread); returns a handle."""
        cb = Callback(self, fn)  # type: ignore[arg-type]
        with self._cond:
            self._callbacks.append(cb)
        return cb

    def on_close(self, fn: Callable[[], object]) -> None:
        """Call ``fn()`` when the topic closes (at once if it is closed already)."""
        with self._cond:
            if not self._closed:
                self._close_hooks.append(fn)
                return
        fn()

    def wait(self, timeout: float) -> T | None:
        """The latest item, waiting up to ``timeout`` s for a first one."""
        with self._cond:
            self._cond.wait_for(lambda: self.latest is not None or self._closed, timeout)
            return self.latest

    @property
    def age(self) -> float:
        """Seconds since the latest item arrived (inf before any)."""
        return time.monotonic() - self.received if self.count else float("inf")

    def _remove(self, s: Stream[T]) -> None:
        with self._cond:
            if s in self._streams:
                self._streams.remove(s)

    def _remove_callback(self, cb: Callback) -> None:
        with self._cond:
            if cb in self._callbacks:
                self._callbacks.remove(cb)

    def close(self) -> None:
        """Close every stream (their iteration ends) and forget the callbacks."""
        with self._cond:
            self._closed = True
            streams, self._streams = self._streams, []
            hooks, self._close_hooks = self._close_hooks, []
            self._callbacks.clear()
            self._cond.notify_all()
        for s in streams:
            with s._cond:
                s._closed = True
                s._cond.notify_all()
        for fn in hooks:
            try:
                fn()
            except Exception:
                log.exception("%s: close hook %r failed", self.name, fn)
