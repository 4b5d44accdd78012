"""Many vehicles' gateways in one process: the per-host design of issue #35, measured.

``python -m bench.gateway_host -c arena.toml --host bench --vehicle d1 --vehicle d2 …`` runs
:func:`arena_common.gateway.host.serve`: one :class:`~arena_common.gateway.gateway.Gateway` per vehicle
named, each as the gateway service runs it, over one Zenoh session and one clock measurement for the
process, their vision one message per mocap frame when the transform decimates (``--vision vehicle``:
each vehicle's own key, as before, for the comparison).

The bench's fleet point runs it with ``--gateway-hosts K`` (:class:`bench.pipeline.RunSettings`): the
vehicles split over K such processes instead of one gateway process each.
"""

from __future__ import annotations

import argparse
import logging
import threading

from arena_common.gateway.host import SERVICE, serve
from arena_common.runtime.options import read_config
from arena_common.runtime.service import setup_logging, take_cpu_share


def main(argv: list[str] | None = None) -> None:
    """The command line above."""
    parser = argparse.ArgumentParser(prog="python -m bench.gateway_host", description=__doc__.split("\n")[0])
    parser.add_argument("-c", "--config", required=True)
    parser.add_argument("--host", default=None)
    parser.add_argument("--log-level", default="WARNING")
    parser.add_argument("--vehicle", action="append", required=True)
    parser.add_argument("--vision", choices=("frame", "vehicle"), default="frame")
    args = parser.parse_args(argv)
    setup_logging(args.log_level)
    take_cpu_share(SERVICE.cpu, logging.getLogger("arena.gateway_host"))
    serve(
        read_config(args.config),
        args.vehicle,
        threading.Event(),
        host=args.host,
        per_frame=args.vision == "frame",
    )


if __name__ == "__main__":
    main()
