"""The README's lab steps on network namespaces, then the outsider on every port of that locked-down lab.

Namespaces this test creates (10.215.9.0/24) stand for the lab's computers of ``deploy/lab.example.toml``:
``ground`` (router, mocap ingest, frame transform, recorder; here also the Motive emulator and the
simulated autopilots, standing where the cameras and vehicles would be), ``cc1`` and ``cc2`` (a companion
computer each, with its vehicle's gateway) and ``outsider``.  The config is the shipped example with only
what a namespace lab needs substituted (addresses, simulated autopilots on UDP links instead of
serial lines, a temporary recordings folder), in both credential kinds: mutual TLS as shipped, and
user/password.  Every step is typed as the README gives it: ``arena security init``, ``arena security
check``, ``arena config check``, ``arena up lab.toml --host NAME`` on each computer, ``arena status``.

The pilots' program flies c1 from the ground computer (the only ``command_hosts`` entry).  The outsider
lists every listening socket of the arena's computers (``ss``) and tries each: Zenoh with no credentials
(plain and TLS), a certificate of another CA or a wrong password, a lab identity that is no host of the
config (``visitor``), a non-commanding host's identity (a researcher's ``laptop``, added to the
config); unsigned, wrongly signed and replayed MAVLink to every UDP port.  Nothing may arm, move, spoof
a reading or divert a link, and c1 keeps flying.
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
from tests.helpers import REPO, wait_for
from tests.netnslib import Lab, drain, namespaces_usable

pytestmark = [pytest.mark.netns, pytest.mark.system]

SUBNET = "10.215.9"
ADDRESS = {
    "ground": f"{SUBNET}.1",
    "cc1": f"{SUBNET}.11",
    "cc2": f"{SUBNET}.12",
    "outsider": f"{SUBNET}.66",
}
ARENA = [str(Path(sys.executable).with_name("arena"))]
VEHICLES = """
[vehicles.c1]
rigid_body = "c1"
mavlink = "udpin:{cc1}:14541"
system_id = 11
signing_key_file = "keys/c1.key"
sim = {{ start = [-1.0, 0.0] }}

[vehicles.c2]
rigid_body = "c2"
mavlink = "udpin:{cc2}:14542"
system_id = 12
signing_key_file = "keys/c2.key"
sim = {{ start = [1.0, 0.0] }}

[vehicles.c3]
rigid_body = 3
mavlink = "udpin:127.0.0.1:14543"
system_id = 13
vision_rate = 30.0
state_rate = 20.0
telemetry_rate = 2.0
sim = {{ start = [0.0, 1.0] }}
"""
SYSIDS = {"c1": 11, "c2": 12, "c3": 13}


def lab_config(kind: str, directory: Path) -> str:
    """``deploy/lab.example.toml`` for the namespaces: their addresses, the Motive emulator and simulated
    autopilots on the ground computer (signed UDP where a link crosses the network), recordings in
    ``directory``; with ``kind`` "password", user/password logins over TCP instead of mutual TLS."""
    text = (REPO / "deploy" / "lab.example.toml").read_text()
    for lab_address, host in (("192.168.1.20", "ground"), ("192.168.1.31", "cc1"), ("192.168.1.32", "cc2")):
        text = text.replace(f'"{lab_address}', f'"{ADDRESS[host]}').replace(
            f"/{lab_address}:", f"/{ADDRESS[host]}:"
        )
    text = text.replace('server = "192.168.1.10"', 'server = "127.0.0.1"')
    text = text.replace(f'interface = "{ADDRESS["ground"]}"', 'interface = "127.0.0.1"')
    text = text.replace("multicast = true", "multicast = false")
    text = text.replace('services = ["router", "mocap", "transform", "recorder"]',
                        'services = ["router", "sim", "mocap", "transform", "recorder"]')  # fmt: skip
    text = text.replace('"/var/lib/arena/recordings"', f'"{directory / "recordings"}"')
    laptop = "[hosts.laptop]  # a researcher's laptop: reads the arena, commands nothing\n\n"
    vehicles = VEHICLES.format(**ADDRESS) + "\n"
    text = text[: text.index("# autopilot = ")] + laptop + vehicles + text[text.index("[recorder]") :]
    assert text.count("[vehicles.") == 3, text
    if kind == "password":
        text = text.replace('"tls/', '"tcp/')
        start = text.index("tls = true")
        end = text.index("command_hosts")
        text = text[:start] + PASSWORD + "\n" + text[end:]
    return text


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
                if "n_spoofed" in msg:
                    self.latest = msg
                else:
                    self.messages.append(msg)
        return self.latest


@pytest.mark.timeout(600)
@pytest.mark.parametrize("kind", ["tls", "password"])
@pytest.mark.covers(
    "arena security init lab.toml",
    "arena security check lab.toml",
    "arena config check lab.toml",
    "arena up lab.toml --host ground",
    "arena up lab.toml --host cc1",
    "arena status -c lab.toml",
)
def test_lab_steps_then_the_outsider_cannot_command_spoof_or_divert(
    lab: Lab, tmp_path: Path, kind: str
) -> None:
    scheme = "tls" if kind == "tls" else "tcp"
    cfg = tmp_path / "lab.toml"
    cfg.write_text(lab_config(kind, tmp_path))
    (tmp_path / "keys").mkdir()
    for v in ("c1", "c2"):  # their links cross the network: signed (c3's stays on the ground's loopback)
        generate_key_file(tmp_path / "keys" / f"{v}.key")
    # The README's lab steps, as typed on the ground computer (the credentials are copied to each host:
    # here the namespaces share this folder).
    print(typed("security", "init", "lab.toml", cwd=tmp_path))
    typed("security", "check", "lab.toml", cwd=tmp_path)
    typed("config", "check", "lab.toml", cwd=tmp_path)
    # Identities the router knows of (a lab certificate, a dictionary entry) that the config does not name.
    tried = identities(kind, tmp_path, f"{scheme}/{ADDRESS['ground']}:7447")
    for host in ("cc1", "cc2"):
        dry = typed("up", "lab.toml", "--host", host, "--dry-run", cwd=tmp_path)
        assert "--listen" not in dry and "--mode peer" not in dry, dry

    logs: dict[str, list[str]] = {h: [] for h in ("ground", "cc1", "cc2")}
    outs = {}
    for host in logs:
        _, outs[host] = lab.spawn(host, *ARENA, "up", "lab.toml", "--host", host, cwd=tmp_path)

    def context() -> str:
        for h, q in outs.items():
            drain(q, logs[h])
        tails = "\n".join(f"--- {h}\n{''.join(lines[-20:])}" for h, lines in logs.items())
        return f"{json.dumps(ops.latest)[:1500]}\n{''.join(ops.raw[-10:])}\n{tails}"

    def router_up() -> bool:
        drain(outs["ground"], logs["ground"])
        return any("routing on" in line for line in logs["ground"])

    wait_for(router_up, timeout=60, what="the router")
    pilots = [sys.executable, "-m", "tests.outsider_ops", str(cfg), "ground", "c1"]
    ops_proc, ops_lines = lab.spawn("ground", *pilots, stdin=True)
    ops = Reader(ops_lines)
    try:
        wait_for(lambda: ops.pump() is not None and any("airborne" in m for m in ops.messages), 180, 0.2,
                 what="c1 airborne")  # fmt: skip
    except (AssertionError, TimeoutError) as exc:
        raise AssertionError(f"{exc}\n{context()}") from None
    assert not [m for m in ops.messages if "error" in m], context()
    status_proc, status_lines = lab.spawn(
        "ground", *ARENA, "status", "-c", "lab.toml", cwd=tmp_path, env={"ARENA_HOST": "ground"}
    )
    assert status_proc.wait(timeout=60) == 0
    status = "".join(drain(status_lines, []))
    for expected in ("gateway.c1", "gateway.c2", "gateway.c3", "router", "transform"):
        assert expected in status, status

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
    # UDP: the gateways' links of c1 and c2, and the simulated autopilots of c1 and c2 on the ground's
    # address that faces them; c3's link (unsigned) stays on the ground's loopback, out of the outsider's reach.
    assert (ADDRESS["cc1"], 14541) in udp and (ADDRESS["cc2"], 14542) in udp, udp
    assert sorted(address for address, _ in udp) == sorted(
        [ADDRESS["ground"]] * 2 + [ADDRESS["cc1"], ADDRESS["cc2"]]
    ), udp

    spec: dict[str, Any] = {
        "vehicles": SYSIDS,
        "ca": str(tmp_path / "secrets" / "ca.pem") if kind == "tls" else "",
        "tcp": tcp,
        "udp": udp,
        "identities": tried,
        "replays": {v: replay_frame(tmp_path / "keys" / f"{v}.key", SYSIDS[v]) for v in ("c1", "c2")},
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
    visitor = results[f"visitor {tried['visitor'][0]}"]
    companion = results[f"laptop {tried['laptop'][0]}"]
    # A lab identity that is no host of the config gets nothing: not one sample, no command answered.
    assert visitor["seen"] == 0, visitor
    assert all("True" not in a for a in visitor["answers"].values()), visitor
    # A non-commanding host reads (it is a host) but commands nothing.
    assert companion["seen"] > 0, companion
    assert all("True" not in a for a in companion["answers"].values()), companion
    assert results["mavlink "]["diverted_bytes"] == 0, results["mavlink "]

    # The pilots saw no spoofed state or estop, c2/c3 never armed, c1 flew on with its vision fused.
    report = ops.pump()
    assert report["n_spoofed"] == 0, report["spoofed"]
    for other in ("c2", "c3"):
        assert report[other]["armed"] is False and report[other]["mode"] != "SPOOFED", report
    c1 = report["c1"]
    assert c1["armed"] and c1["z"] < -0.7 and c1["fused"], json.dumps(
        {"c1": c1, "rejected": report["rejected"]}
    )
    assert all(report[v]["link"] for v in SYSIDS), report
    north, east, _ = report["c1"]["p"]
    assert abs(north + 1.0) < 0.25 and abs(east) < 0.25, f"c1 moved: {report['c1']}"
    # What the links dropped is counted by reason in each gateway's stats, never silently.
    for gateway in ("gateway.c1", "gateway.c2"):
        dropped = report["rejected"].get(gateway, {})
        assert sum(n for k, n in dropped.items() if k.startswith("mavlink")) > 0, f"{gateway}: {dropped}"
    assert ops_proc.stdin is not None
    ops_proc.stdin.write("land\n")
    ops_proc.stdin.flush()
    wait_for(lambda: ops.pump() is not None and any("landed" in m for m in ops.messages), 90, 0.2,
             what="c1 landed")  # fmt: skip
    print(context())
