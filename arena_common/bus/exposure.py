"""What an arena may expose to the network: nothing listens beyond loopback unauthenticated unless the
config says ``security.insecure = true``, and a pinned MAVLink peer (``mavlink_peer``) is one real host.

:func:`check_exposure` applies these rules to a loaded config; :func:`load` (``arena_common.load_config``,
and :class:`~arena_common.client.arena.Arena` given a path) reads a config file with them.  The arena's
own processes and commands load through :func:`arena_common.runtime.options.read_config`, which applies
them too.  docs/safety.md §3.3 says why.
"""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path
from typing import Any

from arena_common.core import config as config_mod
from arena_common.core.config import ArenaConfig, VehicleSpec
from arena_common.core.convert import field_error
from arena_common.core.endpoints import endpoint_host, is_loopback

_INSECURE = "enable [security] (arena security init) or, knowingly, set security.insecure = true"


def check_exposure(cfg: ArenaConfig) -> None:
    """:class:`~arena_common.core.errors.ConfigError` naming the file and the field when ``cfg`` breaks a
    rule of this module's docstring.

    Without ``[security]``, Zenoh endpoints and host addresses stay on loopback; in any case, a MAVLink
    link or a ground-station link that listens on the network must be signed or pinned to the
    autopilot's address (``mavlink_peer``), unless ``security.insecure``.
    """
    for name, v in cfg.vehicles.items():
        if v.mavlink_peer:
            _check_peer(cfg.path, f"vehicles.{name}", v)
    if cfg.security.insecure:
        return
    zenoh, zenoh_too = cfg.zenoh, not cfg.security.enabled
    for field_name, endpoints in (("router_listen", zenoh.router_listen), ("listen", zenoh.listen)):
        for e in endpoints:
            if zenoh_too and not is_loopback(endpoint_host(e)):
                raise field_error(cfg.path, f"zenoh.{field_name}", f"loopback endpoints only: {_INSECURE}", e)
    for name, h in cfg.hosts.items():
        if (
            zenoh_too
            and h.address
            and not is_loopback(h.address)
            and zenoh.mode == "peer"
            and not zenoh.listen
        ):
            raise field_error(
                cfg.path,
                f"hosts.{name}.address",
                f"no address to listen on without authentication (its peers would): {_INSECURE}",
                h.address,
            )
    for name, v in cfg.vehicles.items():
        scheme = v.mavlink.partition(":")[0]
        listens = scheme in ("udpin", "tcpin", "udp") and not is_loopback(endpoint_host(v.mavlink))
        gcs_scheme = v.gcs.partition(":")[0]
        if gcs_scheme in ("udpin", "tcpin", "udp") and not is_loopback(endpoint_host(v.gcs)):
            raise field_error(
                cfg.path,
                f"vehicles.{name}.gcs",
                "a ground-station link on loopback only (it forwards whatever it receives to the vehicle, "
                "unauthenticated): use udpout:GCS_IP:PORT, or, knowingly, set security.insecure = true",
                v.gcs,
            )
        if listens and not v.signing_key_file and not v.mavlink_peer:
            raise field_error(
                cfg.path,
                f"vehicles.{name}.mavlink",
                f"an unsigned MAVLink link listening on loopback only: sign it (vehicles.{name}."
                f"signing_key_file), pin the autopilot's address (vehicles.{name}.mavlink_peer) or, "
                "knowingly, set security.insecure = true",
                v.mavlink,
            )


def _check_peer(path: str, where: str, v: VehicleSpec) -> None:
    """``mavlink_peer``: one host's IPv4 address and a port, on a listening UDP link to a real autopilot.

    A link not known yet (a PX4 SITL vehicle's left out, loaded without
    :mod:`arena_common.runtime.px4_sitl_rules`, which make it ``udpin`` on loopback) is not judged.
    """
    host, _, port = v.mavlink_peer.rpartition(":")
    try:
        ip = ipaddress.IPv4Address(host)
    except ValueError:
        ip = None
    if (
        ip is None
        or ip.is_unspecified
        or ip.is_multicast
        or ip == ipaddress.IPv4Address("255.255.255.255")
        or not re.fullmatch(r"[0-9]{1,5}", port, re.ASCII)
        or not 0 < int(port) < 65536
    ):
        raise field_error(
            path,
            f"{where}.mavlink_peer",
            "the autopilot's IPv4 address and UDP port, IP:PORT (e.g. 192.168.1.31:14550)",
            v.mavlink_peer,
        )
    if v.mavlink and v.mavlink.partition(":")[0] not in ("udpin", "udp"):
        raise field_error(
            path,
            f"{where}.mavlink_peer",
            f"no mavlink_peer unless mavlink is udpin:HOST:PORT (got {v.mavlink!r})",
            v.mavlink_peer,
        )
    if v.autopilot == "sim":
        raise field_error(
            path,
            f"{where}.mavlink_peer",
            'no mavlink_peer with autopilot = "sim" (the simulated autopilot sends from any port)',
            v.mavlink_peer,
        )


def parse(data: dict[str, Any], path: str = "<config>") -> ArenaConfig:
    """:func:`arena_common.core.config.parse`, then :func:`check_exposure`."""
    cfg = config_mod.parse(data, path)
    check_exposure(cfg)
    return cfg


def load(path: str | Path) -> ArenaConfig:
    """Read and check a config file as a program that joins the arena's bus needs it.

    The config's shape and the rules across its fields (:func:`arena_common.core.config.load`), then what
    it may expose to the network (:func:`check_exposure`); :class:`~arena_common.core.errors.ConfigError`
    naming the file and the field.  Not the PX4 SITL rules (:mod:`arena_common.runtime.px4_sitl_rules`):
    a ``"px4-sitl"`` vehicle that leaves its ``mavlink`` and ``system_id`` out keeps them empty and 0 here
    (a client never talks MAVLink to it); ``arena config check`` and every arena process apply them.
    """
    cfg = config_mod.load(path)
    check_exposure(cfg)
    return cfg
