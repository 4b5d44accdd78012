"""Who may move a gateway's MAVLink link: real UDP sockets on loopback, real MAVLink bytes from pymavlink.

The gateway listens (``udpin:``) and replies to the address the vehicle's frames come from.  Another host
is another loopback address (127.0.0.2, 127.0.0.3) or another port.  On a signed link only a frame whose
signature verified moves the link: a flood of unsigned RADIO_STATUS (let through by design: radios cannot
sign), a frame signed with another key and a replayed one are taken as data or dropped, never as the
vehicle's new address.  With a pinned peer (``mavlink_peer``) datagrams from any other address are
dropped, counted and logged.  Without either, anyone who can reach the port is taken for the vehicle:
the documented risk of docs/safety.md §3.3.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.mavlink import px4
from arena_common.mavlink.link import MSG, Frame, FrameSplitter, MavlinkLink, MavlinkLinkError
from arena_common.mavlink.signing import LinkSigning, SigningKey, generate_key_file
from arena_common.runtime.options import read_config
from tests.helpers import free_port
from tests.unit.core.test_config import BASE, write
from tests.unit.mavlink.test_signing import encoder

ODOMETRY = 331


class Host:
    """A UDP socket on its own loopback address: the vehicle, an attacker, the vehicle after a move."""

    def __init__(self, ip: str, to: tuple[str, int], port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((ip, port))
        self.sock.setblocking(False)
        self.addr: tuple[str, int] = self.sock.getsockname()
        self.to = to

    def send(self, *frames: bytes) -> None:
        """One datagram carrying ``frames``."""
        self.sock.sendto(b"".join(frames), self.to)

    def received(self, wait: float = 0.2) -> list[Frame]:
        """Every frame that arrived, waiting until nothing more comes for ``wait`` s."""
        splitter = FrameSplitter(stream=False)
        out: list[Frame] = []
        while select.select([self.sock], [], [], wait)[0]:
            data, _ = self.sock.recvfrom(65535)
            out += splitter.feed(data)
        return out

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def hosts() -> Iterator[Callable[..., Host]]:
    opened: list[Host] = []

    def make(ip: str, to: tuple[str, int], port: int = 0) -> Host:
        opened.append(Host(ip, to, port))
        return opened[-1]

    yield make
    for h in opened:
        h.close()


@pytest.fixture
def key(tmp_path: Path) -> SigningKey:
    return generate_key_file(tmp_path / "d1.key")


def listening_link(**kwargs: Any) -> tuple[MavlinkLink, tuple[str, int]]:
    port = free_port(socket.SOCK_DGRAM)
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, **kwargs)
    link.open()
    return link, ("127.0.0.1", port)


def read_until(link: MavlinkLink, done: Callable[[], bool], timeout: float = 2.0) -> list[Frame]:
    """Read the link until ``done()``; every frame it returned."""
    got: list[Frame] = []
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "the link did not read what was sent"
        got += link.read(0.02)
    return got


def reaches(count: Callable[[], int], n: int) -> Callable[[], bool]:
    """A condition for :func:`read_until`: ``count()`` is at least ``n``."""
    return lambda: count() >= n


def odometry(link: MavlinkLink, i: int) -> Any:
    return link.mav.odometry_encode(**px4.odometry_args(i, (0.0, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0)))


def pack(mav: Any, msg: Any) -> bytes:
    return bytes(msg.pack(mav))


def heartbeat(mav: Any) -> bytes:
    return pack(mav, mav.heartbeat_encode(2, 12, 0, 0, 3))


def radio_status(mav: Any) -> bytes:
    return pack(mav, mav.radio_status_encode(200, 190, 90, 10, 12, 0, 0))


def sent_to(host: Host, msgid: int) -> int:
    return sum(1 for f in host.received() if f.msgid == msgid)


# ------------------------------------------------------------------------------------------ signed link
def test_signed_link_moves_only_for_a_verified_signature(
    hosts: Callable[..., Host], key: SigningKey, tmp_path: Path
) -> None:
    signing = LinkSigning(key)
    rejected: list[str] = []
    link, at = listening_link(signing=signing, on_reject=lambda reason, frame: rejected.append(reason))
    try:
        vehicle, attacker = hosts("127.0.0.1", at), hosts("127.0.0.2", at)
        signed, plain = encoder(1, key), encoder(1)
        first = heartbeat(signed)
        vehicle.send(first)
        read_until(link, link.can_send)

        # 150 ODOMETRY, each sent right after the link took an unsigned RADIO_STATUS of the vehicle's
        # system id from the attacker: every one still goes to the vehicle.
        radios: list[Frame] = []
        for i in range(150):
            n = signing.accepted_unsigned
            attacker.send(radio_status(plain), radio_status(plain))
            radios += read_until(link, reaches(lambda: signing.accepted_unsigned, n + 2))
            assert link.send(odometry(link, i))
        assert sent_to(vehicle, ODOMETRY) == 150
        assert attacker.received() == []
        # Taken as data all the same (the radio's link quality), never refused.
        assert len(radios) == 300 and {(f.msgid, f.sysid) for f in radios} == {(MSG["RADIO_STATUS"], 1)}
        assert rejected == []

        # Neither a RADIO_STATUS nor a heartbeat signed with another key, nor the vehicle's own frame
        # replayed, nor an unsigned heartbeat moves the link.
        wrong = encoder(1, generate_key_file(tmp_path / "other.key"))
        n = signing.accepted_unsigned
        attacker.send(radio_status(wrong))
        assert [f.msgid for f in read_until(link, lambda: signing.accepted_unsigned > n)] == [
            MSG["RADIO_STATUS"]
        ]
        attempts = ((heartbeat(wrong), "bad signature"), (first, "replayed"), (heartbeat(plain), "unsigned"))
        for k, (raw, reason) in enumerate(attempts):
            attacker.send(raw)
            read_until(link, reaches(lambda: len(rejected), k + 1))
            assert rejected[k] == reason
            assert link.send(odometry(link, 1000))
            assert sent_to(vehicle, ODOMETRY) == 1 and attacker.received() == []
        assert rejected == ["bad signature", "replayed", "unsigned"]

        # The vehicle itself, from a new address, with a frame that verifies: the link follows it.
        moved = hosts("127.0.0.3", at)
        moved.send(heartbeat(signed))
        assert [f.msgid for f in read_until(link, lambda: signing.accepted >= 2)] == [MSG["HEARTBEAT"]]
        assert link.send(odometry(link, 2000))
        got = moved.received()
        assert [f.msgid for f in got] == [ODOMETRY] and got[0].raw[2] & 0x01  # signed by the gateway
        assert vehicle.received() == [] and attacker.received() == []
        assert link.wrong_source == 0  # nothing is pinned: the signature is what decides
    finally:
        link.close()


# ------------------------------------------------------------------------------------------ pinned link
def test_pinned_link_drops_counts_and_names_every_other_source(
    hosts: Callable[..., Host], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="arena.mavlink.link")
    vport = free_port(socket.SOCK_DGRAM)
    link, at = listening_link(peer=f"127.0.0.1:{vport}")
    try:
        vehicle = hosts("127.0.0.1", at, vport)
        attacker = hosts("127.0.0.2", at)
        same_ip = hosts("127.0.0.1", at)  # the vehicle's address, another port
        assert link.can_send()  # pinned: the gateway knows where to send before hearing anything
        assert link.send(odometry(link, 0))
        assert sent_to(vehicle, ODOMETRY) == 1

        plain, other = encoder(1), encoder(7)
        dropped: list[Frame] = []
        for i in range(50):
            attacker.send(heartbeat(plain), radio_status(plain), heartbeat(other))
            same_ip.send(heartbeat(plain))
            dropped += read_until(link, reaches(lambda: link.wrong_source, 4 * (i + 1)))
            assert link.send(odometry(link, i))
        assert dropped == [] and link.wrong_source == 200 and link.foreign == 0
        assert link.last_wrong_source in (attacker.addr, same_ip.addr)
        assert sent_to(vehicle, ODOMETRY) == 50
        assert attacker.received() == [] and same_ip.received() == []

        # The operator hears of it once per 10 s, with the offending addresses named.
        warnings = [r.getMessage() for r in caplog.records if r.name == "arena.mavlink.link"]
        assert len(warnings) == 1
        text = warnings[0]
        assert f"{attacker.addr[0]}:{attacker.addr[1]}" in text and f"127.0.0.1:{vport}" in text
        assert "pinned peer" in text

        # The vehicle's own frames are read; the pin survives a re-opening.
        vehicle.send(heartbeat(plain))
        assert [f.msgid for f in read_until(link, lambda: link.frames_in >= 1)] == [MSG["HEARTBEAT"]]
        assert link.reopen() and link.can_send()
        attacker.send(heartbeat(plain))
        read_until(link, lambda: link.wrong_source == 201)
        assert link.send(odometry(link, 99))
        assert sent_to(vehicle, ODOMETRY) == 1 and attacker.received() == []
    finally:
        link.close()


def test_pinned_signed_link_checks_the_address_first(hosts: Callable[..., Host], key: SigningKey) -> None:
    """Pinned and signed: a frame from elsewhere, signed or not, is dropped before any signing check."""
    vport = free_port(socket.SOCK_DGRAM)
    signing = LinkSigning(key)
    link, at = listening_link(signing=signing, peer=f"127.0.0.1:{vport}")
    try:
        vehicle, moved = hosts("127.0.0.1", at, vport), hosts("127.0.0.3", at)
        signed = encoder(1, key)
        moved.send(heartbeat(signed))
        read_until(link, lambda: link.wrong_source == 1)
        assert signing.accepted == 0 and not signing.rejected
        assert link.send(odometry(link, 0))
        assert sent_to(vehicle, ODOMETRY) == 1 and moved.received() == []
    finally:
        link.close()


@pytest.mark.parametrize(
    ("url", "peer", "message"),
    [
        ("tcp:127.0.0.1:5760", "127.0.0.1:5760", "udpin:HOST:PORT links only"),
        ("udpout:127.0.0.1:14550", "127.0.0.1:14550", "udpin:HOST:PORT links only"),
        ("serial:/dev/ttyS0", "127.0.0.1:14550", "udpin:HOST:PORT links only"),
        ("udpin:127.0.0.1:14550", "drone.local:14550", "expected the autopilot's IPv4 address and port"),
        ("udpin:127.0.0.1:14550", "192.168.1.31", "expected the autopilot's IPv4 address and port"),
        ("udpin:127.0.0.1:14550", "192.168.1.31:0", "expected the autopilot's IPv4 address and port"),
        ("udpin:127.0.0.1:14550", "192.168.1.31:70000", "expected the autopilot's IPv4 address and port"),
        ("udpin:127.0.0.1:14550", "0.0.0.0:14550", "is not the address of one host"),
        ("udpin:127.0.0.1:14550", "239.255.42.99:14550", "is not the address of one host"),
    ],
)
def test_a_wrong_pin_fails_when_the_link_is_made(url: str, peer: str, message: str) -> None:
    with pytest.raises(MavlinkLinkError, match=message):
        MavlinkLink(url, 1, peer=peer)


# ---------------------------------------------------------------------------------------- unpinned link
def test_unpinned_unsigned_link_follows_whoever_sends_as_the_vehicle(hosts: Callable[..., Host]) -> None:
    """The documented risk (docs/safety.md §3.3): without signing or a pin, any host that can reach the
    gateway's port is taken for the vehicle, and the gateway's output follows it."""
    link, at = listening_link()
    try:
        vehicle, attacker = hosts("127.0.0.1", at), hosts("127.0.0.2", at)
        plain = encoder(1)
        vehicle.send(heartbeat(plain))
        read_until(link, link.can_send)
        assert link.send(odometry(link, 0)) and sent_to(vehicle, ODOMETRY) == 1

        # The vehicle goes on sending; one frame from the attacker before each ODOMETRY diverts them all.
        forged = encoder(1)
        injected: list[Frame] = []
        for i in range(150):
            if i % 10 == 0:
                vehicle.send(heartbeat(plain))
            attacker.send(heartbeat(forged))
            injected += read_until(link, reaches(lambda: link.frames_in, 2 + i + (i // 10 + 1)))
            assert link.send(odometry(link, i))
        assert len(injected) == 165 and {f.sysid for f in injected} == {1}  # all taken for the vehicle's
        assert sent_to(attacker, ODOMETRY) == 150 and sent_to(vehicle, ODOMETRY) == 0

        vehicle.send(heartbeat(plain))  # the vehicle's next frame takes the link back
        read_until(link, reaches(lambda: link.frames_in, 167))
        assert link.send(odometry(link, 2)) and sent_to(vehicle, ODOMETRY) == 1
        assert link.wrong_source == 0
    finally:
        link.close()


# ------------------------------------------------------------------------------------------------ config
PX4 = BASE.replace("system_id = 1", 'system_id = 1\nautopilot = "px4"')


def test_mavlink_peer_is_read_from_the_vehicle_config(tmp_path: Path) -> None:
    cfg = read_config(
        write(tmp_path, PX4.replace("system_id = 1", 'system_id = 1\nmavlink_peer = "192.168.1.31:14550"'))
    )
    v = cfg.vehicle("d1")
    assert v.mavlink_peer == "192.168.1.31:14550"
    MavlinkLink(v.mavlink, v.system_id, peer=v.mavlink_peer)  # what the config accepts, the link accepts
    assert read_config(write(tmp_path, PX4)).vehicle("d1").mavlink_peer == ""
    sitl = '[vehicles.d1]\nautopilot = "px4-sitl"\npx4_instance = 0\nmavlink_peer = "127.0.0.1:14580"\n'
    assert read_config(write(tmp_path, sitl)).vehicle("d1").mavlink_peer == "127.0.0.1:14580"
