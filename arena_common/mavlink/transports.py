"""Raw byte transports of a MAVLink link: UDP (in/out), TCP (client/server), serial ports, pymavlink's others.

:func:`open_transport` opens one from a connection string; :class:`~arena_common.mavlink.link.MavlinkLink`
frames, checks and routes what flows through it.

A listening UDP transport (``udpin:``) sends to the address the link last accepted
(:meth:`_Transport.accept_source`), unless its peer is *pinned* (``peer="IP:PORT"``,
:func:`parse_peer`): then it sends there from the start, never anywhere else, and
:meth:`_Transport.source_allowed` refuses datagrams from every other address.
"""

from __future__ import annotations

import ipaddress
import os
import re
import socket
from abc import ABC, abstractmethod
from typing import Any

from arena_common.core.errors import ArenaError

__all__ = [
    "SERIAL_DEFAULT_BAUD",
    "MavlinkLinkError",
    "check_peer",
    "open_transport",
    "parse_peer",
    "parse_serial",
]


class MavlinkLinkError(ArenaError):
    """A MAVLink connection string that cannot be used, or a link that cannot be opened."""


def _host_port(rest: str, url: str) -> tuple[str, int]:
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise MavlinkLinkError(f"MAVLink connection {url!r}: expected HOST:PORT after the scheme")
    return host, int(port)


_PEER = re.compile(r"([0-9.]+):([0-9]{1,5})", re.ASCII)
_PINNABLE = ("udpin", "udp")


def parse_peer(text: str) -> tuple[str, int]:
    """The (IPv4 address, port) of a pinned peer ``"IP:PORT"``; :class:`MavlinkLinkError` if it is not one.

    An address, not a host name: a name would be resolved through the very network the pin guards.
    """
    m = _PEER.fullmatch(text) if isinstance(text, str) else None
    try:
        ip = ipaddress.IPv4Address(m.group(1)) if m is not None else None
    except ValueError:
        ip = None
    if m is None or ip is None or not 0 < int(m.group(2)) < 65536:
        raise MavlinkLinkError(
            f"MAVLink peer {text!r}: expected the autopilot's IPv4 address and port, IP:PORT"
        )
    if ip.is_unspecified or ip.is_multicast or ip == ipaddress.IPv4Address("255.255.255.255"):
        raise MavlinkLinkError(f"MAVLink peer {text!r}: {ip} is not the address of one host")
    return str(ip), int(m.group(2))


def check_peer(url: str, peer: str | None) -> tuple[str, int] | None:
    """The pinned peer of connection ``url`` (None: not pinned); :class:`MavlinkLinkError` when ``peer``
    is not an address or ``url`` is not a listening UDP link (the only kind whose peer moves)."""
    if peer is None:
        return None
    if url.partition(":")[0] not in _PINNABLE:
        raise MavlinkLinkError(
            f"MAVLink connection {url!r}: a peer can be pinned on udpin:HOST:PORT links only"
        )
    return parse_peer(peer)


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
        """The vehicle's own trusted frames came from ``address`` (a listening UDP link replies there)."""

    def source_allowed(self, address: Any) -> bool:
        """Whether a chunk read from ``address`` may be used at all (False: not the pinned peer)."""
        return True

    def kernel_drops(self) -> int | None:
        """Datagrams the system dropped before anything read them (the receive buffer full); None where
        the transport keeps no such count."""
        return None


class _Udp(_Transport):
    stream = False

    def __init__(self, host: str, port: int, listen: bool, pinned: tuple[str, int] | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            if listen:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((host, port))
                self.peer: tuple[str, int] | None = pinned
            else:
                self.peer = (socket.gethostbyname(host), port)
        except OSError:
            self.sock.close()
            raise
        self.listen = listen
        self.pinned = listen and pinned is not None

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
        if self.listen and not self.pinned:
            self.peer = address

    def source_allowed(self, address: Any) -> bool:
        return not self.pinned or address == self.peer

    def kernel_drops(self) -> int | None:
        return udp_drops(self.sock)

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


def udp_drops(sock: socket.socket) -> int | None:
    """The datagrams Linux dropped for ``sock`` since it opened (its receive buffer full): the ``drops``
    column of ``/proc/net/udp``; None where the system does not say."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
        with open("/proc/net/udp") as table:
            for line in table:
                fields = line.split()
                if len(fields) > 12 and fields[9] == inode:
                    return int(fields[12])
    except (OSError, ValueError):
        pass
    return None


def open_transport(url: str, peer: str | None = None) -> _Transport:
    """Open the raw transport of a pymavlink connection string; :class:`MavlinkLinkError` if impossible.

    ``peer`` (``"IP:PORT"``, ``udpin:`` only) pins the address a listening UDP link talks to.
    """
    if not isinstance(url, str) or not url.strip():
        raise MavlinkLinkError(f"MAVLink connection string must be a non-empty string, got {url!r}")
    pinned = check_peer(url, peer)
    scheme, sep, rest = url.partition(":")
    try:
        if sep and scheme in _PINNABLE:
            return _Udp(*_host_port(rest, url), listen=True, pinned=pinned)
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
