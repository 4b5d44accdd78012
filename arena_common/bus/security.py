"""Who may say what on the arena's bus: Zenoh authentication, access control and TLS from the config.

On a secured arena (``[security] enabled``) the router is the only process that listens on the network,
and it authenticates every connection; every other session — services, ``arena`` commands, user programs
— is a Zenoh *client* of it that listens on nothing (:func:`secured_options`).  So every message between
two processes crosses the router, which enforces:

* **authentication** — each computer logs in as its host name (Zenoh ``usrpwd``: the router holds the
  ``user:password`` dictionary, each host its own password file), and/or presents a certificate of the
  lab's CA whose common name is its host name (mutual TLS; ``arena security init`` makes them);
* **deny by default** — an identity gets only what :func:`grants` allows it; one that is no host (or
  observer) of the config matches no rule and gets nothing, not even reads;
* **ownership of keys** — only the host running a vehicle's gateway may publish its ``state``,
  ``telemetry/**`` and ``events`` or serve its ``cmd``; only the host that decimates it its ``vision``;
  only the mocap/transform/sim hosts ``mocap``/``pose``/``truth``; a host's presence, stats and clock
  reports live under its own name;
* **who commands** — only ``command_hosts`` may query ``arena/*/cmd`` and ``arena/sys/rec/*`` or put
  ``setpoint`` and ``arena/estop`` (empty: every host);
* **TLS** on every endpoint that leaves the machine (``tls/…``), with the lab's own CA.

Why clients and not peers: Zenoh routers do not relay between peers, so peers of different computers
need direct links, i.e. a listener each — which would accept anyone who reaches its port (measured on
loopback: a router hop costs ≈ 80 µs p50; docs/safety.md §3.3).  :func:`router_settings` and
:func:`session_settings` give ``path → value`` settings for
:class:`~arena_common.bus.session.BusOptions` ``settings``; :func:`zenoh_json` nests them into a Zenoh
JSON config (``--zconfig``).
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from arena_common.bus.pki import secret_mode_problem
from arena_common.bus.session import BusOptions
from arena_common.core import keys
from arena_common.core.config import ArenaConfig, SecuritySpec
from arena_common.core.endpoints import endpoint_host, is_loopback
from arena_common.core.errors import ArenaError


class SecurityError(ArenaError):
    """Security settings that cannot work (a missing file, a plain endpoint crossing the network…)."""


def resolve(cfg: ArenaConfig, template: str, host: str) -> str:
    """A ``[security]`` file path for ``host``: ``{host}`` replaced, relative to the config file's folder."""
    return str(cfg.file(template.replace("{host}", host))) if template else ""


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
    own("arena/sys/fleet", None)
    own("arena/sys/vision", None)
    for h in cfg.hosts.values():
        if "mocap" in h.services:
            own("arena/sys/frames", h.name)
        if "transform" in h.services:
            own("arena/sys/fleet", h.name)
            if cfg.pipeline.decimate == "transform":
                own("arena/sys/vision", h.name)
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
    for name in (*cfg.hosts, *spec.observers):
        if spec.users_file:
            subjects.append({"id": f"user:{name}", "usernames": [name]})
        if spec.tls and spec.mtls:
            subjects.append({"id": f"cert:{name}", "cert_common_names": [name]})
    return subjects


def _subject_ids(cfg: ArenaConfig, spec: SecuritySpec, names: Iterable[str]) -> list[str]:
    wanted = set(names)
    return [s["id"] for s in _subjects(cfg, spec) if s["id"].split(":", 1)[1] in wanted]


#: What every identity the config names may receive: data, replies, presence and declarations on the
#: arena's keys (the router sends a host only what it subscribed to or serves).
_READ_EGRESS = ["put", "delete", "reply", "liveliness_token", "declare_subscriber", "declare_queryable"]
_READ_INGRESS = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


def grants(cfg: ArenaConfig, spec: SecuritySpec) -> dict[str, list[tuple[str, list[str], list[str]]]]:
    """Identity → what it is allowed: ``(flow, messages, key expressions)`` triples; all else is denied.

    Every host of the config may read every arena key, answer its own time/recorder/command queries
    and publish the keys it owns (:func:`owners`), its own presence, stats and clock reports.  Commands,
    setpoints and estops come from ``command_hosts`` only (every host when empty).  ``observers`` may
    only read.  An identity that is none of these is no subject at all: it gets nothing.
    """
    table = owners(cfg)
    commanders = set(spec.command_hosts or cfg.hosts)
    out: dict[str, list[tuple[str, list[str], list[str]]]] = {}
    read = [("egress", _READ_EGRESS, ["arena/**"]), ("ingress", _READ_INGRESS, ["arena/**"])]
    for name in spec.observers:
        out[name] = list(read)
    for h in cfg.hosts:
        publish = sorted(k for k, hosts in table.items() if h in hosts and not k.endswith("/cmd"))
        publish += [f"arena/sys/alive/{h}/**", f"arena/sys/stats/{h}/**", f"arena/sys/clock/{h}/**"]
        serve = sorted(k for k, hosts in table.items() if h in hosts and k.endswith("/cmd"))
        serve.append(f"arena/sys/rec/{h}")
        mocap_host = "mocap" in cfg.hosts[h].services
        if mocap_host:
            publish.append("arena/sys/bodies/**")
            serve.append(keys.TIME)
        g = [
            *read,
            ("egress", ["query"], serve),
            ("ingress", ["put", "delete"], [k for k in publish if not k.startswith("arena/sys/alive/")]),
            ("ingress", ["liveliness_token"], [f"arena/sys/alive/{h}/**"]),
            ("ingress", ["declare_queryable", "reply"], serve),
            ("ingress", ["query"], [keys.TIME]),
        ]
        g += _ros2_grants(cfg, h, h in commanders)
        if h in commanders:
            g += [
                ("ingress", ["query"], ["arena/*/cmd", "arena/sys/rec/*"]),
                ("ingress", ["put", "delete"], ["arena/*/setpoint", keys.ESTOP]),
            ]
        out[h] = g
    return out


#: ROS 2 over rmw_zenoh (domain 0): data under ``0/…``, graph tokens under the hermetic ``@ros2_lv/0/…``.
ROS2_KEYS = ["0/**", "@ros2_lv/0/**"]


def _ros2_grants(cfg: ArenaConfig, host: str, commander: bool) -> list[tuple[str, list[str], list[str]]]:
    """What a host needs for ROS 2 (docs/ros2.md): the ``ros2`` host publishes every topic and answers the
    late-joiner caches; any host's ROS 2 nodes read them and declare their own graph tokens; only
    command hosts' ROS 2 nodes may send ``goto`` and ``cmd_vel``."""
    g = [
        ("egress", [*_READ_EGRESS, "query"], ROS2_KEYS),
        ("ingress", _READ_INGRESS, ROS2_KEYS),
        ("ingress", ["liveliness_token"], ["@ros2_lv/0/**"]),
        ("ingress", ["query"], ["0/**"]),
    ]
    if "ros2" in cfg.hosts[host].services:
        g += [
            ("ingress", ["put", "delete"], ["0/**"]),
            ("ingress", ["liveliness_token"], ["0/**"]),  # the advanced publishers' cache tokens
            ("ingress", ["declare_queryable", "reply"], ["0/**"]),
        ]
    elif commander:
        g.append(("ingress", ["put", "delete"], ["0/arena/*/goto/**", "0/arena/*/cmd_vel/**"]))
    return g


def access_control(cfg: ArenaConfig, spec: SecuritySpec) -> dict[str, Any]:
    """The router's Zenoh ``access_control`` section for this arena: **deny by default**.

    Identities are host names (user names and/or certificate common names); without any identity
    configured the rules could not tell hosts apart, which is a :class:`SecurityError`.  Each identity
    gets the allow rules of :func:`grants`; any other identity — a certificate of the lab CA whose
    name is no host of the config, a user of the dictionary that the config does not name — matches
    no subject and gets the default: nothing.
    """
    if not (spec.users_file or (spec.tls and spec.mtls)):
        raise SecurityError(
            f"{cfg.path}: security.acl needs an identity for each host: set security.users_file "
            "(user names) or security.tls with security.mtls (certificate common names)"
        )
    for field_name, names in (("command_hosts", spec.command_hosts), ("observers", spec.observers)):
        for name in names:
            if field_name == "command_hosts" and name not in cfg.hosts:
                raise SecurityError(
                    f"{cfg.path}: security.command_hosts: {name!r} is not a host of the config "
                    f"(known hosts: {', '.join(cfg.hosts)})"
                )
            if field_name == "observers" and name in cfg.hosts:
                raise SecurityError(f"{cfg.path}: security.observers: {name!r} is a host (hosts read anyway)")
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for name, allowed in grants(cfg, spec).items():
        ids = []
        for i, (flow, messages, key_exprs) in enumerate(allowed):
            if not key_exprs:
                continue
            rule_id = f"{name}:{i}"
            ids.append(rule_id)
            rules.append(
                {
                    "id": rule_id,
                    "permission": "allow",
                    "flows": [flow],
                    "messages": messages,
                    "key_exprs": key_exprs,
                }
            )
        policies.append({"id": f"policy:{name}", "rules": ids, "subjects": _subject_ids(cfg, spec, [name])})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": _subjects(cfg, spec),
        "policies": policies,
    }


# -- settings for the router and for every other session ----------------------------------------------------


def check_endpoints(cfg: ArenaConfig, spec: SecuritySpec) -> None:
    """With ``tls``, every configured endpoint that is not loopback must be ``tls/…``."""
    if not spec.tls:
        return
    for field_name, endpoints in (("router_listen", cfg.zenoh.router_listen), ("connect", cfg.zenoh.connect)):
        for e in endpoints:
            if not e.startswith("tls/") and not is_loopback(endpoint_host(e)):
                raise SecurityError(
                    f"{cfg.path}: zenoh.{field_name}: {e!r} leaves this computer without TLS "
                    "(security.tls is on): use tls/HOST:PORT"
                )


def _require(path: str, what: str, secret: bool = False) -> str:
    if not path:
        raise SecurityError(f"security.{what} is required here")
    if not Path(path).is_file():
        raise SecurityError(f"security.{what}: {path} does not exist or is not a file")
    if secret and (problem := secret_mode_problem(Path(path))):
        raise SecurityError(f"security.{what}: {problem}")
    return path


def router_settings(cfg: ArenaConfig, spec: SecuritySpec, host: str) -> dict[str, Any]:
    """Zenoh settings (``path → value``) of the router run by ``host``."""
    if not spec.enabled:
        return {}
    check_endpoints(cfg, spec)
    out: dict[str, Any] = {}
    if spec.users_file:
        out["transport/auth/usrpwd/dictionary_file"] = _require(
            resolve(cfg, spec.users_file, host), "users_file", secret=True
        )
    if spec.tls:
        out["transport/link/tls/root_ca_certificate"] = _require(resolve(cfg, spec.ca, host), "ca")
        out["transport/link/tls/listen_certificate"] = _require(resolve(cfg, spec.cert, host), "cert")
        out["transport/link/tls/listen_private_key"] = _require(
            resolve(cfg, spec.key, host), "key", secret=True
        )
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
        pw_path = _require(resolve(cfg, spec.password_file, host), "password_file", secret=True)
        password = Path(pw_path).read_text(encoding="utf-8").strip()
        if not password:
            raise SecurityError(f"security.password_file: {pw_path} is empty")
        out["transport/auth/usrpwd/user"] = host
        out["transport/auth/usrpwd/password"] = password
    if spec.tls:
        out["transport/link/tls/root_ca_certificate"] = _require(resolve(cfg, spec.ca, host), "ca")
        if spec.mtls:
            out["transport/link/tls/connect_certificate"] = _require(resolve(cfg, spec.cert, host), "cert")
            out["transport/link/tls/connect_private_key"] = _require(
                resolve(cfg, spec.key, host), "key", secret=True
            )
            out["transport/link/tls/enable_mtls"] = True
    return out


def secured_options(cfg: ArenaConfig, host: str, options: BusOptions) -> BusOptions:
    """The bus options of a session on ``host`` of a secured arena: a client of the router, with its login.

    Only routers listen, and they authenticate every connection; any other session is a client that
    listens on nothing, so no process of a secured arena can be reached without the lab's credentials,
    and the router's access rules see every message between services (docs/safety.md §3.3).  A peer
    would listen for other peers without authentication: ``--mode peer`` is refused.
    """
    mode = options.mode or cfg.zenoh.mode
    if options.mode == "peer":
        raise SecurityError(
            f"{cfg.path}: --mode peer on a secured arena: a peer accepts other peers without authentication; "
            "every session of a secured arena is a client of its authenticated router (docs/safety.md §3.3)"
        )
    if options.listen and mode != "router":
        raise SecurityError(
            f"{cfg.path}: --listen on a secured arena: only the router listens (it authenticates every "
            "connection); this session is a client of it"
        )
    extra = session_settings(cfg, cfg.security, host)
    if mode == "router":
        return replace(options, settings={**extra, **options.settings})
    return replace(
        options,
        mode="client",
        listen=(),
        address="",
        settings={**extra, "listen/endpoints": [], **options.settings},
    )


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
    """Generate a password per host (and observer): ``users.txt`` for the router, ``<host>.password`` each.

    Files are created readable by their owner only; existing passwords are kept.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    lines = []
    for host in (*cfg.hosts, *cfg.security.observers):
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
