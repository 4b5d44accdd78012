"""ROS 2 bridge-less view of the arena: its keys as rmw_zenoh topics, ROS 2 commands through the client's
safety path (:mod:`arena_common.ros2`; docs/ros2.md).

One per arena (or one per host with ``--vehicle`` for that host's vehicles).  ROS 2 nodes on
``rmw_zenoh_cpp`` connected to the arena's router see the topics of :data:`arena_common.ros2.topics.TOPICS`
and command with its subscribed ones; an arena sample that is not bridged is counted among the service's
rejected inputs, by key and reason.
"""

from __future__ import annotations

import os
import threading
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError, MissingExtra
from arena_common.core.services import by_module, missing_extra
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.ros2").name  # its one name: arena_common/core/services.py


def default_domain() -> int:
    """``$ROS_DOMAIN_ID``, else 0 (what rmw_zenoh reads)."""
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    except ValueError:
        raise ConfigError(f"ROS_DOMAIN_ID must be a number, not {os.environ['ROS_DOMAIN_ID']!r}") from None


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
    domain: int | None = None,
    vehicles: tuple[str, ...] = (),
    node: str = "arena_bridge",
    commands: bool = True,
) -> None:
    """Serve the arena to ROS 2 until ``stop`` is set (or SIGINT/SIGTERM)."""
    dom = default_domain() if domain is None else domain
    if not 0 <= dom <= 232:
        raise ConfigError(f"ROS domain {dom} outside 0..232")
    why = missing_extra("ros2")
    if why:  # said before anything of the extra is imported: arena up, systemd, python -m alike
        raise MissingExtra(f"the ROS 2 service: {why}")
    from arena_common.ros2.bridge import Bridge, BridgeOptions

    with running(SERVICE, cfg, options, host=host, stop=stop) as svc:
        bridge = Bridge(
            cfg,
            svc.bus,
            BridgeOptions(domain=dom, node=node, vehicles=vehicles, commands=commands),
            src=f"{svc.host}/ros2",
            stats=svc.stats,
            log=svc.log,
            reject=svc.reject,
        )
        svc.log.info(
            "ROS 2 domain %d, node /%s (zid %s): %d vehicle(s)%s",
            dom,
            node,
            bridge.node.zid,
            len(bridge.vehicles),
            ", commands from ROS 2 taken" if commands else "",
        )
        try:
            while not svc.sleep(0.5):
                pass
        finally:
            bridge.close()


@service_command
def cli(
    shared: Shared,
    domain: Annotated[
        int | None, typer.Option("--domain", help="ROS domain id (default: $ROS_DOMAIN_ID, else 0).")
    ] = None,
    vehicle: Annotated[
        list[str] | None, typer.Option("--vehicle", "-v", help="Serve only this vehicle (repeatable).")
    ] = None,
    node: Annotated[str, typer.Option("--node", help="The ROS 2 node's name.")] = "arena_bridge",
    no_commands: Annotated[
        bool, typer.Option("--no-commands", help="Publish only; take no goto or cmd_vel from ROS 2.")
    ] = False,
) -> None:
    """The arena as ROS 2 topics for rmw_zenoh (poses, odometry, TF, battery, diagnostics, /rosout), and
    goto / cmd_vel commands from ROS 2 under the arena's safety rules."""
    main(
        shared.config,
        shared.bus,
        host=shared.host,
        domain=domain,
        vehicles=tuple(vehicle or ()),
        node=node,
        commands=not no_commands,
    )


if __name__ == "__main__":
    typer.run(cli)
