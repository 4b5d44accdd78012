"""Who may say what on the arena's bus: Zenoh authentication, access control and TLS from the config.

The router is the only place where hosts meet (services listen on loopback only, so every message
between two computers crosses the router), so the router enforces:

* **authentication** — each computer logs in as its host name (Zenoh ``usrpwd``: the router holds the
  ``user:password`` dictionary, each host its own password file), and/or presents a TLS certificate
  whose common name is its host name (mutual TLS);
* **ownership of keys** — only the host running a vehicle's gateway may publish its ``state``,
  ``telemetry/**`` and ``events`` or serve its ``cmd``; only its downsampler's host its ``vision`` (the
  transform's host when the transform decimates); only
  the mocap/transform/sim hosts ``mocap``/``pose``/``truth``; a host's presence and stats live under
  its own name;
* **who commands** — only ``command_hosts`` may query ``arena/*/cmd`` and ``arena/sys/rec/*`` or put
  ``setpoint`` and ``arena/estop`` (empty: every host);
* **TLS** on every endpoint that leaves the machine (``tls/…``), with the lab's own CA.

The rules are Zenoh 1.x ``access_control`` (``default_permission: allow`` plus deny rules per subject;
a deny always wins).  :func:`router_settings` and :func:`session_settings` give ``path → value``
settings for :class:`~arena_common.bus.session.BusOptions` ``settings``; :func:`zenoh_json` nests them into a
Zenoh JSON config (``--zconfig``).
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from arena_common.core.config import ArenaConfig, SecuritySpec
from arena_common.core.errors import ArenaError


class SecurityError(ArenaError):
    """Security settings that cannot work (a missing file, a plain endpoint crossing the network…)."""


def _path(template: str, host: str) -> str:
    return template.replace("{host}", host)


# -- who owns what ----------------------------------------------------------------------------------------


def owners(cfg: ArenaConfig) -> dict[str, set[str]]:
    """Key expression → the hosts allowed to publish (or serve) it; every other host is denied."""
    table: dict[str, set[str]] = {}

    def own(key: str, host: str | None) -> None:
        table.setdefault(key, set())
        if host is not None:
            table[key].add(host)

    for v in cfg.vehicles:
        for leaf in ("mocap", "pose", "vision", "state", "telemetry/**", "events", "cmd", "truth"):
            own(f"arena/{v}/{leaf}", None)
    own("arena/sys/frames", None)
    for h in cfg.hosts.values():
        if "mocap" in h.services:
            own("arena/sys/frames", h.name)
        for v in cfg.vehicles:
            if "mocap" in h.services:
                own(f"arena/{v}/mocap", h.name)
            if "transform" in h.services:
                own(f"arena/{v}/pose", h.name)
                if cfg.pipeline.decimate == "transform":
                    own(f"arena/{v}/vision", h.name)
            if "sim" in h.services:
                own(f"arena/{v}/truth", h.name)
        for v in h.vehicles:
            if "gateway" in h.vehicle_services and cfg.vehicles[v].px4_sitl:
                own(f"arena/{v}/truth", h.name)  # its PX4 SITL's truth bridge runs with its gateway
            if "downsampler" in h.vehicle_services:
                own(f"arena/{v}/vision", h.name)
            if "gateway" in h.vehicle_services:
                for leaf in ("state", "telemetry/**", "events", "cmd"):
                    own(f"arena/{v}/{leaf}", h.name)
    return table


def _subjects(cfg: ArenaConfig, spec: SecuritySpec) -> list[dict[str, Any]]:
    subjects: list[dict[str, Any]] = []
    for h in cfg.hosts:
        if spec.users_file:
            subjects.append({"id": f"user:{h}", "usernames": [h]})
        if spec.tls and spec.mtls:
            subjects.append({"id": f"cert:{h}", "cert_common_names": [h]})
    return subjects


def _subject_ids(cfg: ArenaConfig, spec: SecuritySpec, hosts: Iterable[str]) -> list[str]:
    wanted = set(hosts)
    return [s["id"] for s in _subjects(cfg, spec) if s["id"].split(":", 1)[1] in wanted]


def access_control(cfg: ArenaConfig, spec: SecuritySpec) -> dict[str, Any]:
    """The router's Zenoh ``access_control`` section for this arena.

    Identities are host names (user names and/or certificate common names); without any identity
    configured the rules could not tell hosts apart, which is a :class:`SecurityError`.
    """
    if not (spec.users_file or (spec.tls and spec.mtls)):
        raise SecurityError(
            f"{cfg.path}: security.acl needs an identity for each host: set security.users_file "
            "(user names) or security.tls with security.mtls (certificate common names)"
        )
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    hosts = list(cfg.hosts)

    def deny(rule_id: str, messages: list[str], key_exprs: list[str], denied_hosts: Iterable[str]) -> None:
        subjects = _subject_ids(cfg, spec, denied_hosts)
        if not subjects:
            return
        rules.append(
            {
                "id": rule_id,
                "permission": "deny",
                "flows": ["ingress"],
                "messages": messages,
                "key_exprs": key_exprs,
            }
        )
        policies.append({"id": f"policy:{rule_id}", "rules": [rule_id], "subjects": subjects})

    for key, allowed in sorted(owners(cfg).items()):
        others = [h for h in hosts if h not in allowed]
        if key.endswith("/cmd"):
            deny(f"serve:{key}", ["declare_queryable", "reply"], [key], others)
        else:
            deny(f"publish:{key}", ["put", "delete"], [key], others)
    for h in hosts:
        others = [o for o in hosts if o != h]
        deny(f"presence:{h}", ["liveliness_token"], [f"arena/sys/alive/{h}/**"], others)
        deny(f"stats:{h}", ["put", "delete"], [f"arena/sys/stats/{h}/**"], others)
        deny(f"recorder:{h}", ["declare_queryable", "reply"], [f"arena/sys/rec/{h}"], others)
    if spec.command_hosts:
        unknown = [h for h in spec.command_hosts if h not in cfg.hosts]
        if unknown:
            raise SecurityError(
                f"{cfg.path}: security.command_hosts: {unknown[0]!r} is not a host of the config "
                f"(known hosts: {', '.join(cfg.hosts)})"
            )
        non_commanders = [h for h in hosts if h not in spec.command_hosts]
        deny("commands:query", ["query"], ["arena/*/cmd", "arena/sys/rec/*"], non_commanders)
        deny("commands:put", ["put", "delete"], ["arena/*/setpoint", "arena/estop"], non_commanders)
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": rules,
        "subjects": _subjects(cfg, spec),
        "policies": policies,
    }


# -- settings for the router and for every other session ----------------------------------------------------


def _is_loopback(endpoint: str) -> bool:
    rest = endpoint.partition("/")[2].split("#", 1)[0].split("?", 1)[0]
    host = rest.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_endpoints(cfg: ArenaConfig, spec: SecuritySpec) -> None:
    """With ``tls``, every configured endpoint that is not loopback must be ``tls/…``."""
    if not spec.tls:
        return
    for field_name, endpoints in (("router_listen", cfg.zenoh.router_listen), ("connect", cfg.zenoh.connect)):
        for e in endpoints:
            if not e.startswith("tls/") and not _is_loopback(e):
                raise SecurityError(
                    f"{cfg.path}: zenoh.{field_name}: {e!r} leaves this computer without TLS "
                    "(security.tls is on): use tls/HOST:PORT"
                )


def _require(path: str, what: str) -> str:
    if not path:
        raise SecurityError(f"security.{what} is required here")
    if not Path(path).is_file():
        raise SecurityError(f"security.{what}: {path} does not exist or is not a file")
    return path


def router_settings(cfg: ArenaConfig, spec: SecuritySpec, host: str) -> dict[str, Any]:
    """Zenoh settings (``path → value``) of the router run by ``host``."""
    if not spec.enabled:
        return {}
    check_endpoints(cfg, spec)
    out: dict[str, Any] = {}
    if spec.users_file:
        out["transport/auth/usrpwd/dictionary_file"] = _require(_path(spec.users_file, host), "users_file")
    if spec.tls:
        out["transport/link/tls/root_ca_certificate"] = _require(_path(spec.ca, host), "ca")
        out["transport/link/tls/listen_certificate"] = _require(_path(spec.cert, host), "cert")
        out["transport/link/tls/listen_private_key"] = _require(_path(spec.key, host), "key")
        out["transport/link/tls/enable_mtls"] = spec.mtls
    if spec.acl:
        out["access_control"] = access_control(cfg, spec)
    return out


def session_settings(cfg: ArenaConfig, spec: SecuritySpec, host: str) -> dict[str, Any]:
    """Zenoh settings (``path → value``) of every other session on ``host`` (services, user programs)."""
    if not spec.enabled:
        return {}
    check_endpoints(cfg, spec)
    out: dict[str, Any] = {}
    if spec.users_file:
        pw_path = _require(_path(spec.password_file, host), "password_file")
        password = Path(pw_path).read_text(encoding="utf-8").strip()
        if not password:
            raise SecurityError(f"security.password_file: {pw_path} is empty")
        out["transport/auth/usrpwd/user"] = host
        out["transport/auth/usrpwd/password"] = password
    if spec.tls:
        out["transport/link/tls/root_ca_certificate"] = _require(_path(spec.ca, host), "ca")
        if spec.mtls:
            out["transport/link/tls/connect_certificate"] = _require(_path(spec.cert, host), "cert")
            out["transport/link/tls/connect_private_key"] = _require(_path(spec.key, host), "key")
            out["transport/link/tls/enable_mtls"] = True
    return out


def zenoh_json(settings: Mapping[str, Any]) -> dict[str, Any]:
    """Nest ``path → value`` settings into a Zenoh JSON config document."""
    doc: dict[str, Any] = {}
    for path, value in settings.items():
        node = doc
        *parents, leaf = path.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return doc


def write_zconfig(path: Path | str, settings: Mapping[str, Any]) -> Path:
    """Write settings as a Zenoh JSON config readable only by its owner (it may hold a password)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        json.dump(zenoh_json(settings), f, indent=2)
    return p


def make_credentials(cfg: ArenaConfig, directory: Path | str) -> tuple[Path, dict[str, Path]]:
    """Generate a password per host: ``users.txt`` for the router, ``<host>.password`` for each host.

    Files are created readable by their owner only; existing passwords are kept.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    lines = []
    for host in cfg.hosts:
        p = d / f"{host}.password"
        if p.exists():
            password = p.read_text(encoding="utf-8").strip()
        else:
            password = secrets.token_urlsafe(24)
            fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(password + "\n")
        files[host] = p
        lines.append(f"{host}:{password}")
    users = d / "users.txt"
    fd = os.open(users, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    return users, files
