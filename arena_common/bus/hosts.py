"""This computer on the bus: its name as a key chunk, and the bus options of a session on it."""

from __future__ import annotations

import os
import re
import socket
from dataclasses import replace
from typing import Any

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig

__all__ = ["host_bus_options", "host_name"]


def host_name(explicit: str | None = None) -> str:
    """This machine's name as a key chunk (``--host`` wins over the hostname)."""
    name = explicit or os.environ.get("ARENA_HOST") or socket.gethostname().split(".")[0]
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name) or "host"


def host_bus_options(cfg: ArenaConfig | None, host: str, options: BusOptions | None) -> BusOptions:
    """The bus options of a session on ``host``: its address to listen on, its security settings."""
    options = options or BusOptions()
    if cfg is None:
        return options
    spec = cfg.hosts.get(host)
    if spec is not None and spec.address and not options.address:
        options = replace(options, address=spec.address)
    extra: dict[str, Any] = {}
    if cfg.security.enabled:  # the security module is loaded only for a secured arena
        from arena_common.bus import security

        extra = security.session_settings(cfg, cfg.security, host)
    if extra:
        options = replace(options, settings={**extra, **options.settings})
    return options
