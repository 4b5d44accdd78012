"""A simulated autopilot's MAVLink connection, as PX4's: on the address that faces its gateway, MAVLink 2,
and through a :class:`~arena_common.sim.linkdelay.LinkDelay` relay when its link is slow."""

from __future__ import annotations

import os
import socket
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is first imported: MAVLink 2, as PX4

from pymavlink import mavutil

from arena_common.mavlink.transports import MavlinkLinkError, parse_serial
from arena_common.sim.base import SimAutopilotError
from arena_common.sim.linkdelay import LinkDelay

__all__ = ["open_connection"]


def open_connection(
    connection: str, system_id: int, component_id: int, link_delay: tuple[float, float] = (0.0, 0.0)
) -> tuple[Any, LinkDelay | None]:
    """The pymavlink connection of a simulated autopilot, and its relay (``link_delay``: (delay, jitter) s
    each way; not zero only on ``udpout`` links); :class:`SimAutopilotError` naming what failed."""
    relay: LinkDelay | None = None
    if link_delay[0] > 0:
        host, _, port_text = connection.removeprefix("udpout:").rpartition(":")
        if not connection.startswith("udpout:") or not port_text.isdigit():
            raise SimAutopilotError(f"a link delay needs a udpout:HOST:PORT link, not {connection!r}")
        try:
            relay = LinkDelay((host, int(port_text)), *link_delay, seed=system_id)
        except (OSError, ValueError) as exc:
            raise SimAutopilotError(f"link delay for {connection!r}: {exc}") from exc
        connection = f"udpout:{host}:{relay.port}"
    try:
        device, extra = connection, {}
        if connection.startswith("serial:"):  # the gateway's spelling: serial:DEVICE[:BAUD]
            device, baud = parse_serial(connection[len("serial:") :], connection)
            extra = {"baud": baud}
        conn = mavutil.mavlink_connection(
            device,
            source_system=system_id,
            source_component=component_id,
            dialect="common",
            **extra,
        )
    except (OSError, ValueError, MavlinkLinkError) as exc:
        if relay is not None:
            relay.close()
        raise SimAutopilotError(f"cannot open MAVLink connection {connection!r}: {exc}") from exc
    port = getattr(conn, "port", None)
    if connection.startswith("udpout:") and port is not None:
        # Like PX4 on its link, the vehicle reads whoever sends to its port, but only on the address
        # that faces its gateway (loopback for a gateway on this computer), never on every interface:
        # the serial line or radio it stands for is not on the lab's network.
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(conn.destination_addr)
            port.bind((probe.getsockname()[0], 0))
    if not type(conn.mav).__module__.startswith("pymavlink.dialects.v20."):
        conn.close()
        if relay is not None:
            relay.close()
        raise SimAutopilotError("pymavlink was loaded for MAVLink 1; import this module before pymavlink")
    return conn, relay
