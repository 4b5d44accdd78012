"""The pilots' program of ``tests/system/test_outsider.py``: flies one vehicle from the commanding host and watches.

``python -m tests.outsider_ops CONFIG HOST VEHICLE`` waits for every vehicle's fused vision, takes VEHICLE
off to 1 m, prints ``{"airborne": ...}``, then a JSON report every 0.2 s: each vehicle's state as the
pilots see it, the gateways' rejected counters and every spoofed reading that reached them (a state
whose system id is not the vehicle's, an estop).  A line ``land`` on stdin lands it and ends the program.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

from arena_common import Arena
from arena_common.core import keys


def report(**kw: Any) -> None:
    print(json.dumps(kw), flush=True)


def main() -> None:
    config, host, flown = sys.argv[1:4]
    with Arena(config, host=host, name="outsider-ops") as arena:
        cfg = arena.config
        assert cfg is not None
        names = list(cfg.vehicles)
        sysids = {n: cfg.vehicle(n).system_id for n in names}
        spoofed: list[str] = []
        states = {n: arena.bus.subscribe(keys.state(n), capacity=10000, ring=False) for n in names}
        estops = arena.bus.subscribe(keys.ESTOP, capacity=100, ring=False)
        stats = arena.bus.subscribe("arena/sys/stats/**", capacity=1000, ring=False)
        rejected: dict[str, dict[str, int]] = {}
        vehicles = {n: arena.vehicle(n) for n in names}
        for v in vehicles.values():
            v.wait_until(lambda x: x.state is not None and x.state.vis_fused, timeout=90, what="fused vision")
        pilot = vehicles[flown]
        pilot.arm()
        pilot.takeoff(1.0, timeout=60)
        report(airborne=pilot.position)
        landing = threading.Event()

        def commands() -> None:
            for line in sys.stdin:
                if line.strip() == "land":
                    landing.set()
                    return

        threading.Thread(target=commands, daemon=True).start()
        while not landing.is_set():
            for n, sub in states.items():
                for item in sub.channel.drain():
                    if item.payload is None or item.payload.sysid != sysids[n]:
                        spoofed.append(f"{n}: {item.payload or item.error}")
            for item in estops.channel.drain():
                spoofed.append(f"estop: {item.payload}")
            for item in stats.channel.drain():
                if item.payload is not None and item.payload.service.startswith("gateway."):
                    rejected[item.payload.service] = dict(item.payload.rejected)
            snap = {}
            for n, v in vehicles.items():
                s = v.state
                snap[n] = None if s is None else {
                    "p": s.p, "z": s.p[2] if s.p else None, "armed": s.armed, "mode": s.mode, "fused": s.vis_fused,
                    "vis_rate": s.vis_rate, "link": s.link, "age": v.state_age,
                    "events": [f"{e.kind}: {e.text}" for e in v.events() if e.sev <= 4 or e.kind == "mode"][-8:],
                }  # fmt: skip
            report(t=time.time(), spoofed=spoofed[-20:], n_spoofed=len(spoofed), rejected=rejected, **snap)
            time.sleep(0.2)
        pilot.land(timeout=60)
        report(landed=True)


if __name__ == "__main__":
    main()
