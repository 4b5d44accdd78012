"""Both names of the Foxglove WebSocket protocol on one port: :class:`SubprotocolBridge`.

The Foxglove SDK's server (``foxglove.start_server``) accepts only the subprotocol ``foxglove.sdk.v1``
and answers HTTP 400 to a client that offers only the older name ``foxglove.websocket.v1`` (older
Lichtblick, PlotJuggler, roslibjs-foxglove), although both name the same protocol (Foxglove's stance,
quoted in Lichtblick's pull request 819).  The bridge listens where the viewer should, relays every TCP
connection to the SDK's server on loopback, and rewrites only the opening handshake: a request that
offers the old name but not the new one is passed on offering the new one, and the answer names the
old one again.  Every byte after the handshake passes unchanged.
"""

from __future__ import annotations

import logging
import re
import socket
import threading

__all__ = ["LEGACY", "SDK", "SubprotocolBridge", "rewrite_request", "rewrite_response"]

SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
MAX_HEAD = 65536  # bytes of an HTTP head; a longer one is passed on unchanged
_HEADER = re.compile(rb"^sec-websocket-protocol[ \t]*:(.*)$", re.IGNORECASE | re.MULTILINE)
log = logging.getLogger("arena_common.recording")


def _read_head(sock: socket.socket) -> tuple[bytes, tuple[bytes, bytes] | None]:
    """What ``sock`` sends until an HTTP head is complete (at most :data:`MAX_HEAD` bytes), and the head
    split from what follows it (None: no complete head within the limit)."""
    data, split = b"", None
    while split is None and len(data) < MAX_HEAD:
        chunk = sock.recv(4096)
        if not chunk:
            raise OSError("closed during the handshake")
        data += chunk
        split = _split_head(data)
    return data, split


def _split_head(data: bytes) -> tuple[bytes, bytes] | None:
    end = data.find(b"\r\n\r\n")
    return None if end < 0 else (data[: end + 4], data[end + 4 :])


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """The handshake request to pass on, and whether the client offered only the old name."""
    offered = [t.strip() for m in _HEADER.finditer(head) for t in m.group(1).decode("latin-1").split(",")]
    if LEGACY not in offered or SDK in offered:
        return head, False
    return _HEADER.sub(
        lambda m: b"Sec-WebSocket-Protocol: " + m.group(1).replace(LEGACY.encode(), SDK.encode()), head
    ), True


def rewrite_response(head: bytes) -> bytes:
    """The handshake answer for a client that offered only the old name."""
    return _HEADER.sub(lambda m: b"Sec-WebSocket-Protocol: " + LEGACY.encode() + b"\r", head)


class SubprotocolBridge:
    """Listens on ``address:port`` (0: a free port, see :attr:`port`) and relays each connection to
    ``127.0.0.1:inner_port``, translating the subprotocol's old name (see the module)."""

    def __init__(self, address: str, port: int, inner_port: int) -> None:
        self.inner_port = inner_port
        self._sock = socket.create_server((address, port), reuse_port=False)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self.connections = 0
        self.legacy = 0  # connections that offered only foxglove.websocket.v1
        self._thread = threading.Thread(target=self._accept, name="viewer-bridge", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The TCP port the bridge listens on."""
        return int(self._sock.getsockname()[1])

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), name="viewer-client", daemon=True).start()

    def _track(self, *socks: socket.socket) -> None:
        with self._lock:
            self._open.update(socks)

    def _serve(self, client: socket.socket) -> None:
        try:
            server = socket.create_connection(("127.0.0.1", self.inner_port), timeout=5.0)
        except OSError as exc:
            log.warning("viewer: cannot reach the Foxglove server: %s", exc)
            client.close()
            return
        server.settimeout(None)
        self._track(client, server)
        try:
            legacy = self._handshake(client, server)
        except OSError:
            self._close(client, server)
            return
        self.connections += 1
        self.legacy += legacy
        threading.Thread(target=self._pump, args=(server, client), daemon=True).start()
        self._pump(client, server)

    def _handshake(self, client: socket.socket, server: socket.socket) -> bool:
        """Pass the request on (rewritten when needed), then the answer; True for an old-name client."""
        data, split = _read_head(client)
        if split is None:
            server.sendall(data)
            return False
        head, legacy = rewrite_request(split[0])
        server.sendall(head + split[1])
        if not legacy:
            return False
        data, split = _read_head(server)
        client.sendall(data if split is None else rewrite_response(split[0]) + split[1])
        return True

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while chunk := src.recv(65536):
                dst.sendall(chunk)
        except OSError:
            pass
        self._close(src, dst)

    def _close(self, *socks: socket.socket) -> None:
        for s in socks:
            with self._lock:
                self._open.discard(s)
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def close(self) -> None:
        """Stop listening and drop every relayed connection."""
        self._stop.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        with self._lock:
            socks = list(self._open)
        self._close(*socks)
        self._thread.join(2.0)
