"""A locked-down lab from its config: default exposure, secured sessions, the lab CA, `arena security` as typed.

Fast and local: configs parsed, settings computed, certificates made and checked, commands run as an
administrator types them.  The router enforcing the rules is in ``test_security.py``; the outsider on
the lab network in ``test_outsider.py``.
"""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from arena_common.bus import exposure, pki, security
from arena_common.bus.hosts import host_bus_options
from arena_common.bus.session import BusOptions
from arena_common.core import config as config_mod
from arena_common.core.errors import ConfigError
from arena_common.runtime.ports import fixed_ports, taken_ports
from tests.helpers import REPO, free_port

ARENA = str(Path(sys.executable).with_name("arena"))
LAB_EXAMPLE = REPO / "deploy" / "lab.example.toml"

OPEN = """
[zenoh]
connect = ["tcp/10.0.0.1:7447"]
router_listen = ["{listen}"]
[hosts.ground]
address = "{address}"
services = ["router", "mocap", "transform"]
vehicles = ["c1"]
[vehicles.c1]
autopilot = "px4"
mavlink = "{mavlink}"
system_id = 1
{extra}
"""


def parse(listen: str = "tcp/127.0.0.1:7447", address: str = "", mavlink: str = "udpin:127.0.0.1:14540",
          extra: str = "") -> config_mod.ArenaConfig:  # fmt: skip
    import tomllib

    text = OPEN.format(listen=listen, address=address, mavlink=mavlink, extra=extra)
    return exposure.parse(tomllib.loads(text), "lab.toml")


def test_nothing_listens_beyond_loopback_unauthenticated_unless_the_config_says_insecure() -> None:
    parse()  # everything on loopback: fine
    with pytest.raises(ConfigError, match=r"lab.toml: zenoh.router_listen: expected loopback endpoints only"):
        parse(listen="tcp/0.0.0.0:7447")
    with pytest.raises(ConfigError, match=r"hosts.ground.address: expected no address to listen on"):
        parse(address="192.168.1.20")
    with pytest.raises(
        ConfigError, match=r"vehicles.c1.mavlink: expected an unsigned MAVLink link listening"
    ):
        parse(mavlink="udpin:0.0.0.0:14550")
    # Signed, or pinned to the autopilot's address: the link is authenticated (or cannot be diverted).
    parse(mavlink="udpin:0.0.0.0:14550", extra='signing_key_file = "c1.key"')
    parse(mavlink="udpin:0.0.0.0:14550", extra='mavlink_peer = "192.168.1.41:14555"')
    with pytest.raises(
        ConfigError, match=r"vehicles.c1.gcs: expected a ground-station link on loopback only"
    ):
        parse(extra='gcs = "udpin:0.0.0.0:14550"')
    parse(extra='gcs = "udpout:192.168.1.50:14550"')  # sends to the GCS; answers come from where it sends
    insecure = parse(listen="tcp/0.0.0.0:7447", address="192.168.1.20", extra="[security]\ninsecure = true")
    assert insecure.security.insecure and not insecure.security.enabled


def test_an_insecure_arena_says_so_at_every_start(caplog: pytest.LogCaptureFixture) -> None:
    cfg = parse(listen="tcp/0.0.0.0:7447", extra="[security]\ninsecure = true")
    with caplog.at_level(logging.WARNING, logger="arena.security"):
        host_bus_options(cfg, "ground", None)
        host_bus_options(cfg, "ground", None)
    warnings = [r.getMessage() for r in caplog.records if "security.insecure = true" in r.getMessage()]
    assert len(warnings) == 2 and "accept anyone on the network" in warnings[0]


def _secured(tmp_path: Path) -> config_mod.ArenaConfig:
    text = LAB_EXAMPLE.read_text()
    (tmp_path / "lab.toml").write_text(text)
    return config_mod.load(tmp_path / "lab.toml")


def test_every_session_of_a_secured_arena_is_a_client_of_its_router(tmp_path: Path) -> None:
    cfg = _secured(tmp_path)
    pki.init_lab(tmp_path / "secrets", "lab", {h: s.address for h, s in cfg.hosts.items()})
    opts = host_bus_options(cfg, "cc1", BusOptions())
    assert opts.mode == "client" and opts.listen == () and opts.address == ""
    assert opts.settings["listen/endpoints"] == []
    assert opts.settings["transport/link/tls/connect_certificate"] == str(tmp_path / "secrets" / "cc1.pem")
    router = host_bus_options(cfg, "ground", BusOptions(mode="router", listen=("tls/192.168.1.20:7447",)))
    assert router.mode == "router" and router.listen == ("tls/192.168.1.20:7447",)
    with pytest.raises(security.SecurityError, match="--mode peer on a secured arena"):
        host_bus_options(cfg, "cc1", BusOptions(mode="peer"))
    with pytest.raises(security.SecurityError, match="--listen on a secured arena"):
        host_bus_options(cfg, "cc1", BusOptions(listen=("tcp/0.0.0.0:0",)))


def test_the_shipped_lab_recipe_is_locked_down() -> None:
    cfg = config_mod.load(LAB_EXAMPLE)
    spec = cfg.security
    assert spec.enabled and spec.tls and spec.mtls and spec.acl and not spec.insecure
    assert spec.command_hosts and set(spec.command_hosts) <= set(cfg.hosts)
    assert cfg.zenoh.mode == "client"
    assert all(e.startswith("tls/") for e in (*cfg.zenoh.router_listen, *cfg.zenoh.connect))
    acl = security.access_control(cfg, spec)
    assert acl["default_permission"] == "deny"


def test_the_lab_ca_certificates_and_what_check_finds(tmp_path: Path) -> None:
    d = tmp_path / "secrets"
    certificates = pki.init_lab(d, "lab", {"ground": "192.168.1.20", "cc1": ""})
    assert oct(d.stat().st_mode & 0o777) == "0o700"
    assert oct((d / "ca.key").stat().st_mode & 0o777) == "0o600"
    assert oct((d / "cc1.key").stat().st_mode & 0o777) == "0o600"
    assert [
        p for n, (pem, key) in certificates.items() for p in pki.check_certificate(d / "ca.pem", pem, key, n)
    ] == []
    with pytest.raises(pki.PkiError, match="a lab CA is already there"):
        pki.init_lab(d, "lab", {"ground": ""})
    # A certificate of another CA, or under another name, or a key others may read: each named.
    other = tmp_path / "other"
    other.mkdir()
    pki.make_ca(other, "impostor")
    pki.issue_certificate(other / "ca.pem", other / "ca.key", "cc1", other)
    (problem,) = pki.check_certificate(d / "ca.pem", other / "cc1.pem", other / "cc1.key", "cc1")
    assert "not signed by the lab CA" in problem
    (problem,) = pki.check_certificate(d / "ca.pem", d / "cc1.pem", d / "cc1.key", "cc2")
    assert "common name 'cc1' is not the host name 'cc2'" in problem
    (d / "cc1.key").chmod(0o644)
    (problem,) = pki.check_certificate(d / "ca.pem", d / "cc1.pem", d / "cc1.key", "cc1")
    assert "readable by others (mode 0644)" in problem


def typed(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([ARENA, *argv], cwd=cwd, capture_output=True, text=True, timeout=60)


@pytest.mark.covers("arena security init", "arena security check", "arena security rules")
def test_arena_security_as_an_administrator_types_it(tmp_path: Path) -> None:
    (tmp_path / "lab.toml").write_text(LAB_EXAMPLE.read_text())
    failed = typed("security", "check", "lab.toml", cwd=tmp_path)
    assert failed.returncode == 1 and "security.ca:" in failed.stderr and "does not exist" in failed.stderr
    made = typed("security", "init", "lab.toml", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    assert {p.name for p in (tmp_path / "secrets").iterdir()} == {
        "ca.pem", "ca.key", *(f"{h}.{x}" for h in ("ground", "cc1", "cc2") for x in ("pem", "key"))
    }  # fmt: skip
    ok = typed("-c", "lab.toml", "security", "check", cwd=tmp_path)
    assert ok.returncode == 0 and "ok — 3 host(s) with mutual TLS" in ok.stdout, ok.stderr
    (tmp_path / "secrets" / "cc2.key").chmod(0o640)
    bad = typed("security", "check", "--config", "lab.toml", "--host", "cc2", cwd=tmp_path)
    assert bad.returncode == 1 and "cc2.key is readable by others" in bad.stderr
    again = typed("security", "init", "lab.toml", cwd=tmp_path)
    assert again.returncode == 2 and "a lab CA is already there" in again.stderr
    rules = typed("security", "rules", "lab.toml", cwd=tmp_path)
    assert rules.returncode == 0 and json.loads(rules.stdout)["default_permission"] == "deny"
    dry = typed("up", "lab.toml", "--host", "cc1", "--dry-run", cwd=tmp_path)
    assert dry.returncode == 0 and "--listen" not in dry.stdout and "gateway.c1" in dry.stdout


def test_passwords_for_a_password_lab(tmp_path: Path) -> None:
    text = LAB_EXAMPLE.read_text().replace(
        "tls = true                  # TLS on every endpoint that leaves a computer\n", ""
    )
    text = text.replace(
        "mtls = true", 'users_file = "secrets/users.txt"\npassword_file = "secrets/{host}.password"'
    )
    text = text.replace('"tls/192.168.1.20:7447"', '"tcp/192.168.1.20:7447"')
    (tmp_path / "lab.toml").write_text(text)
    made = typed("security", "init", "lab.toml", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    users = (tmp_path / "secrets" / "users.txt").read_text().split()
    assert [u.split(":")[0] for u in users] == ["ground", "cc1", "cc2"]
    assert oct((tmp_path / "secrets" / "cc1.password").stat().st_mode & 0o777) == "0o600"
    ok = typed("security", "check", "lab.toml", cwd=tmp_path)
    assert ok.returncode == 0 and "passwords" in ok.stdout, ok.stderr


def test_arena_up_refuses_a_taken_port_naming_its_field_before_starting_anything(tmp_path: Path) -> None:
    port, udp = free_port(), free_port(socket.SOCK_DGRAM)
    cfg = tmp_path / "arena.toml"
    cfg.write_text(
        f'[zenoh]\nconnect = ["tcp/127.0.0.1:{port}"]\nrouter_listen = ["tcp/127.0.0.1:{port}"]\n'
        f'[hosts.ground]\nservices = ["router"]\nvehicles = ["d1"]\n'
        f'[vehicles.d1]\nmavlink = "udpin:127.0.0.1:{udp}"\nsystem_id = 1\n'
    )
    loaded = config_mod.load(cfg)
    assert [str(p) for p in fixed_ports(loaded, "ground")] == [
        f"zenoh.router_listen (tcp 127.0.0.1:{port})",
        f"vehicles.d1.mavlink (udp 127.0.0.1:{udp})",
    ]
    with socket.socket() as holder, socket.socket(type=socket.SOCK_DGRAM) as udp_holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        udp_holder.bind(("127.0.0.1", udp))
        assert len(taken_ports(loaded, "ground")) == 2
        res = typed("up", str(cfg), "--host", "ground", cwd=tmp_path)
    assert res.returncode == 2
    assert f"zenoh.router_listen (tcp 127.0.0.1:{port}) is taken" in res.stderr
    assert f"vehicles.d1.mavlink (udp 127.0.0.1:{udp}) is taken" in res.stderr
    assert "starting" not in res.stdout and "nothing started" in res.stderr
    assert taken_ports(loaded, "ground") == []


def test_a_host_that_may_not_command_is_told_so_not_timed_out(tmp_path: Path) -> None:
    from arena_common import Arena, NotPermitted
    from arena_common.bus.session import open_bus

    cfg = _secured(tmp_path)  # command_hosts = ["ground"]
    bus = open_bus(None, BusOptions(mode="peer", listen=(f"tcp/127.0.0.1:{free_port()}",)))
    with Arena(cfg, bus=bus, host="cc1") as arena, pytest.raises(NotPermitted) as err:
        arena.vehicle("c1").arm()
    bus.close()
    assert "host 'cc1' may not command vehicles (security.command_hosts = ['ground'])" in str(err.value)


def test_the_live_view_stays_on_loopback_unless_made_public(tmp_path: Path) -> None:
    res = typed("view", "--address", "0.0.0.0", "--port", "0", cwd=tmp_path)
    assert res.returncode == 2 and "--address 0.0.0.0: the live view has no login" in res.stderr
    assert "--public" in res.stderr
