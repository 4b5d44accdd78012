"""The outsider of ``tests/system/test_outsider.py``: run on its own computer (a namespace), it attacks every port.

``python -m tests.outsider_attack SPEC.json`` prints one JSON line per attempt and a last line
``{"done": true}``.  Each attempt says what it tried and what it got; the test decides what is allowed.
The spec names the TCP and UDP ports to try, the identities to try them with and the vehicles.
"""

from __future__ import annotations

import json
import socket
import sys
import time
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from arena_common.bus.session import Bus, BusOptions, open_bus
from arena_common.core import keys, wire
from arena_common.core.config import ZenohSpec
from arena_common.core.errors import ArenaError
from arena_common.mavlink.signing import LinkSigning, SigningKey


def report(**kw: Any) -> None:
    print(json.dumps(kw), flush=True)


def session(endpoint: str, settings: dict[str, Any]) -> Bus | str:
    """A client session to ``endpoint`` with ``settings``, or why none opened."""
    try:
        return open_bus(
            ZenohSpec(mode="client", connect=(endpoint,)),
            BusOptions(settings={"connect/timeout_ms": 4000, **settings}),
        )
    except (ArenaError, Exception) as exc:  # a refused session is the expected outcome
        return f"{type(exc).__name__}: {str(exc)[:200]}"


def act(bus: Bus, vehicles: dict[str, int], tag: str) -> dict[str, Any]:
    """Everything an identity might try once connected: read, command, spoof, estop, pose as a service."""
    sub = bus.subscribe("arena/**", capacity=100000, ring=False)
    time.sleep(3.0)
    seen = len(sub.channel.drain())
    answers = {}
    for name in vehicles:
        try:
            res = bus.request(keys.cmd(name), wire.Command(op="arm"), 2.0)
            answers[name] = f"{res.ok} {res.result} {res.reason}"
        except Exception as exc:
            answers[name] = f"{type(exc).__name__}"
    token = bus.token(keys.alive("cc1", f"gateway.{tag}"))
    for name in vehicles:
        fake = bus.stream_publisher(keys.state(name), wire.State)
        vision = bus.stream_publisher(keys.vision(name), wire.Pose)
        setpoint = bus.stream_publisher(keys.setpoint(name), wire.Setpoint)
        for _ in range(20):
            fake.put(wire.State(t=wire.now_ns(), sysid=66, armed=True, mode="SPOOFED"))
            vision.put(wire.Pose(t=wire.now_ns(), p=(1.0, 1.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True))
            setpoint.put(wire.Setpoint(t=wire.now_ns(), lease=1.0, v=(0.5, 0.0, 0.0), src=tag))
            time.sleep(0.02)
    estop = bus.command_publisher(keys.ESTOP, wire.Estop)
    estop.put(wire.Estop(t=wire.now_ns(), kill=True, reason=tag))
    time.sleep(0.5)
    token.undeclare()
    return {"seen": seen, "answers": answers}


def mavlink_attack(targets: list[tuple[str, int]], vehicles: dict[str, int], replays: dict[str, str]) -> int:
    """Unsigned, wrongly signed and replayed MAVLink to every UDP port; returns the bytes sent back to us."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("0.0.0.0", 0))
    sock.setblocking(False)
    wrong = SigningKey(bytes(range(1, 33)))
    for sysid in vehicles.values():
        unsigned = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
        signed = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
        LinkSigning(wrong, link_id=0).attach(signed)
        frames = [
            unsigned.radio_status_encode(200, 200, 100, 0, 0, 0, 0).pack(unsigned),
            unsigned.heartbeat_encode(2, 12, 0x81, 0, 4).pack(unsigned),
            unsigned.command_long_encode(sysid, 1, 400, 0, 1, 21196, 0, 0, 0, 0, 0).pack(unsigned),
            unsigned.statustext_encode(2, b"spoofed").pack(unsigned),
            signed.heartbeat_encode(2, 12, 0x81, 0, 4).pack(signed),
            signed.command_long_encode(sysid, 1, 400, 0, 1, 21196, 0, 0, 0, 0, 0).pack(signed),
        ]
        frames += [bytes.fromhex(r) for r in replays.values()]
        for host, port in targets:
            for _ in range(25):
                for frame in frames:
                    try:
                        sock.sendto(frame, (host, port))
                    except OSError:
                        pass
                time.sleep(0.004)
    got = 0
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        try:
            got += len(sock.recv(65536))
        except BlockingIOError:
            time.sleep(0.02)
    sock.close()
    return got


def main() -> None:
    with open(sys.argv[1], encoding="utf-8") as f:
        spec = json.load(f)
    vehicles: dict[str, int] = spec["vehicles"]
    ca = {"transport/link/tls/root_ca_certificate": spec["ca"]} if spec.get("ca") else {}
    for host, port in spec["tcp"]:
        for scheme in ("tcp", "tls"):
            bus = session(f"{scheme}/{host}:{port}", ca if scheme == "tls" else {})
            opened = not isinstance(bus, str)
            result = act(bus, vehicles, "anonymous") if not isinstance(bus, str) else {}
            if not isinstance(bus, str):
                bus.close()
            report(attempt="no credentials", endpoint=f"{scheme}/{host}:{port}", opened=opened, **result)
    for name, (endpoint, settings) in spec["identities"].items():
        bus = session(endpoint, settings)
        if isinstance(bus, str):
            report(attempt=name, endpoint=endpoint, opened=False, why=bus)
            continue
        result = act(bus, vehicles, name)
        bus.close()
        report(attempt=name, endpoint=endpoint, opened=True, **result)
    targets = [(h, p) for h, p in spec["udp"]]
    report(
        attempt="mavlink",
        targets=len(targets),
        diverted_bytes=mavlink_attack(targets, vehicles, spec["replays"]),
    )
    report(done=True)


if __name__ == "__main__":
    main()
