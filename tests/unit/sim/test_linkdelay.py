"""A slow radio link for a simulated vehicle: the relay on real UDP sockets, and its settings in the config."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

from arena_common.core.config import load
from arena_common.core.errors import ConfigError
from arena_common.sim.base import SimAutopilotError
from arena_common.sim.connection import open_connection
from arena_common.sim.linkdelay import LinkDelay
from tests.helpers import wait_for


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(5.0)
    return s


def test_every_datagram_waits_its_delay_each_way_and_keeps_its_order() -> None:
    gateway, vehicle = _udp(), _udp()
    relay = LinkDelay(gateway.getsockname(), 0.020, 0.005, seed=3)
    try:
        # Before the vehicle sent anything, the gateway's datagram has nowhere to go: dropped, counted.
        gateway.sendto(b"early", relay.source)
        wait_for(lambda: relay.dropped == 1, 5.0, what="the early datagram dropped")
        sent: dict[bytes, float] = {}
        for n in range(40):
            data = n.to_bytes(2, "big")
            sent[data] = time.monotonic()
            vehicle.sendto(data, ("127.0.0.1", relay.port))
            time.sleep(0.002)
        got, waited = [], []
        for _ in range(40):
            data, back_to = gateway.recvfrom(64)
            waited.append(time.monotonic() - sent[data])
            got.append(data)
        assert got == sorted(got)  # in order, whatever each one's jitter
        assert back_to == relay.source
        assert min(waited) >= 0.015 - 0.001, min(waited)  # never sooner than delay - jitter
        # The gateway answers whoever sent: the relay's own socket, which hands it to the vehicle, late.
        t0 = time.monotonic()
        gateway.sendto(b"answer", back_to)
        data, _ = vehicle.recvfrom(64)
        assert data == b"answer" and time.monotonic() - t0 >= 0.015 - 0.001
        # Counted once sent (the thread counts just after the datagram left): all 41, the early one dropped.
        wait_for(lambda: relay.forwarded == 41, 5.0, what="41 datagrams counted")
        assert relay.dropped == 1 and relay.send_errors == 0
    finally:
        relay.close()
        gateway.close()
        vehicle.close()


def test_a_link_delay_is_refused_where_it_cannot_be() -> None:
    with pytest.raises(ValueError, match="jitter <= delay"):
        LinkDelay(("127.0.0.1", 9), 0.01, 0.02)
    with pytest.raises(SimAutopilotError, match="needs a udpout:HOST:PORT link"):
        open_connection("tcpin:127.0.0.1:0", 1, 1, (0.03, 0.0))


def test_the_config_says_a_vehicle_s_link_delay(tmp_path: Path) -> None:
    def cfg(sim: str, link: str = 'mavlink = "udpin:127.0.0.1:14540"') -> Path:
        path = tmp_path / "arena.toml"
        path.write_text(f"[vehicles.d1]\nsystem_id = 1\n{link}\n[vehicles.d1.sim]\n{sim}\n")
        return path

    v = load(cfg("link_delay_ms = 30.0\nlink_jitter_ms = 10.0")).vehicle("d1")
    assert (v.sim.link_delay_ms, v.sim.link_jitter_ms) == (30.0, 10.0)
    with pytest.raises(ConfigError, match=r"vehicles.d1.sim.link_jitter_ms: expected at most link_delay_ms"):
        load(cfg("link_delay_ms = 5.0\nlink_jitter_ms = 10.0"))
    with pytest.raises(ConfigError, match=r"vehicles.d1.sim.link_delay_ms: expected a number in 0.0..500.0"):
        load(cfg("link_delay_ms = 900.0"))
    with pytest.raises(
        ConfigError, match=r"sim.link_delay_ms: expected a simulated vehicle .* on a udpin link"
    ):
        load(cfg("link_delay_ms = 30.0", 'mavlink = "tcp:127.0.0.1:5760"'))
