"""Connection strings and endpoints: the host of a Zenoh endpoint or MAVLink link, loopback or not.

Pure string helpers shared by the config's rules, the security settings and ``arena up``'s port check.
"""

from __future__ import annotations

import ipaddress

from arena_common.core.errors import ConfigError

__all__ = ["endpoint_host", "is_loopback", "mirror_connection", "udp_listen_port"]


def mirror_connection(conn: str) -> str:
    """The other end of a pymavlink connection string: udpin↔udpout, tcp↔tcpin."""
    scheme, sep, rest = conn.partition(":")
    mirror = {"udpin": "udpout", "udpout": "udpin", "udp": "udpout", "tcp": "tcpin", "tcpin": "tcp"}
    if not sep or scheme not in mirror:
        raise ConfigError(f"cannot derive the simulated side of MAVLink connection {conn!r}; set sim.mavlink")
    return f"{mirror[scheme]}:{rest}"


def udp_listen_port(conn: str) -> int | None:
    """The local UDP port a gateway binds for ``udpin:HOST:PORT`` (or ``udp:…``); None for other links."""
    scheme, _, rest = conn.partition(":")
    port = rest.rpartition(":")[2]
    return int(port) if scheme in ("udpin", "udp") and port.isdigit() else None


def is_loopback(address: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (brackets allowed); False for names and the rest."""
    address = address.strip("[]")
    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


def endpoint_host(endpoint: str) -> str:
    """The host part of a Zenoh endpoint (``tcp/HOST:PORT#…``) or of ``udpin:HOST:PORT``."""
    rest = endpoint.partition("/")[2] if "/" in endpoint.split(":", 1)[0] else endpoint.partition(":")[2]
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    return rest.rpartition(":")[0].strip("[]")
