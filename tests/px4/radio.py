"""A slow radio link between a PX4 SITL instance and its gateway, in a process of its own.

``python -m tests.px4.radio --gateway-port G --px4-port P --delay 0.03 --jitter 0.01`` relays every
MAVLink datagram between PX4 (its offboard port P) and the gateway (listening on G) through
:class:`~arena_common.sim.linkdelay.LinkDelay`.  It speaks to PX4 first (a heartbeat), so PX4, which
answers only its first peer, sends everything through it.  A line of JSON on stdout each second gives its
counts (``forwarded``, ``dropped``, ``send_errors``), the first once PX4 has been spoken to; SIGTERM stops it.

A radio is hardware beside the test, not a part of it.  While the relay ran as a thread of the test's
own process, one run's gateway measured the link's round trip at 119 ms where 40–80 ms were set, and PX4
landed in failsafe in three runs of three; with the relay in a process of its own, neither was seen.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading

from arena_common.mavlink.link import mavlink2
from arena_common.sim.linkdelay import LinkDelay


def main(argv: list[str] | None = None) -> None:
    """Relay until SIGTERM; print the counts each second."""
    ap = argparse.ArgumentParser(prog="python -m tests.px4.radio", description=__doc__.splitlines()[0])
    ap.add_argument("--gateway-port", type=int, required=True, help="the gateway's udpin port (loopback)")
    ap.add_argument("--px4-port", type=int, required=True, help="PX4's own offboard port (loopback)")
    ap.add_argument("--delay", type=float, required=True, help="s each way")
    ap.add_argument("--jitter", type=float, default=0.0, help="± s each way (uniform)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    relay = LinkDelay(
        ("127.0.0.1", args.gateway_port),
        args.delay,
        args.jitter,
        seed=args.seed,
        vehicle=("127.0.0.1", args.px4_port),
    )
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER)
    beat = mav.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    relay.poke(beat.pack(mav))

    def counts() -> str:
        return json.dumps(
            {"forwarded": relay.forwarded, "dropped": relay.dropped, "send_errors": relay.send_errors}
        )

    print(counts(), flush=True)
    while not stop.wait(1.0):
        print(counts(), flush=True)
    relay.close()
    print(counts(), flush=True)


if __name__ == "__main__":
    main()
