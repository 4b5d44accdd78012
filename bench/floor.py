"""The floor of ``make bench``: the arena's process topology with processes that only move bytes.

``python -m bench.floor source …`` plays Motive (a datagram of the NatNet frame's size to a
multicast group at a fixed rate on a drift-free clock); ``… relay …`` plays every other process: it takes
each message from its input and sends it on, fanned out per vehicle for the transform's place (the ingest
sends one message per frame, as the arena does).  Chained like
the arena (source → ingest → transform → N downsamplers → N gateways → the harness), over Zenoh with the
arena's own session settings and stream QoS, or over plain UDP, it measures what the transport alone costs
on this machine, so the arena's figures can be read as a ratio to it.

Messages start with the frame number (u64) and the vehicle index (u16), padded to the size the arena's
payload has at that hop; the harness matches them exactly.  Zenoh samples are handed from the callback to
the relay's own thread through a queue, as the arena's idiom requires (``--inline`` forwards inside the
callback instead, to show what the hand-off costs).
"""

from __future__ import annotations

import argparse
import queue
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

HEADER = struct.Struct("<QH")
_FN = struct.Struct("<Q")


def _pad(data: bytes, size: int) -> bytes:
    if size <= 0 or len(data) == size:
        return data
    return data[:size] if len(data) > size else data + bytes(size - len(data))


def _udp_out() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    return s


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def run_source(group: str, port: int, rate: float, size: int, stop: threading.Event) -> int:
    """Send frame ``1, 2, …`` (``size`` bytes) to ``group:port`` on loopback at ``rate`` Hz; frames sent."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    s.bind(("127.0.0.1", 0))
    period = 1e9 / rate
    start = time.perf_counter_ns()
    k = 0
    pad = bytes(max(0, size - _FN.size))
    try:
        while not stop.is_set():
            due = start + round(k * period)
            left = due - time.perf_counter_ns()
            if left > 0 and stop.wait(left / 1e9):
                break
            behind = int((time.perf_counter_ns() - due) // period)
            if behind >= 2:  # stalled: skip the frames of the past, as the emulator does
                k += behind
            k += 1
            s.sendto(_FN.pack(k) + pad, (group, port))
    finally:
        s.close()
    return k


class _Output:
    """Where a relay sends: UDP ports indexed by vehicle (one port: all there) or Zenoh keys ``…{i}…``."""

    def __init__(self, spec: str, connect: Sequence[str], size: int) -> None:
        kind, _, rest = spec.partition(":")
        self.size = size
        self.session: Any = None
        self._send: Callable[[int, bytes], None]
        if kind == "udp":
            ports = [int(p) for p in rest.split(",") if p]
            sock = _udp_out()
            addrs = [("127.0.0.1", p) for p in ports]

            def send_udp(i: int, data: bytes) -> None:
                try:
                    sock.sendto(data, addrs[i] if len(addrs) > 1 else addrs[0])
                except OSError:
                    pass

            self._send = send_udp
        elif kind == "zenoh":
            import zenoh

            self.session = _zenoh_session(connect)
            template = rest
            pubs: dict[int, Any] = {}
            session = self.session

            def send_zenoh(i: int, data: bytes) -> None:
                pub = pubs.get(i)
                if pub is None:
                    pub = pubs[i] = session.declare_publisher(
                        template.format(i=i),
                        congestion_control=zenoh.CongestionControl.DROP,
                        priority=zenoh.Priority.DATA,
                        reliability=zenoh.Reliability.BEST_EFFORT,
                    )
                pub.put(data)

            self._send = send_zenoh
        else:
            raise SystemExit(f"unknown output {spec!r}: udp:PORT[,PORT…] or zenoh:KEY{{i}}")

    def send(self, i: int, data: bytes) -> None:
        self._send(i, _pad(data, self.size))


def _zenoh_session(connect: Sequence[str]) -> Any:
    """A peer session with the arena's own settings (batching, lease, listen on loopback)."""
    import zenoh

    from arena_common.bus.session import zenoh_config
    from arena_common.core.config import ZenohSpec

    return zenoh.open(zenoh_config(ZenohSpec(mode="peer", connect=tuple(connect))))


def kept(fn: int, keep: float) -> bool:
    """Whether a relay passing the share ``keep`` of its messages (evenly, by frame number) passes ``fn``."""
    return keep >= 1.0 or int(fn * keep) != int((fn - 1) * keep)


def run_relay(
    source: str,
    target: str,
    *,
    connect: Sequence[str] = (),
    fanout: int = 0,
    size: int = 0,
    inline: bool = False,
    keep: float = 1.0,
    stop: threading.Event,
) -> int:
    """Forward every message from ``source`` to ``target`` until ``stop``; messages forwarded.

    ``fanout`` > 0: each input becomes ``fanout`` messages, one per vehicle index (the transform's place);
    otherwise the vehicle index is read from the message.  ``keep`` < 1 passes only that share of the
    frames, evenly (:func:`kept`): a decimator's place.
    """
    out = _Output(target, connect, size)
    forward, sent = _forwarder(out, fanout, keep)
    kind, _, rest = source.partition(":")
    if kind in ("udp", "mcast"):
        _relay_datagrams(kind, rest, forward, stop)
    elif kind == "zenoh":
        _relay_zenoh(rest, out, connect, inline, forward, stop)
    else:
        raise SystemExit(f"unknown input {source!r}: mcast:GROUP:PORT, udp:PORT or zenoh:KEYEXPR")
    if out.session is not None:
        out.session.close()
    return sent()


def _forwarder(out: _Output, fanout: int, keep: float) -> tuple[Callable[[bytes], None], Callable[[], int]]:
    """What a relay does with each message (see :func:`run_relay`), and how many it has sent so far."""
    sent = 0

    def forward(data: bytes) -> None:
        nonlocal sent
        if fanout:
            fn = _FN.unpack_from(data)[0]
            if keep < 1.0 and not kept(fn, keep):
                return
            for i in range(fanout):
                out.send(i, HEADER.pack(fn, i))
            sent += fanout
        elif len(data) >= HEADER.size:
            fn, i = HEADER.unpack_from(data)
            if keep < 1.0 and not kept(fn, keep):
                return
            out.send(i, data)
            sent += 1
        else:
            out.send(0, data)
            sent += 1

    return forward, lambda: sent


def _relay_datagrams(kind: str, rest: str, forward: Callable[[bytes], None], stop: threading.Event) -> None:
    """Datagrams from a UDP port (``udp``: ``PORT``) or a multicast group (``mcast``: ``GROUP:PORT``)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    if kind == "mcast":
        group, port = rest.rsplit(":", 1)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((group, int(port)))
        mreq = socket.inet_aton(group) + socket.inet_aton("127.0.0.1")
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
    else:
        s.bind(("127.0.0.1", int(rest)))
    s.settimeout(0.2)
    while not stop.is_set():
        try:
            data = s.recv(65536)
        except TimeoutError:
            continue
        forward(data)
    s.close()


def _relay_zenoh(
    keyexpr: str,
    out: _Output,
    connect: Sequence[str],
    inline: bool,
    forward: Callable[[bytes], None],
    stop: threading.Event,
) -> None:
    """Samples on ``keyexpr``: forwarded inside Zenoh's callback (``inline``) or from a queue by this thread."""
    session = out.session or _zenoh_session(connect)
    if inline:
        sub = session.declare_subscriber(keyexpr, lambda sample: forward(sample.payload.to_bytes()))
        stop.wait()
    else:
        q: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        sub = session.declare_subscriber(keyexpr, lambda sample: q.put(sample.payload.to_bytes()))
        while not stop.is_set():
            try:
                data = q.get(timeout=0.2)
            except queue.Empty:
                continue
            forward(data)
    sub.undeclare()
    if session is not out.session:
        session.close()


def main(argv: Sequence[str] | None = None) -> None:
    """Command line: ``source`` or ``relay`` (see ``--help``)."""
    parser = argparse.ArgumentParser(prog="python -m bench.floor", description=__doc__)
    sub = parser.add_subparsers(dest="role", required=True)
    src = sub.add_parser("source", help="Send numbered frames to a multicast group at a fixed rate.")
    src.add_argument("--group", required=True)
    src.add_argument("--port", type=int, required=True)
    src.add_argument("--rate", type=float, required=True)
    src.add_argument("--size", type=int, default=64)
    rel = sub.add_parser("relay", help="Forward messages from one input to one output.")
    rel.add_argument("--in", dest="source", required=True, help="mcast:GROUP:PORT, udp:PORT or zenoh:KEYEXPR")
    rel.add_argument("--out", dest="target", required=True, help="udp:PORT[,PORT…] or zenoh:KEY{i}")
    rel.add_argument("--connect", action="append", default=[], help="Zenoh endpoint (repeatable).")
    rel.add_argument("--fanout", type=int, default=0)
    rel.add_argument("--size", type=int, default=0)
    rel.add_argument("--inline", action="store_true", help="Forward inside the Zenoh callback.")
    rel.add_argument("--keep", type=float, default=1.0, help="Share of the frames passed (a decimator).")
    args = parser.parse_args(argv)
    stop = _stop_event()
    if args.role == "source":
        run_source(args.group, args.port, args.rate, args.size, stop)
    else:
        run_relay(
            args.source,
            args.target,
            connect=args.connect,
            fanout=args.fanout,
            size=args.size,
            inline=args.inline,
            keep=args.keep,
            stop=stop,
        )


if __name__ == "__main__":
    main()
