"""Connection strings and endpoints: the host of a Zenoh endpoint or MAVLink link, loopback or not.

Pure string helpers shared by the config's rules, the security settings and ``arena up``'s port check.
"""

from __future__ import annotations

import ipaddress

from arena_common.core.errors import ConfigError

__all__ = ["endpoint_host", "is_loopback", "mirror_connection", "split_endpoint", "udp_listen_port"]


def mirror_connection(conn: str) -> str:
    """The other end of a pymavlink connection string: udpin↔udpout, tcp↔tcpin."""
    scheme, sep, rest = conn.partition(":")
    mirror = {"udpin": "udpout", "udpout": "udpin", "udp": "udpout", "tcp": "tcpin", "tcpin": "tcp"}
    if not sep or scheme not in mirror:
        raise ConfigError(f"cannot derive the simulated side of MAVLink connection {conn!r}; set sim.mavlink")
    return f"{mirror[scheme]}:{rest}"


def udp_listen_port(conn: str) -> int | None:
    """The local UDP port a gateway binds for ``udpin:HOST:PORT`` (or ``udp:…``); None for other links."""
    scheme, _, port = split_endpoint(conn)
    return port if scheme in ("udpin", "udp") else None


def is_loopback(address: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (brackets allowed); False for names and the rest."""
    address = address.strip("[]")
    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


def split_endpoint(endpoint: str) -> tuple[str, str, int | None]:
    """``(protocol, host, port)`` of a Zenoh endpoint (``tcp/HOST:PORT#…``) or of a connection string
    (``udpin:HOST:PORT``); the port is None when there is none (or it is no number)."""
    sep = "/" if "/" in endpoint.split(":", 1)[0] else ":"
    proto, _, rest = endpoint.partition(sep)
    host, _, port = rest.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    return proto, host.strip("[]"), int(port) if port.isdigit() else None


def endpoint_host(endpoint: str) -> str:
    """The host part of a Zenoh endpoint (``tcp/HOST:PORT#…``) or of ``udpin:HOST:PORT``."""
    return split_endpoint(endpoint)[1]
