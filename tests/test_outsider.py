"""The outsider on the lab network: every port every arena process listens on, tried without the right identity.

Network namespaces this test creates (10.215.9.0/24): ``ground`` (router, Motive emulator, simulated
autopilots, mocap ingest, frame transform), ``cc1`` and ``cc2`` (a companion computer each, with its
vehicle's gateway), ``ops`` (the only ``command_hosts`` entry: the pilots' program flies d1) and
``outsider``.  The arena is the documented locked-down lab (``deploy/lab.example.toml``'s ``[security]``),
its credentials made by ``arena security init`` as a lab administrator types it, in both kinds: mutual
TLS with the lab's CA, and user/password.  Every computer runs ``arena up lab.toml --host NAME``.

The outsider lists every listening socket of the arena's computers (``ss``) and tries each: Zenoh with no
credentials (plain and TLS), a certificate of another CA or a wrong password, a lab identity that is no
host of the config (``visitor``), a non-commanding host's identity (``laptop``); unsigned, wrongly signed
and replayed MAVLink to every UDP port.  Nothing may arm, move, spoof a reading or divert a link, and d1
keeps flying.
"""

from __future__ import annotations

import json
import queue
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from arena_common.bus import pki
from arena_common.core.endpoints import is_loopback
from arena_common.mavlink.signing import LinkSigning, generate_key_file
from tests.conftest import wait_for
from tests.netnslib import Lab, drain, namespaces_usable

pytestmark = [pytest.mark.netns, pytest.mark.system]

SUBNET = "10.215.9"
ADDRESS = {
    "ground": f"{SUBNET}.1",
    "cc1": f"{SUBNET}.11",
    "cc2": f"{SUBNET}.12",
    "ops": f"{SUBNET}.21",
    "outsider": f"{SUBNET}.66",
}
ARENA = [str(Path(sys.executable).with_name("arena"))]
CONFIG = """
[arena]
name = "outsider"
[mocap]
server = "127.0.0.1"
interface = "127.0.0.1"
multicast = false
[zenoh]
mode = "client"
connect = ["{scheme}/{ground}:7447"]
router_listen = ["{scheme}/{ground}:7447"]
lease_ms = 2000
[security]
enabled = true
command_hosts = ["ops"]
{credentials}
[pipeline]
decimate = "transform"
[hosts.ground]
address = "{ground}"
services = ["router", "sim", "mocap", "transform"]
[hosts.cc1]
address = "{cc1}"
vehicles = ["d1"]
[hosts.cc2]
address = "{cc2}"
vehicles = ["d2"]
[hosts.ops]
address = "{ops}"
[hosts.laptop]
[vehicles.d1]
mavlink = "udpin:{cc1}:14541"
system_id = 1
signing_key_file = "keys/d1.key"
sim = {{ start = [-1.0, 0.0] }}
[vehicles.d2]
mavlink = "udpin:{cc2}:14542"
system_id = 2
signing_key_file = "keys/d2.key"
sim = {{ start = [1.0, 0.0] }}
"""
TLS = (
    'tls = true\nmtls = true\nca = "secrets/ca.pem"\ncert = "secrets/{host}.pem"\nkey = "secrets/{host}.key"'
)
PASSWORD = 'users_file = "secrets/users.txt"\npassword_file = "secrets/{host}.password"'


@pytest.fixture
def lab() -> Iterator[Lab]:
    reason = namespaces_usable()
    if reason:
        pytest.skip(reason)
    the_lab = Lab(ADDRESS)
    try:
        the_lab.build()
        yield the_lab
    finally:
        the_lab.teardown()


def typed(*argv: str, cwd: Path) -> str:
    """Run an ``arena`` command as the administrator types it; its output (it must succeed)."""
    import subprocess

    res = subprocess.run([*ARENA, *argv], cwd=cwd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, f"arena {' '.join(argv)}: {res.returncode}\n{res.stdout}\n{res.stderr}"
    return res.stdout


def replay_frame(key_file: Path, sysid: int) -> str:
    """A frame the vehicle really signed, 10 s ago: what a recording of the radio would hold."""
    from arena_common.mavlink.signing import load_key

    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    LinkSigning(load_key(key_file), link_id=0, clock=lambda: time.time() - 10.0).attach(mav)
    return bytes(mav.radio_status_encode(200, 200, 100, 0, 0, 0, 0).pack(mav)).hex()


def identities(kind: str, d: Path, endpoint: str) -> dict[str, tuple[str, dict[str, Any]]]:
    """The identities the outsider tries, each with its endpoint and Zenoh settings."""
    s = d / "secrets"
    if kind == "tls":
        other = d / "other-ca"
        other.mkdir()
        pki.make_ca(other, "impostor")
        pki.issue_certificate(other / "ca.pem", other / "ca.key", "ops", other)
        pki.issue_certificate(s / "ca.pem", s / "ca.key", "visitor", s)  # the lab CA's, but no host

        def cert(folder: Path, name: str) -> dict[str, Any]:
            return {
                "transport/link/tls/root_ca_certificate": str(s / "ca.pem"),
                "transport/link/tls/connect_certificate": str(folder / f"{name}.pem"),
                "transport/link/tls/connect_private_key": str(folder / f"{name}.key"),
                "transport/link/tls/enable_mtls": True,
            }

        return {
            "another CA's 'ops'": (endpoint, cert(other, "ops")),
            "visitor": (endpoint, cert(s, "visitor")),
            "laptop": (endpoint, cert(s, "laptop")),
        }
    users = s / "users.txt"
    users.write_text(
        users.read_text() + "visitor:visitor-password\n"
    )  # the router knows it; the config does not

    def login(user: str, password: str) -> dict[str, Any]:
        return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}

    return {
        "wrong password for 'ops'": (endpoint, login("ops", "not-the-password")),
        "visitor": (endpoint, login("visitor", "visitor-password")),
        "laptop": (endpoint, login("laptop", (s / "laptop.password").read_text().strip())),
    }


class Reader:
    """The JSON lines of a process, the latest report and every other message."""

    def __init__(self, lines: queue.Queue[str]) -> None:
        self.lines, self.raw = lines, []  # type: ignore[var-annotated]
        self.latest: dict[str, Any] = {}
        self.messages: list[dict[str, Any]] = []

    def pump(self) -> dict[str, Any]:
        for line in drain(self.lines, []):
            self.raw.append(line)
            if line.startswith("{"):
                msg = json.loads(line)
                if "t" in msg and "d1" in msg:
                    self.latest = msg
                else:
                    self.messages.append(msg)
        return self.latest


@pytest.mark.timeout(600)
@pytest.mark.parametrize("kind", ["tls", "password"])
def test_outsider_cannot_command_spoof_or_divert(lab: Lab, tmp_path: Path, kind: str) -> None:
    scheme = "tls" if kind == "tls" else "tcp"
    credentials = TLS if kind == "tls" else PASSWORD
    cfg = tmp_path / "lab.toml"
    cfg.write_text(CONFIG.format(scheme=scheme, credentials=credentials, **ADDRESS))
    (tmp_path / "keys").mkdir()
    for v in ("d1", "d2"):
        generate_key_file(tmp_path / "keys" / f"{v}.key")
    print(typed("security", "init", "lab.toml", cwd=tmp_path))
    typed("security", "check", "lab.toml", cwd=tmp_path)
    # Identities the router knows of (a lab certificate, a dictionary entry) that the config does not name.
    tried = identities(kind, tmp_path, f"{scheme}/{ADDRESS['ground']}:7447")
    dry = typed("up", "lab.toml", "--host", "cc1", "--dry-run", cwd=tmp_path)
    assert "--listen" not in dry and "--mode peer" not in dry, dry

    logs: dict[str, list[str]] = {h: [] for h in ("ground", "cc1", "cc2")}
    outs = {}
    for host in logs:
        _, outs[host] = lab.spawn(host, *ARENA, "up", str(cfg), "--host", host)

    def context() -> str:
        for h, q in outs.items():
            drain(q, logs[h])
        tails = "\n".join(f"--- {h}\n{''.join(lines[-20:])}" for h, lines in logs.items())
        return f"{json.dumps(ops.latest)[:1500]}\n{''.join(ops.raw[-10:])}\n{tails}"

    def router_up() -> bool:
        drain(outs["ground"], logs["ground"])
        return any("routing on" in line for line in logs["ground"])

    wait_for(router_up, timeout=60, what="the router")
    ops_proc, ops_lines = lab.spawn("ops", sys.executable, "-m", "tests.outsider_ops", str(cfg), stdin=True)
    ops = Reader(ops_lines)
    try:
        wait_for(
            lambda: ops.pump() and any("airborne" in m for m in ops.messages), 180, 0.2, what="d1 airborne"
        )
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{context()}") from None
    assert not [m for m in ops.messages if "error" in m], context()

    # Every socket the arena's computers listen on: only the router's (authenticated) port leaves a
    # computer over TCP; the UDP ones are MAVLink links (signed here) and the simulated autopilots.
    tcp: list[tuple[str, int]] = []
    udp: list[tuple[str, int]] = []
    for host in ("ground", "cc1", "cc2"):
        for proto, address, port in lab.listening(host):
            if is_loopback(address):
                continue
            target = (ADDRESS[host] if address in ("0.0.0.0", "*", "::") else address, port)
            (tcp if proto == "tcp" else udp).append(target)
    assert tcp == [(ADDRESS["ground"], 7447)], f"TCP listeners beyond loopback: {tcp}"
    assert (ADDRESS["cc1"], 14541) in udp and (ADDRESS["cc2"], 14542) in udp, udp

    spec: dict[str, Any] = {
        "vehicles": {"d1": 1, "d2": 2},
        "ca": str(tmp_path / "secrets" / "ca.pem") if kind == "tls" else "",
        "tcp": tcp,
        "udp": udp,
        "identities": tried,
        "replays": {v: replay_frame(tmp_path / "keys" / f"{v}.key", i) for i, v in ((1, "d1"), (2, "d2"))},
    }
    spec_file = tmp_path / "attack.json"
    spec_file.write_text(json.dumps(spec))
    _, attack_lines = lab.spawn("outsider", sys.executable, "-m", "tests.outsider_attack", str(spec_file))
    attack = Reader(attack_lines)
    wait_for(lambda: attack.pump() is not None and any(m.get("done") for m in attack.messages), 240, 0.5,
             what="the outsider's attempts")  # fmt: skip
    results = {
        m.get("attempt", "") + " " + m.get("endpoint", ""): m for m in attack.messages if "attempt" in m
    }
    print(json.dumps(results, indent=1))

    for name, r in results.items():
        if name.startswith("no credentials") or name.startswith(("another CA", "wrong password")):
            assert not r["opened"], f"{name}: a session opened: {r}"
    visitor = results[f"visitor {spec['identities']['visitor'][0]}"]
    laptop = results[f"laptop {spec['identities']['laptop'][0]}"]
    # A lab identity that is no host of the config gets nothing: not one sample, no command answered.
    assert visitor["seen"] == 0, visitor
    assert all("True" not in a for a in visitor["answers"].values()), visitor
    # A non-commanding host reads (it is a host) but commands nothing.
    assert laptop["seen"] > 0, laptop
    assert all("True" not in a for a in laptop["answers"].values()), laptop
    assert results["mavlink "]["diverted_bytes"] == 0, results["mavlink "]

    # The pilots saw no spoofed state or estop, d2 never armed, d1 flew on with its vision fused.
    report = ops.pump()
    assert report["n_spoofed"] == 0, report["spoofed"]
    assert report["d2"]["armed"] is False and report["d2"]["mode"] != "SPOOFED", report
    assert report["d1"]["armed"] and report["d1"]["z"] < -0.7 and report["d1"]["fused"], report
    assert report["d1"]["link"] and report["d2"]["link"], report
    north, east, _ = report["d1"]["p"]
    assert abs(north + 1.0) < 0.25 and abs(east) < 0.25, f"d1 moved: {report['d1']}"
    # What the links dropped is counted by reason in each gateway's stats, never silently.
    for gateway in ("gateway.d1", "gateway.d2"):
        dropped = report["rejected"].get(gateway, {})
        signing = {k: n for k, n in dropped.items() if k.startswith(("signing", "mavlink"))}
        assert sum(signing.values()) > 0, f"{gateway}: nothing counted: {dropped}"
    assert ops_proc.stdin is not None
    ops_proc.stdin.write("land\n")
    ops_proc.stdin.flush()
    wait_for(lambda: ops.pump() is not None and any("landed" in m for m in ops.messages), 90, 0.2,
             what="d1 landed")  # fmt: skip

    # What the link dropped is counted and named in the gateways' logs, never silently.
    for h, q in outs.items():
        drain(q, logs[h])
    print(context())
