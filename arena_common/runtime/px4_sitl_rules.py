"""What a PX4 SITL instance number fixes: its ports and system id (:func:`ports`), and the config rules of
an ``autopilot = "px4-sitl"`` vehicle (:func:`apply`).

Ports of instance *i*, all on 127.0.0.1: the offboard (API) link listens on 14580+i and sends to 14540+i
(a gateway uses ``udpin:127.0.0.1:<14540+i>``), the ground-station link listens on 18570+i and sends to
14550, SIH's ground truth (HIL_STATE_QUATERNION) goes from 19450+i to 19410+i; MAV_SYS_ID is i+1.

A ``"px4-sitl"`` vehicle names its instance (``px4_instance``, 0..:data:`MAX_INSTANCE`, one vehicle per
instance); its ``mavlink`` defaults to the instance's gateway link and its ``system_id`` to the instance's
MAV_SYS_ID, and must agree with them when given.  No other vehicle has a ``px4_instance`` or
``px4_params``.  Kept apart from :mod:`arena_common.runtime.px4_sitl` (the launcher, numpy and all) so that
every process's config loader (:func:`arena_common.runtime.options.read_config`) stays light.
"""

from __future__ import annotations

from dataclasses import dataclass

from arena_common.core.config import ArenaConfig, VehicleSpec, check_distinct, check_links
from arena_common.core.convert import field_error
from arena_common.core.errors import ArenaError

MAX_INSTANCE = 9  # instance 10 would send its offboard link to 14550, the ground stations' port


class Px4SitlError(ArenaError):
    """No PX4 build, an instance that cannot start or stop, a listener that cannot answer."""


@dataclass(frozen=True, slots=True)
class Ports:
    """The loopback UDP ports and system id of one PX4 SITL instance."""

    instance: int
    offboard: int  # where PX4 sends its offboard (API) link: the gateway listens here
    px4_offboard: int  # where PX4 listens for it
    gcs: int  # where PX4 sends its ground-station link (every instance)
    px4_gcs: int
    truth: int  # where SIH's HIL_STATE_QUATERNION goes: the truth bridge listens here
    px4_truth: int
    system_id: int

    def gateway_mavlink(self) -> str:
        """The gateway's connection string for this instance."""
        return f"udpin:127.0.0.1:{self.offboard}"


def ports(instance: int) -> Ports:
    """The ports of instance ``instance`` (0..:data:`MAX_INSTANCE`)."""
    check_instance(instance)
    return Ports(
        instance=instance,
        offboard=14540 + instance,
        px4_offboard=14580 + instance,
        gcs=14550,
        px4_gcs=18570 + instance,
        truth=19410 + instance,
        px4_truth=19450 + instance,
        system_id=instance + 1,
    )


def check_instance(instance: int) -> int:
    """``instance`` if within 0..:data:`MAX_INSTANCE`, else :class:`Px4SitlError`."""
    if isinstance(instance, bool) or not isinstance(instance, int) or not 0 <= instance <= MAX_INSTANCE:
        raise Px4SitlError(
            f"PX4 SITL instance must be an integer in 0..{MAX_INSTANCE} (instance 10 and above would send "
            f"its offboard link to 14550, the ground stations' port), got {instance!r}"
        )
    return instance


def apply(cfg: ArenaConfig) -> ArenaConfig:
    """``cfg`` with each PX4 SITL vehicle's link and system id filled in from its instance.

    :class:`~arena_common.core.errors.ConfigError` naming the file and the field when a vehicle breaks a
    rule of this module's docstring, or when the ids and ports it fills in clash with another vehicle's
    (:func:`arena_common.core.config.check_links`).
    """
    out = cfg.replace(vehicles={name: _vehicle(cfg.path, name, v) for name, v in cfg.vehicles.items()})
    check_distinct(out, "px4_instance", "a PX4 SITL instance", unset=None)
    check_links(out)
    return out


def _vehicle(path: str, name: str, v: VehicleSpec) -> VehicleSpec:
    where = f"vehicles.{name}"
    if not v.px4_sitl:
        for key, given in (("px4_instance", v.px4_instance is not None), ("px4_params", bool(v.px4_params))):
            if given:
                raise field_error(
                    path, f"{where}.{key}", f'no {key} unless autopilot = "px4-sitl" (got {v.autopilot!r})'
                )
        return v
    n = v.px4_instance
    if n is None:
        raise field_error(
            path,
            f"{where}.px4_instance",
            f'the PX4 SITL instance number (0..{MAX_INSTANCE}) of a "px4-sitl" vehicle',
        )
    if not 0 <= n <= MAX_INSTANCE:
        raise field_error(path, f"{where}.px4_instance", f"an integer in 0..{MAX_INSTANCE}", n)
    p = ports(n)
    if v.mavlink:
        scheme, _, rest = v.mavlink.partition(":")
        host, _, port = rest.rpartition(":")
        if (
            scheme not in ("udpin", "udp")
            or host not in ("127.0.0.1", "localhost", "0.0.0.0")
            or port != str(p.offboard)
        ):
            raise field_error(
                path,
                f"{where}.mavlink",
                f"{p.gateway_mavlink()} for PX4 SITL instance {n} (px4_instance; or leave mavlink out)",
                v.mavlink,
            )
    if v.system_id and v.system_id != p.system_id:  # 0: left out
        raise field_error(
            path,
            f"{where}.system_id",
            f"{p.system_id}, the MAV_SYS_ID of PX4 SITL instance {n} (or leave it out)",
            v.system_id,
        )
    return v.replace(mavlink=v.mavlink or p.gateway_mavlink(), system_id=v.system_id or p.system_id)
