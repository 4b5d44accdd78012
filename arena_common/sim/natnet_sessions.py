"""The unicast clients of the Motive emulator: who is subscribed, where its frames go, from which socket.

Motive serves two generations of NatNet client in unicast, and each reads its frames somewhere else:

* **NatNet 4 SDK clients** — the NatNet SDK 4.x library, its PacketClient and PythonClient samples (PyPI
  ``natnetsdk``). Their "data socket" is bound to port 0 and never read: the command thread reads the frames
  on the socket that sent CONNECT and sends a KEEPALIVE after each receive. So their frames go to the CONNECT
  source address. The SDK library takes a unicast datagram for a frame only when it comes from the server's
  data port (the 4.1 Linux library connects, but receives no frame at all, when frames come from the command
  port), so those frames leave from a socket bound to the data port — one per client, connected to it, so
  that it never takes datagrams meant for another process listening on that port on the same computer.
* **Older clients** — NatNet SDK ≤ 3.x and the depacketizers written after it (libmotioncapture, PyPI
  ``motioncapture``). They send an empty or 264-byte CONNECT and never a KEEPALIVE, read SERVERINFO and
  MODELDEF as the next datagrams on their command socket, then listen for frames on the data port SERVERINFO
  announces. Their frames go to the client's address at the server's data port, never to the command socket
  (where libmotioncapture would take a frame for the MODELDEF it waits for).

How Motive tells them apart is not documented; the emulator goes by what only 4.x clients send: a CONNECT
with the connection options after the 264-byte sender block (:data:`NATNET4_CONNECT_SIZE` bytes or more), or
one declaring NatNet 4 or later, or a KEEPALIVE.

**SERVERINFO first.** A client gets no frame before the SERVERINFO that answers its CONNECT: the answer is
sent before the client joins the frame targets, under the lock every frame send holds, so no frame can come
between (a CONNECT from a subscribed address stops its frames until the answer is out). A KEEPALIVE from an
address that is not subscribed (a client that outlived a server restart) subscribes it again, likewise after
a SERVERINFO.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from arena_common.mocap.natnet import ConnectRequest, Version

__all__ = ["NATNET4_CONNECT_SIZE", "ClientInfo", "SendResult", "Subscriptions", "is_natnet4_client"]

log = logging.getLogger("arena.natnet_server")

#: CONNECT payload size from which a client is a NatNet 4 SDK client: the 264-byte sender block (name, app
#: and NatNet versions) followed by the 5-byte connection options (subscribed-data-only flag, bitstream
#: version) that the 4.x SDK added. The PythonClient sample sends 271 bytes, PacketClient 273, the SDK 269.
NATNET4_CONNECT_SIZE = 269

Address = tuple[str, int]


def is_natnet4_client(hello: ConnectRequest, payload_size: int) -> bool:
    """Whether a CONNECT (decoded ``hello``, ``payload_size`` bytes) comes from a NatNet 4 SDK client."""
    declared = hello.natnet_version
    return payload_size >= NATNET4_CONNECT_SIZE or (declared is not None and declared.major >= 4)


@dataclass(slots=True)
class ClientInfo:
    """A client that sent CONNECT: where it is, what it said it is, where its frames go, when last heard."""

    address: Address
    app_name: str = ""
    natnet_version: Version | None = None
    connected: float = field(default_factory=time.monotonic)
    last_seen: float = field(default_factory=time.monotonic)
    keeps_alive: bool = False
    natnet4: bool = False  # a NatNet 4 SDK client: frames go to ``address``, else to its data port
    frames_to: Address = ("", 0)  # where its unicast frames go


@dataclass(slots=True)
class SendResult:
    """What one frame send did: datagrams sent, failures ``(address, error)``, clients found gone."""

    sent: int = 0
    failures: list[tuple[Address, OSError]] = field(default_factory=list)
    gone: list[Address] = field(default_factory=list)


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
        self._socks: dict[Address, socket.socket] = {}  # NatNet 4 clients: bound to the data port, connected
        self._legacy: socket.socket | None = None  # older clients' frames (any source port will do)
        self._warned_port = False

    # -- life cycle --------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the socket older clients' frames leave from (unicast only)."""
        if not self.unicast or self._legacy is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, 0))
        except OSError:
            sock.close()
            raise
        self._legacy = sock

    def close(self) -> None:
        """Close every socket and forget the clients."""
        with self._lock:
            for sock in (*self._socks.values(), self._legacy):
                if sock is not None:
                    sock.close()
            self._socks.clear()
            self._legacy = None
            self._clients.clear()

    # -- state -------------------------------------------------------------------------------------
    def clients(self) -> list[ClientInfo]:
        """Copies of the subscribed clients."""
        with self._lock:
            return [replace(c) for c in self._clients.values()]

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
        self, address: Address, hello: ConnectRequest, natnet4: bool, now: float, answer: Callable[[], None]
    ) -> bool:
        """Subscribe ``address`` after ``answer()`` sent it SERVERINFO; ``True`` if it was not subscribed."""
        client = ClientInfo(address, hello.app_name, hello.natnet_version, now, now, natnet4=natnet4)
        with self._lock:
            old = self._clients.pop(address, None)  # no frame to it until its SERVERINFO is out
            answer()
            if old is not None:
                client.keeps_alive = old.keeps_alive
                client.natnet4 = client.natnet4 or old.keeps_alive
            self._add(client)
        return old is None

    def keepalive(self, address: Address, now: float, answer: Callable[[], None]) -> bool:
        """A KEEPALIVE from ``address``; an unknown one is subscribed again after ``answer()``: ``True``."""
        with self._lock:
            client = self._clients.get(address)
            if client is not None:
                client.keeps_alive = True
                if not client.natnet4:  # only NatNet 4 SDK clients keep alive: frames go to them directly
                    client.natnet4 = True
                    self._add(client)
                return False
            answer()
            self._add(ClientInfo(address, connected=now, last_seen=now, keeps_alive=True, natnet4=True))
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
        """Record ``client`` and route its frames (lock held)."""
        address = client.address
        old = self._socks.pop(address, None)
        if old is not None:
            old.close()
        if client.natnet4:
            client.frames_to = address
            if self.unicast:
                sock = self._data_port_socket(address)
                if sock is not None:
                    self._socks[address] = sock
        else:
            client.frames_to = (address[0], self.data_port)
        self._clients[address] = client

    def _remove(self, address: Address) -> bool:
        sock = self._socks.pop(address, None)
        if sock is not None:
            sock.close()
        return self._clients.pop(address, None) is not None

    def _data_port_socket(self, address: Address) -> socket.socket | None:
        """A socket bound to the data port and connected to ``address`` (``None``: use the shared one).

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
                        "cannot send unicast frames from data port %s:%d (%s): NatNet 4 SDK clients may "
                        "ignore frames from another port",
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
        """Send ``datagram`` to every subscribed client (unicast).

        A NatNet 4 client whose port is closed (the kernel reports the ICMP port-unreachable on its connected
        socket) is forgotten: its address is in ``gone``.
        """
        result = SendResult()
        with self._lock:
            for address, client in list(self._clients.items()):
                sock = self._socks.get(address)
                try:
                    if sock is not None:
                        sock.send(datagram)
                    elif self._legacy is not None:
                        self._legacy.sendto(datagram, client.frames_to)
                    else:
                        continue
                    result.sent += 1
                except ConnectionRefusedError:
                    self._remove(address)
                    result.gone.append(address)
                except OSError as exc:
                    result.failures.append((client.frames_to, exc))
        return result
