"""The floors of the peer comparison: the least a Python process can do to forward the vision stream.

``python -m bench.forwarders zenoh -c CONFIG --host HOST --vehicle d1 --out PORT`` opens a Zenoh session
exactly as the arena's services do (the same config, :func:`~arena_common.bus.session.open_bus` with the
host's bus options), subscribes to the vehicle's vision key and, inside the Zenoh callback, decodes the
:class:`~arena_common.core.wire.Pose` (msgspec, under a microsecond), puts its ``t`` into a ready-made
ODOMETRY payload as ``time_usec`` (so the harness can match it to the pose it published) and sends the
framed ODOMETRY (header and CRC packed, no pymavlink object) over UDP: the Zenoh receive, the decode and
one datagram, nothing else.  This is what the gateway's vision path costs at the least.

``python -m bench.forwarders udp --listen PORT --out PORT`` receives datagrams (ODOMETRY frames) and sends
them on as they are: MAVProxy's input-to-output path with bytes only.
"""

from __future__ import annotations

import argparse
import signal
import socket
import struct
import threading
from collections.abc import Sequence
from typing import Any

_USEC = struct.Struct("<Q")


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _udp_out() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    return s


def run_zenoh(
    config: str, host: str, vehicle: str, out_port: int, stop: threading.Event, *, direct: bool = False
) -> int:
    """Forward ``vehicle``'s vision poses as ODOMETRY to ``127.0.0.1:out_port`` until ``stop``; frames sent.

    ``direct``: the callback runs on Zenoh's receiving thread itself (zenoh-python's unstable
    ``Callback(indirect=False)``) instead of the Python thread zenoh-python hands each sample to by
    default (as the arena's subscribers do): one thread wake-up less per message.
    """
    import zenoh

    from arena_common.bus.hosts import host_bus_options
    from arena_common.bus.session import open_bus
    from arena_common.core import keys, wire
    from arena_common.mavlink import fastframe, px4
    from arena_common.runtime.options import read_config as load_config

    cfg = load_config(config)
    spec = cfg.vehicles[vehicle]
    template = bytearray(
        fastframe.odometry_payload(px4.odometry_args(0, (0.0, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0)))
    )
    frame = fastframe.ODOMETRY.frame
    sock = _udp_out()
    addr = ("127.0.0.1", out_port)
    decode = wire.Pose.decode
    system, component = spec.system_id, px4.MAV_COMP_ID_ONBOARD_COMPUTER
    state = {"seq": 0, "sent": 0}
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        try:
            pose = decode(sample.payload.to_bytes())
        except Exception:
            return
        with lock:  # calls may come from several Zenoh threads: one frame at a time, as the gateway
            _USEC.pack_into(template, 0, pose.t // 1000)
            seq = state["seq"]
            state["seq"] = (seq + 1) & 0xFF
            try:
                sock.sendto(frame(bytes(template), seq, system, component), addr)
            except OSError:
                return
            state["sent"] += 1

    bus = open_bus(cfg.zenoh, host_bus_options(cfg, host, None))
    try:
        handler: Any = zenoh.handlers.Callback(on_sample, indirect=False) if direct else on_sample
        sub = bus.session.declare_subscriber(keys.vision(vehicle), handler)
        stop.wait()
        sub.undeclare()
    finally:
        bus.close()
        sock.close()
    return state["sent"]


def run_udp(listen: int, out_port: int, stop: threading.Event) -> int:
    """Send every datagram received on ``127.0.0.1:listen`` on to ``127.0.0.1:out_port``; datagrams sent."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    rx.bind(("127.0.0.1", listen))
    rx.settimeout(0.2)
    tx = _udp_out()
    addr = ("127.0.0.1", out_port)
    sent = 0
    try:
        while not stop.is_set():
            try:
                data = rx.recv(65536)
            except TimeoutError:
                continue
            try:
                tx.sendto(data, addr)
            except OSError:
                continue
            sent += 1
    finally:
        rx.close()
        tx.close()
    return sent


def main(argv: Sequence[str] | None = None) -> None:
    """Command line: ``zenoh`` or ``udp`` (see ``--help``)."""
    parser = argparse.ArgumentParser(prog="python -m bench.forwarders", description=__doc__)
    sub = parser.add_subparsers(dest="kind", required=True)
    z = sub.add_parser("zenoh", help="Vision poses from Zenoh to ODOMETRY over UDP, nothing more.")
    z.add_argument("-c", "--config", required=True)
    z.add_argument("--host", required=True)
    z.add_argument("--vehicle", default="d1")
    z.add_argument("--out", type=int, required=True, help="UDP port on 127.0.0.1 to send ODOMETRY to.")
    z.add_argument("--direct", action="store_true", help="Run the callback on Zenoh's receiving thread.")
    u = sub.add_parser("udp", help="Datagrams in, the same datagrams out.")
    u.add_argument("--listen", type=int, required=True)
    u.add_argument("--out", type=int, required=True)
    args = parser.parse_args(argv)
    stop = _stop_event()
    if args.kind == "zenoh":
        run_zenoh(args.config, args.host, args.vehicle, args.out, stop, direct=args.direct)
    else:
        run_udp(args.listen, args.out, stop)


if __name__ == "__main__":
    main()
