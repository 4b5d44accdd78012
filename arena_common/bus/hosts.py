"""This computer on the bus: its name as a key chunk, and the bus options of a session on it."""

from __future__ import annotations

import logging
import os
import re
import socket
from dataclasses import replace

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig

__all__ = ["host_bus_options", "host_name"]

log = logging.getLogger("arena.security")


def host_name(explicit: str | None = None) -> str:
    """This machine's name as a key chunk (``--host`` wins over the hostname)."""
    name = explicit or os.environ.get("ARENA_HOST") or socket.gethostname().split(".")[0]
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name) or "host"


def host_bus_options(
    cfg: ArenaConfig | None, host: str, options: BusOptions | None, *, vehicle: str = ""
) -> BusOptions:
    """The bus options of a session on ``host``: its address to listen on, its security settings.

    On a secured arena every session but a router is a Zenoh *client* of the router (it listens on
    nothing; :func:`arena_common.bus.security.secured_options`).  So is a ``vehicle``'s own process when
    ``zenoh.vehicle_mode`` is "client" and no ``--mode`` was given.  Otherwise a peer listens on its
    host's address; an arena that listens beyond loopback without security (``security.insecure``)
    says so at every start.
    """
    options = options or BusOptions()
    if cfg is None:
        return options
    if vehicle and cfg.zenoh.vehicle_mode == "client" and options.mode is None and cfg.zenoh.mode != "router":
        options = replace(options, mode="client", listen=())
    if cfg.security.enabled:  # the security module is loaded only for a secured arena
        from arena_common.bus import security

        return security.secured_options(cfg, host, options)
    if cfg.security.insecure:
        log.warning(
            "%s: security.insecure = true: this arena's Zenoh and MAVLink endpoints beyond loopback accept "
            "anyone on the network (no login, no access rules); see docs/safety.md §3.3",
            cfg.path,
        )
    spec = cfg.hosts.get(host)
    if spec is not None and spec.address and not options.address:
        options = replace(options, address=spec.address)
    return options
