"""The unicast clients of the Motive emulator: who is subscribed, and the sockets their frames leave from.

**Where Motive sends unicast frames** (docs/architecture.md, "NatNet unicast", has the evidence): to the
address the client's CONNECT came from — its IP *and* port, so the socket that sent CONNECT — and nowhere
else, from the socket Motive binds to its data port. NatNet 3.0 and 3.1 (Motive 2.x) and NatNet 4.0 and 4.1
(Motive 3.x) do the same, whatever the client: the unicast server of OptiTrack's NatNet library (3.0, 3.1
and 4.1) keeps each client's CONNECT source address and sends every frame there from its data-port socket,
and every unicast client OptiTrack ships (the NatNet library 3.x and 4.x, PacketClient, PythonClient) reads
frames on the socket that sent CONNECT, the library taking a datagram for a streamed frame only when it comes
from the server's data port. Nothing is sent to the data port of the client's address: a client that listens
there (libmotioncapture's unicast mode) gets no frame from Motive, nor from the emulator.

So each client's frames leave from a socket bound to the data port and connected to the client (one per
client, so that it never takes datagrams meant for another process listening on that port on this computer;
where the data port cannot be bound, from an ephemeral port, with a warning).

**SERVERINFO first.** A client gets no frame before the SERVERINFO that answers its CONNECT: the answer is
sent before the client joins the frame targets, under the lock every frame send holds, so no frame can come
between (a CONNECT from a subscribed address stops its frames until the answer is out). A KEEPALIVE from an
address that is not subscribed (a client that outlived a server restart) subscribes it again, likewise after
a SERVERINFO.
"""

from __future__ import annotations

import collections
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from arena_common.mocap.natnet import ConnectRequest, Version

__all__ = ["ClientInfo", "SendResult", "Subscriptions"]

log = logging.getLogger("arena.natnet_server")

Address = tuple[str, int]


@dataclass(slots=True)
class ClientInfo:
    """A client that sent CONNECT: where it is, what it said it is, where its frames go, when last heard."""

    address: Address
    app_name: str = ""
    natnet_version: Version | None = None
    connected: float = field(default_factory=time.monotonic)
    last_seen: float = field(default_factory=time.monotonic)
    keeps_alive: bool = False
    frames_to: Address = ("", 0)  # where its unicast frames go: ``address``, as Motive does


@dataclass(slots=True)
class SendResult:
    """What one frame send did: datagrams sent, failures ``(address, error)``, clients found gone."""

    sent: int = 0
    failures: list[tuple[Address, OSError]] = field(default_factory=list)
    gone: list[Address] = field(default_factory=list)


LEFT_KEPT = 64  # clients that left, kept for who asks what they had declared


class Subscriptions:
    """The subscribed clients of a NatNet server and, in unicast, the sockets their frames leave from.

    ``host`` and ``data_port`` are the server's address and data port. In multicast (``unicast=False``) the
    clients are only recorded; :meth:`send` is for unicast. Thread-safe: the command thread subscribes and
    unsubscribes while another thread sends frames.
    """

    def __init__(self, *, host: str, data_port: int, unicast: bool, client_timeout: float | None) -> None:
        self.host, self.data_port, self.unicast = host, int(data_port), bool(unicast)
        self.client_timeout = client_timeout
        self._lock = threading.Lock()  # the clients, their sockets, and every unicast send
        self._clients: dict[Address, ClientInfo] = {}
        self._left: collections.deque[ClientInfo] = collections.deque(maxlen=LEFT_KEPT)
        self._socks: dict[Address, socket.socket] = {}  # per client: bound to the data port, connected
        self._spare: socket.socket | None = None  # for a client whose own socket could not be made
        self._warned_port = False

    # -- life cycle --------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the spare socket frames leave from when a client's own cannot be made (unicast only)."""
        if not self.unicast or self._spare is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, 0))
        except OSError:
            sock.close()
            raise
        self._spare = sock

    def close(self) -> None:
        """Close every socket and forget the clients."""
        with self._lock:
            for sock in (*self._socks.values(), self._spare):
                if sock is not None:
                    sock.close()
            self._socks.clear()
            self._spare = None
            self._clients.clear()

    # -- state -------------------------------------------------------------------------------------
    def clients(self) -> list[ClientInfo]:
        """Copies of the subscribed clients."""
        with self._lock:
            return [replace(c) for c in self._clients.values()]

    def left(self) -> list[ClientInfo]:
        """Copies of the clients that left, timed out or were found gone, oldest first (the last ``LEFT_KEPT``)."""
        with self._lock:
            return [replace(c) for c in self._left]

    def __len__(self) -> int:
        return len(self._clients)

    def seen(self, address: Address, now: float) -> None:
        """Note that ``address`` was heard from at ``now``."""
        with self._lock:
            client = self._clients.get(address)
            if client is not None:
                client.last_seen = now

    # -- subscription ------------------------------------------------------------------------------
    def connect(
        self, address: Address, hello: ConnectRequest, now: float, answer: Callable[[], None]
    ) -> bool:
        """Subscribe ``address`` after ``answer()`` sent it SERVERINFO; ``True`` if it was not subscribed."""
        client = ClientInfo(address, hello.app_name, hello.natnet_version, now, now)
        with self._lock:
            old = self._clients.pop(address, None)  # no frame to it until its SERVERINFO is out
            answer()
            if old is not None:
                client.keeps_alive = old.keeps_alive
            self._add(client)
        return old is None

    def keepalive(self, address: Address, now: float, answer: Callable[[], None]) -> bool:
        """A KEEPALIVE from ``address``; an unknown one is subscribed again after ``answer()``: ``True``."""
        with self._lock:
            client = self._clients.get(address)
            if client is not None:
                client.keeps_alive = True
                return False
            answer()
            self._add(ClientInfo(address, connected=now, last_seen=now, keeps_alive=True))
        return True

    def disconnect(self, address: Address) -> bool:
        """Unsubscribe ``address``; ``True`` if it was subscribed."""
        with self._lock:
            return self._remove(address)

    def expire(self, now: float) -> list[Address]:
        """Forget the clients that keep alive but were silent for ``client_timeout``; their addresses."""
        if self.client_timeout is None:
            return []
        with self._lock:
            silent = [
                a
                for a, c in self._clients.items()
                if c.keeps_alive and now - c.last_seen > self.client_timeout
            ]
            for address in silent:
                self._remove(address)
        return silent

    def _add(self, client: ClientInfo) -> None:
        """Record ``client`` and open the socket its frames leave from (lock held)."""
        address = client.address
        old = self._socks.pop(address, None)
        if old is not None:
            old.close()
        client.frames_to = address
        if self.unicast:
            sock = self._data_port_socket(address)
            if sock is not None:
                self._socks[address] = sock
        self._clients[address] = client

    def _remove(self, address: Address) -> bool:
        sock = self._socks.pop(address, None)
        if sock is not None:
            sock.close()
        client = self._clients.pop(address, None)
        if client is not None:
            self._left.append(client)
        return client is not None

    def _data_port_socket(self, address: Address) -> socket.socket | None:
        """A socket bound to the data port and connected to ``address`` (``None``: use the spare one).

        ``SO_REUSEADDR`` lets it share the port with other such sockets and with clients listening on it on
        this computer; being connected, it receives nothing from anyone else, so it takes no datagram meant
        for them.
        """
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((self.host, self.data_port))
            except OSError as exc:
                if not self._warned_port:
                    self._warned_port = True
                    log.warning(
                        "cannot send unicast frames from data port %s:%d (%s): NatNet SDK clients take "
                        "frames from another port for replies, not for the stream",
                        self.host,
                        self.data_port,
                        exc.strerror or exc,
                    )
                sock.bind((self.host, 0))
            sock.connect(address)
        except OSError as exc:
            sock.close()
            log.debug("no frame socket for %s:%d: %s", *address, exc)
            return None
        return sock

    # -- frames ------------------------------------------------------------------------------------
    def send(self, datagram: bytes) -> SendResult:
        """Send ``datagram`` to every subscribed client (unicast), to the address its CONNECT came from.

        A client whose port is closed (the kernel reports the ICMP port-unreachable on its connected socket)
        is forgotten: its address is in ``gone``.
        """
        result = SendResult()
        with self._lock:
            for address, client in list(self._clients.items()):
                sock = self._socks.get(address)
                try:
                    if sock is not None:
                        sock.send(datagram)
                    elif self._spare is not None:
                        self._spare.sendto(datagram, client.frames_to)
                    else:
                        continue
                    result.sent += 1
                except ConnectionRefusedError:
                    self._remove(address)
                    result.gone.append(address)
                except OSError as exc:
                    result.failures.append((client.frames_to, exc))
        return result
