"""Security fragments from the config, enforced by a real Zenoh router: logins, key ownership, TLS.

Each "computer" is a Zenoh client session (so that, as between real computers, everything crosses the
router); all on 127.0.0.1 with private ports.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from arena_common.bus.security import (
    SecurityError,
    SecuritySpec,
    access_control,
    make_credentials,
    owners,
    router_settings,
    session_settings,
    write_zconfig,
    zenoh_json,
)
from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, ZenohSpec
from arena_common.core.errors import BusError
from arena_common.runtime.options import read_config
from tests.helpers import free_port, wait_for

pytestmark = pytest.mark.system

LAB = """
[zenoh]
connect = ["{ep}"]
router_listen = ["{ep}"]
[hosts.ground]
services = ["router", "mocap", "transform"]
[hosts.cc1]
vehicles = ["c1"]
[hosts.cc2]
vehicles = ["c2"]
[hosts.laptop]
[vehicles.c1]
mavlink = "udpin:127.0.0.1:14601"
system_id = 1
[vehicles.c2]
mavlink = "udpin:127.0.0.1:14602"
system_id = 2
"""


def lab(tmp_path: Path, endpoint: str, extra: str = "") -> ArenaConfig:
    path = tmp_path / "lab.toml"
    path.write_text(LAB.format(ep=endpoint) + extra)
    return read_config(path)


def test_owners_and_rules(tmp_path: Path) -> None:
    cfg = lab(tmp_path, "tcp/127.0.0.1:7447")
    table = owners(cfg)
    assert table["arena/c1/state"] == {"cc1"} and table["arena/c2/cmd"] == {"cc2"}
    assert table["arena/c1/pose"] == {"ground"} and table["arena/c1/truth"] == set()
    assert table["arena/sys/frames"] == table["arena/c1/mocap"] == {"ground"}  # the mocap host's
    acl = access_control(cfg, SecuritySpec(enabled=True, users_file="u", command_hosts=("laptop",)))
    assert acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])
    rules = {r["id"]: r for r in acl["rules"]}
    allowed: dict[str, list[tuple[str, str, str]]] = {}
    for p in acl["policies"]:
        (subject,) = p["subjects"]
        allowed[subject] = [
            (f, m, k)
            for rid in p["rules"]
            for f in rules[rid]["flows"]
            for m in rules[rid]["messages"]
            for k in rules[rid]["key_exprs"]
        ]
    assert set(allowed) == {"user:ground", "user:cc1", "user:cc2", "user:laptop"}
    assert ("ingress", "put", "arena/c1/state") in allowed["user:cc1"]
    assert ("ingress", "put", "arena/c1/state") not in allowed["user:cc2"]
    assert ("ingress", "declare_queryable", "arena/c1/cmd") in allowed["user:cc1"]
    assert ("ingress", "declare_queryable", "arena/c1/cmd") not in allowed["user:ground"]
    assert ("ingress", "query", "arena/*/cmd") in allowed["user:laptop"]
    assert not [a for a in allowed["user:cc1"] if a[:2] == ("ingress", "query") and "cmd" in a[2]]
    assert ("ingress", "liveliness_token", "arena/sys/alive/cc1/**") in allowed["user:cc1"]
    assert ("ingress", "put", "arena/sys/frames") in allowed["user:ground"]
    assert ("ingress", "declare_queryable", "arena/sys/time") in allowed["user:ground"]
    assert ("egress", "put", "arena/**") in allowed["user:laptop"]  # every host reads
    # An observer reads, nothing else; an identity nobody names matches no subject: the default, deny.
    acl = access_control(cfg, SecuritySpec(enabled=True, users_file="u", observers=("visitor",)))
    (policy,) = [p for p in acl["policies"] if p["subjects"] == ["user:visitor"]]
    observed = [rules_of for rules_of in acl["rules"] if rules_of["id"] in policy["rules"]]
    assert {m for r in observed for m in r["messages"]} <= {
        "put", "delete", "reply", "liveliness_token", "declare_subscriber", "declare_queryable",
        "declare_liveliness_subscriber", "liveliness_query",
    }  # fmt: skip
    assert all(r["flows"] == ["egress"] or "put" not in r["messages"] for r in observed)
    with pytest.raises(SecurityError, match="needs an identity"):
        access_control(cfg, SecuritySpec(enabled=True))
    with pytest.raises(SecurityError, match=r"command_hosts: 'nobody' is not a host"):
        access_control(cfg, SecuritySpec(enabled=True, users_file="u", command_hosts=("nobody",)))
    with pytest.raises(SecurityError, match=r"observers: 'cc1' is a host"):
        access_control(cfg, SecuritySpec(enabled=True, users_file="u", observers=("cc1",)))
    assert zenoh_json({"a/b": 1, "a/c": [2], "d": True}) == {"a": {"b": 1, "c": [2]}, "d": True}


def test_tls_is_required_off_the_machine(tmp_path: Path) -> None:
    with pytest.raises(
        config_mod.ConfigError, match=r"zenoh.router_listen: expected loopback endpoints only"
    ):
        lab(tmp_path, "tcp/192.0.2.1:7447")  # no [security]: nothing beyond loopback, unless insecure
    cfg = lab(tmp_path, "tcp/192.0.2.1:7447", "[security]\ninsecure = true\n")
    with pytest.raises(
        SecurityError, match=r"zenoh.router_listen: 'tcp/192.0.2.1:7447' leaves this computer"
    ):
        session_settings(cfg, SecuritySpec(enabled=True, tls=True), "cc1")
    assert session_settings(cfg, SecuritySpec(enabled=False, tls=True), "cc1") == {}
    with pytest.raises(SecurityError, match=r"security\.password_file: .*nope does not exist"):
        session_settings(
            lab(tmp_path, "tcp/127.0.0.1:1"), SecuritySpec(True, "u", str(tmp_path / "nope")), "cc1"
        )


class Net:
    """A router with the arena's security settings and one client session per "computer"."""

    def __init__(self, cfg: ArenaConfig, spec: SecuritySpec, endpoint: str) -> None:
        self.cfg, self.spec, self.endpoint = cfg, spec, endpoint
        settings = {"connect/endpoints": [], **router_settings(cfg, spec, "ground")}
        self.router = open_bus(
            ZenohSpec(mode="router", router_listen=(endpoint,)), BusOptions(settings=settings)
        )
        self.sessions: list[Bus] = [self.router]

    def host(self, name: str, **override: object) -> Bus:
        settings = {**session_settings(self.cfg, self.spec, name), **override}
        bus = open_bus(ZenohSpec(mode="client", connect=(self.endpoint,)), BusOptions(settings=settings))
        self.sessions.append(bus)
        return bus

    def close(self) -> None:
        for b in reversed(self.sessions):
            b.close()


@pytest.fixture
def nets() -> Iterator[list[Net]]:
    made: list[Net] = []
    yield made
    for n in made:
        n.close()


def state(marker: int) -> wire.State:
    """A State whose ``sysid`` tells the publications apart."""
    return wire.State(t=wire.now_ns(), sysid=marker)


def _delivered(sub_get: Callable[[], object], publish: Callable[[], None], tries: int = 30) -> bool:
    for _ in range(tries):
        publish()
        if sub_get() is not None:
            return True
    return False


def test_router_enforces_logins_ownership_and_commands(tmp_path: Path, nets: list[Net]) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = lab(tmp_path, endpoint)
    users, pw = make_credentials(cfg, tmp_path / "secrets")
    assert oct(users.stat().st_mode & 0o777) == "0o600" and set(pw) == {"ground", "cc1", "cc2", "laptop"}
    spec = SecuritySpec(
        enabled=True,
        users_file=str(users),
        password_file=str(tmp_path / "secrets" / "{host}.password"),
        command_hosts=("laptop",),
    )
    net = Net(cfg, spec, endpoint)
    nets.append(net)
    ground, cc1, cc2, laptop = (net.host(h) for h in ("ground", "cc1", "cc2", "laptop"))

    # A publication of c1's state from its own gateway host arrives; the same key from cc2 never does.
    sub = ground.subscribe(keys.state("c1"), capacity=100, ring=False)
    own = cc1.stream_publisher(keys.state("c1"), wire.State)
    assert _delivered(lambda: sub.get(0.1), lambda: own.put(state(1))), (
        "the owner's publication never arrived"
    )
    sub.channel.drain()
    intruder = cc2.stream_publisher(keys.state("c1"), wire.State)
    for _ in range(20):
        intruder.put(state(66))
    own.put(state(7))
    got = [sub.get(1.0), *sub.channel.drain()]
    assert [g.payload.sysid for g in got if g is not None and g.payload is not None] == [7]

    # Commands: the gateway host serves c1's cmd; the laptop may ask, cc2 may not.
    cc1.serve(keys.cmd("c1"), lambda key, cmd: wire.CommandResult(True, "ACCEPTED", reason=cmd.op))
    ask = wire.Command(op="hold")
    wait_for(lambda: laptop.request(keys.cmd("c1"), ask, 1.0).ok, timeout=10, what="the laptop's command")
    assert not cc2.request(keys.cmd("c1"), ask, 1.0).ok
    # cc2 cannot serve c1's commands either: the laptop's queries still reach only cc1.
    cc2.serve(keys.cmd("c1"), lambda key, cmd: wire.CommandResult(True, "ACCEPTED", reason="impostor"))
    assert {laptop.request(keys.cmd("c1"), ask, 1.0).reason for _ in range(5)} == {"hold"}

    # Presence under someone else's host name is refused.
    seen: list[str] = []
    ground.watch_alive("arena/sys/alive/**", lambda key, alive: seen.append(key) if alive else None)
    cc2.token(keys.alive("cc1", "gateway.c1"))
    cc2.token(keys.alive("cc2", "gateway.c2"))
    wait_for(lambda: "arena/sys/alive/cc2/gateway.c2" in seen, timeout=10, what="cc2's own presence")
    assert "arena/sys/alive/cc1/gateway.c1" not in seen

    # No login, or a wrong password: no session.
    with pytest.raises(BusError):
        net.host("laptop", **{"transport/auth/usrpwd/password": "wrong", "connect/timeout_ms": 0})
    with pytest.raises(BusError):
        open_bus(ZenohSpec(mode="client", connect=(endpoint,)))

    doc = write_zconfig(tmp_path / "z.json", session_settings(cfg, spec, "cc1"))
    assert oct(doc.stat().st_mode & 0o777) == "0o600"


def _openssl(*args: str) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=60)


def make_tls(d: Path, hosts: list[str]) -> None:
    """A throw-away lab CA and one certificate per host (CN = host name, valid for 127.0.0.1)."""
    d.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _openssl("req", "-x509", *ec, "-keyout", str(d / "ca.key"), "-out", str(d / "ca.pem"), "-days", "2",
             "-subj", "/CN=arena-test-ca")  # fmt: skip
    for h in hosts:
        _openssl("req", *ec, "-keyout", str(d / f"{h}.key"), "-out", str(d / f"{h}.csr"), "-subj", f"/CN={h}")
        ext = d / f"{h}.ext"
        ext.write_text(
            f"subjectAltName=DNS:{h},IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
            "extendedKeyUsage=serverAuth,clientAuth\nkeyUsage=digitalSignature\n"
        )
        ca = ["-CA", str(d / "ca.pem"), "-CAkey", str(d / "ca.key"), "-CAcreateserial"]
        _openssl("x509", "-req", "-in", str(d / f"{h}.csr"), *ca, "-out", str(d / f"{h}.pem"), "-days", "2",
                 "-extfile", str(ext))  # fmt: skip


@pytest.mark.skipif(
    shutil.which("openssl") is None, reason="openssl is not installed (needed to make test certificates)"
)
def test_mutual_tls_identifies_hosts_by_certificate(tmp_path: Path, nets: list[Net]) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    cfg = lab(tmp_path, endpoint)
    make_tls(tmp_path / "tls", ["ground", "cc1", "cc2"])
    t = str(tmp_path / "tls")
    spec = SecuritySpec(
        enabled=True, tls=True, mtls=True, ca=f"{t}/ca.pem", cert=t + "/{host}.pem", key=t + "/{host}.key"
    )
    net = Net(cfg, spec, endpoint)
    nets.append(net)
    ground, cc1, cc2 = (net.host(h) for h in ("ground", "cc1", "cc2"))
    sub = ground.subscribe(keys.state("c1"), capacity=100, ring=False)
    own = cc1.stream_publisher(keys.state("c1"), wire.State)
    assert _delivered(lambda: sub.get(0.1), lambda: own.put(state(1))), (
        "the owner's publication never arrived"
    )
    sub.channel.drain()
    bad = cc2.stream_publisher(keys.state("c1"), wire.State)
    for _ in range(20):
        bad.put(state(66))
    own.put(state(3))
    got = [sub.get(1.0), *sub.channel.drain()]
    assert [g.payload.sysid for g in got if g is not None and g.payload is not None] == [3]
    # Without a certificate from the lab CA: no session.
    with pytest.raises(BusError):
        open_bus(
            ZenohSpec(mode="client", connect=(endpoint,)),
            BusOptions(
                settings={"transport/link/tls/root_ca_certificate": f"{t}/ca.pem", "connect/timeout_ms": 0}
            ),
        )
