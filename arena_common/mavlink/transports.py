"""Raw byte transports of a MAVLink link: UDP (in/out), TCP (client/server), serial ports, pymavlink's others.

:func:`open_transport` opens one from a connection string; :class:`~arena_common.mavlink.link.MavlinkLink`
frames, checks and routes what flows through it.
"""

from __future__ import annotations

import socket
from abc import ABC, abstractmethod
from typing import Any

from arena_common.core.errors import ArenaError

__all__ = ["SERIAL_DEFAULT_BAUD", "MavlinkLinkError", "open_transport", "parse_serial"]


class MavlinkLinkError(ArenaError):
    """A MAVLink connection string that cannot be used, or a link that cannot be opened."""


def _host_port(rest: str, url: str) -> tuple[str, int]:
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise MavlinkLinkError(f"MAVLink connection {url!r}: expected HOST:PORT after the scheme")
    return host, int(port)


class _Transport(ABC):
    """Raw bytes in and out of one kind of connection."""

    stream = True

    @abstractmethod
    def fileno(self) -> int | None:
        """The descriptor to wait on, if any."""

    @abstractmethod
    def read(self) -> list[tuple[bytes, Any]]:
        """Whatever is waiting, as (bytes, source address) chunks; never blocks."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send bytes to the peer."""

    @abstractmethod
    def close(self) -> None:
        """Release the connection."""

    def can_send(self) -> bool:
        return True

    def accept_source(self, address: Any) -> None:  # noqa: B027 - optional hook, a no-op by default
        """The vehicle's own frames came from ``address``."""


class _Udp(_Transport):
    stream = False

    def __init__(self, host: str, port: int, listen: bool) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            if listen:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((host, port))
                self.peer: tuple[str, int] | None = None
            else:
                self.peer = (socket.gethostbyname(host), port)
        except OSError:
            self.sock.close()
            raise
        self.listen = listen

    def fileno(self) -> int | None:
        return self.sock.fileno()

    def read(self) -> list[tuple[bytes, Any]]:
        out: list[tuple[bytes, Any]] = []
        for _ in range(256):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                continue  # an ICMP error for an earlier datagram (udpout with nobody listening)
            out.append((data, addr))
        return out

    def write(self, data: bytes) -> None:
        if self.peer is not None:
            self.sock.sendto(data, self.peer)

    def can_send(self) -> bool:
        return self.peer is not None

    def accept_source(self, address: Any) -> None:
        if self.listen:
            self.peer = address

    def close(self) -> None:
        self.sock.close()


class _TcpClient(_Transport):
    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.create_connection((host, port), timeout=2.0)
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.closed_by_peer = False

    def fileno(self) -> int | None:
        return None if self.closed_by_peer else self.sock.fileno()

    def read(self) -> list[tuple[bytes, Any]]:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:
            data = b""
        if not data:
            self.closed_by_peer = True
            return []
        return [(data, None)]

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)

    def close(self) -> None:
        self.sock.close()


class _TcpServer(_Transport):
    def __init__(self, host: str, port: int) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, port))
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.client: socket.socket | None = None

    def fileno(self) -> int | None:
        return (self.client or self.listener).fileno()

    def read(self) -> list[tuple[bytes, Any]]:
        if self.client is None:
            try:
                self.client, _ = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return []
            self.client.setblocking(False)
            self.client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            data = self.client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:
            data = b""
        if not data:
            self.client.close()
            self.client = None
            return []
        return [(data, None)]

    def write(self, data: bytes) -> None:
        if self.client is not None:
            self.client.sendall(data)

    def can_send(self) -> bool:
        return self.client is not None

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        self.listener.close()


SERIAL_DEFAULT_BAUD = 57600


def parse_serial(rest: str, url: str) -> tuple[str, int]:
    """(device, baud) of the part after ``serial:``; :class:`MavlinkLinkError` naming what is wrong."""
    device, sep, baud = rest.rpartition(":")
    if not sep or not baud.isdigit():
        device, baud = rest, str(SERIAL_DEFAULT_BAUD)
    if not device:
        raise MavlinkLinkError(f"MAVLink connection {url!r}: expected serial:DEVICE[:BAUD]")
    if not 50 <= int(baud) <= 20_000_000:
        raise MavlinkLinkError(f"MAVLink connection {url!r}: baud rate {baud} out of 50..20000000")
    return device, int(baud)


class _Serial(_Transport):
    """A serial port (or a pseudo-terminal), raw bytes, never blocking."""

    def __init__(self, device: str, baud: int) -> None:
        import serial  # pyserial: only serial links need it

        self.port = serial.Serial(
            device, baud, timeout=0, write_timeout=1.0, rtscts=False, dsrdtr=False, xonxoff=False
        )
        self.eof = False

    def fileno(self) -> int | None:
        return None if self.eof else int(self.port.fileno())

    def read(self) -> list[tuple[bytes, Any]]:
        try:
            data = self.port.read(self.port.in_waiting or 1)
        except OSError:  # pyserial's SerialException: readable but nothing (the other end went away)
            self.eof = True
            return []
        return [(bytes(data), None)] if data else []

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def close(self) -> None:
        self.port.close()


class _Pymavlink(_Transport):
    """Serial ports and anything else pymavlink opens, used as a raw byte pipe."""

    def __init__(self, url: str) -> None:
        device, baud = url, 57600
        head, sep, tail = url.rpartition(":")
        if sep and tail.isdigit() and (head.startswith("/dev/") or head.upper().startswith("COM")):
            device, baud = head, int(tail)
        from pymavlink import mavutil  # only serial links need it (and it pulls in numpy)

        self.conn: Any = mavutil.mavlink_connection(device, baud=baud, autoreconnect=False)

    def fileno(self) -> int | None:
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def read(self) -> list[tuple[bytes, Any]]:
        data = self.conn.recv(4096)
        if isinstance(data, str):
            data = data.encode("latin-1")
        return [(bytes(data), None)] if data else []

    def write(self, data: bytes) -> None:
        self.conn.write(data)

    def close(self) -> None:
        self.conn.close()


def open_transport(url: str) -> _Transport:
    """Open the raw transport of a pymavlink connection string; :class:`MavlinkLinkError` if impossible."""
    if not isinstance(url, str) or not url.strip():
        raise MavlinkLinkError(f"MAVLink connection string must be a non-empty string, got {url!r}")
    scheme, sep, rest = url.partition(":")
    try:
        if sep and scheme in ("udpin", "udp"):
            return _Udp(*_host_port(rest, url), listen=True)
        if sep and scheme == "udpout":
            return _Udp(*_host_port(rest, url), listen=False)
        if sep and scheme == "tcp":
            return _TcpClient(*_host_port(rest, url))
        if sep and scheme == "tcpin":
            return _TcpServer(*_host_port(rest, url))
        if sep and scheme == "serial":
            return _Serial(*parse_serial(rest, url))
        return _Pymavlink(url)
    except MavlinkLinkError:
        raise
    except (OSError, ValueError) as exc:
        raise MavlinkLinkError(f"cannot open MAVLink connection {url!r}: {exc}") from None
