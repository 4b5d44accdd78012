"""A datagram link's budget (:class:`~arena_common.mavlink.link.MavlinkLink` ``budget``): real UDP on
loopback, real MAVLink bytes. Past the budget, what is read is dropped unparsed and what waits in the
socket is left to the system, and every datagram is one of: a frame, over budget, dropped by the system."""

from __future__ import annotations

import socket
import time

from pymavlink.dialects.v20 import common

from arena_common.mavlink.link import BUDGET_WINDOW_S, MavlinkLink
from arena_common.mavlink.transports import udp_drops
from tests.helpers import free_port

SYSID = 7


def _heartbeat(sysid: int = SYSID) -> bytes:
    mav = common.MAVLink(None, srcSystem=sysid, srcComponent=1)
    return bytes(mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav))


def _read_for(link: MavlinkLink, seconds: float) -> int:
    frames, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        frames += len(link.read(0.05))
    return frames


def test_past_its_budget_a_link_reads_no_more_and_every_datagram_is_counted() -> None:
    port = free_port()
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", SYSID, budget=200)
    link.open()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        frame, sent = _heartbeat(), 3000
        for _ in range(sent):  # a burst fifteen times the second's budget, faster than one window
            sender.sendto(frame, ("127.0.0.1", port))
        started = time.monotonic()
        frames = _read_for(link, 0.5)
        windows = (time.monotonic() - started) / BUDGET_WINDOW_S + 1
        assert frames == link.frames_in <= 200 * BUDGET_WINDOW_S * windows  # at most the budget's share
        assert link.over_budget + link.kernel_drops() > 0
        assert link.datagrams_in - link.over_budget == frames  # what was kept was parsed, every frame
        assert link.datagrams_in + link.kernel_drops() == sent  # every datagram counted, one way or the other
        # under the budget again, every datagram is read and parsed
        before = link.frames_in
        for _ in range(20):
            sender.sendto(frame, ("127.0.0.1", port))
        time.sleep(0.25)
        assert _read_for(link, 0.3) == 20 and link.frames_in - before == 20
    finally:
        sender.close()
        link.close()


def test_without_a_budget_a_link_reads_what_its_socket_holds() -> None:
    port = free_port()
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", SYSID)
    link.open()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(200):
            sender.sendto(_heartbeat(), ("127.0.0.1", port))
        assert _read_for(link, 0.3) == 200 and link.over_budget == 0 and link.kernel_drops() == 0
    finally:
        sender.close()
        link.close()


def test_the_systems_drop_count_is_the_sockets_own() -> None:
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small buffer fills at once
    receiver.setblocking(False)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert udp_drops(receiver) == 0
        for _ in range(500):
            sender.sendto(bytes(200), receiver.getsockname())
        received = 0
        while True:
            try:
                receiver.recv(65535)
            except BlockingIOError:
                break
            received += 1
        assert udp_drops(receiver) == 500 - received > 0
    finally:
        sender.close()
        receiver.close()
