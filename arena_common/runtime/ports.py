"""The fixed ports a host's share of the arena binds, by the config field that names each, and which are taken.

``arena up`` asks :func:`taken_ports` before it starts anything: a router port another program holds would
make the router restart for ever while the rest of the arena comes up without a bus.  Ports ``0`` (any
free port) and links that do not bind (serial, outgoing UDP) are not listed.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass

from arena_common.core.config import ArenaConfig
from arena_common.core.endpoints import endpoint_host, split_endpoint, udp_listen_port

__all__ = ["FixedPort", "fixed_ports", "taken_ports"]


@dataclass(frozen=True, slots=True)
class FixedPort:
    """One port a process of this host binds: the config field naming it, the protocol, address, port."""

    field: str
    proto: str  # "tcp" or "udp"
    address: str
    port: int

    def __str__(self) -> str:
        return f"{self.field} ({self.proto} {self.address}:{self.port})"


def _zenoh(field: str, endpoint: str) -> FixedPort | None:
    proto, host, port = split_endpoint(endpoint)
    if "/" not in endpoint or proto not in ("tcp", "tls", "udp", "quic", "ws") or not port:
        return None
    return FixedPort(field, "udp" if proto in ("udp", "quic") else "tcp", host or "0.0.0.0", port)


def fixed_ports(cfg: ArenaConfig, host: str) -> list[FixedPort]:
    """Every fixed port the processes of ``host`` bind, each with the config field that names it."""
    h = cfg.host(host)
    found: list[FixedPort] = []
    if "router" in h.services:
        found += [p for e in cfg.zenoh.router_listen if (p := _zenoh("zenoh.router_listen", e)) is not None]
    if "sim" in h.services:  # the Motive emulator serves NatNet where the ingest expects it
        address = cfg.mocap.server
        found.append(FixedPort("mocap.command_port", "udp", address, cfg.mocap.command_port))
        if not cfg.mocap.multicast:
            found.append(FixedPort("mocap.data_port", "udp", cfg.mocap.interface, cfg.mocap.data_port))
    if "gateway" in h.vehicle_services:
        for name in h.vehicles:
            v = cfg.vehicle(name)
            port = udp_listen_port(v.mavlink)
            if port:
                address = endpoint_host(v.mavlink) or "0.0.0.0"
                found.append(FixedPort(f"vehicles.{name}.mavlink", "udp", address, port))
    return found


def _bindable(p: FixedPort) -> bool:
    kind = socket.SOCK_STREAM if p.proto == "tcp" else socket.SOCK_DGRAM
    family = socket.AF_INET6 if ":" in p.address else socket.AF_INET
    with socket.socket(family, kind) as s:
        if p.proto == "tcp":
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a server does: TIME_WAIT is no owner
        try:
            s.bind((p.address, p.port))
        except OSError as exc:
            # An address not on this computer is the config's problem, reported by the service itself.
            return exc.errno != errno.EADDRINUSE
    return True


def taken_ports(cfg: ArenaConfig, host: str) -> list[FixedPort]:
    """The fixed ports of ``host`` that another program holds now."""
    return [p for p in fixed_ports(cfg, host) if not _bindable(p)]
