"""Many vehicles' gateways in one process: the per-host design of issue #35, measured before it is built.

``python -m bench.gateway_host -c arena.toml --host bench --vehicle d1 --vehicle d2 …`` runs one
:class:`~arena_common.gateway.gateway.Gateway` per vehicle named, each as the gateway service runs it (its
own :func:`~arena_common.runtime.service.running` service: presence, stats, logger; its own link, lease
and safety rules, its supervisor in a thread of its own), over one Zenoh session and one clock measurement
for the process: what one Python process, one session and its threads cost per vehicle is then paid once.

The bench's fleet point runs it with ``--gateway-hosts K`` (:class:`bench.pipeline.RunSettings`): the
vehicles split over K such processes instead of one gateway process each.  It is the measurement that
chooses the design; fault isolation between the vehicles of one process is not built here.
"""

from __future__ import annotations

import argparse
import logging
import threading
from contextlib import ExitStack

from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import open_bus
from arena_common.core.services import by_module
from arena_common.gateway.gateway import Gateway
from arena_common.runtime.options import read_config
from arena_common.runtime.service import running, setup_logging, take_cpu_share

SERVICE = by_module("services.mavlink_gateway")


def serve(config: str, vehicles: list[str], host: str | None, stop: threading.Event) -> None:
    """Run the gateways of ``vehicles`` in this process until ``stop`` is set (or SIGINT/SIGTERM)."""
    cfg = read_config(config)
    host = host_name(host)
    bus = open_bus(cfg.zenoh, host_bus_options(cfg, host, None, vehicle=vehicles[0]))
    try:
        with ExitStack() as stack:
            services = [
                stack.enter_context(
                    running(SERVICE.name, cfg, bus=bus, vehicle=v, host=host, stop=stop, clock=i == 0)
                )
                for i, v in enumerate(vehicles)
            ]
            clock = services[0].clock
            gateways = [
                stack.enter_context(Gateway(cfg, v, bus, stats=s.stats, log=s.log, clock=clock))
                for v, s in zip(vehicles, services, strict=True)
            ]
            threads = [
                threading.Thread(target=gw.run, args=(stop,), name=f"{gw.name}:supervisor", daemon=True)
                for gw in gateways
            ]
            for t in threads:
                t.start()
            stop.wait()
            for t in threads:
                t.join(timeout=2.0)
    finally:
        bus.close()


def main(argv: list[str] | None = None) -> None:
    """The command line above."""
    parser = argparse.ArgumentParser(prog="python -m bench.gateway_host", description=__doc__.split("\n")[0])
    parser.add_argument("-c", "--config", required=True)
    parser.add_argument("--host", default=None)
    parser.add_argument("--log-level", default="WARNING")
    parser.add_argument("--vehicle", action="append", required=True)
    args = parser.parse_args(argv)
    setup_logging(args.log_level)
    take_cpu_share(SERVICE.cpu, logging.getLogger("arena.gateway_host"))
    serve(args.config, args.vehicle, args.host, threading.Event())


if __name__ == "__main__":
    main()
