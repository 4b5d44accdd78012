"""PX4 SITL truth bridge: SIH's true pose (HIL_STATE_QUATERNION) → ``arena/<drone>/truth`` (Motive emulator).

PX4 SITL instance *N* sends its simulator's ground truth to 127.0.0.1:19410+N — latitude, longitude
(1e-7 °), altitude (mm) and the attitude quaternion, body FRD → NED — at 25 Hz; this service asks for
``--rate`` (default 100 Hz) with SET_MESSAGE_INTERVAL and asks again whenever the rate falls (px4
booted again).  Each sample becomes a :class:`~arena_common.core.wire.Pose` in the arena frame: the position
relative to SIH's home (:func:`~arena_common.runtime.px4_sitl.sih_home`: the floor is z = 0), turned by the
vehicle's ``sim.yaw_deg`` and moved to its ``sim.start``; the quaternion (already NED/FRD) turned by the
same yaw.  The Motive emulator (``services.sim_mocap``) streams it as NatNet, so the arena's whole real
pipeline (ingest → transform → downsampler → gateway) flies PX4 unchanged.

The pose's time is its arrival (PX4 leaves ``time_usec`` at 0 on this link).  The message quantises
positions to ~1.1 cm north, ~0.75 cm east and 1 mm down, which no motion-capture system does: a
hovering vehicle's position then stepped by a centimetre within one frame, the frame transform's velocity
estimate jumped to 0.8 m/s, and the separation guard held a PX4 hovering 0.9 m from another.  So each
position is carried forward by the message's own velocity (1 cm/s steps) and drawn toward the quantised
one over :data:`SMOOTHING_TAU` (:class:`Smoothed`): steps of 11 mm become under 2 mm, and no lag is added (the
unit test's flight at 0.8 m/s stays within 8 mm of the truth, 0.001 mm on average over 30 s).  Stats:
``in`` samples received, ``out`` poses published, ``requests`` rate requests sent.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import msgspec
import typer
from pymavlink import mavutil

from arena_common.bus.session import BusOptions
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.core.services import by_module
from arena_common.geometry.frames import quat_canonical, quat_from_yaw, quat_multiply, quat_normalize
from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.px4_sitl import Px4SitlError, boot_params, find_build, ports, sih_home, sitl_vehicle
from arena_common.runtime.service import running

SERVICE = by_module("services.px4_truth").name  # its one name: arena_common/core/services.py
RATE = 100.0  # Hz asked of PX4 (its 25 Hz default is a coarse mocap)
EARTH_RADIUS = 6371000.0  # m, the sphere PX4's map projection uses


def geodetic_to_ned(
    lat_deg: float, lon_deg: float, alt_m: float, home: Sequence[float]
) -> tuple[float, float, float]:
    """North, east, down [m] of a point from ``home`` (lat °, lon °, alt m): PX4's azimuthal equidistant
    projection on a sphere (the inverse of how SIH makes latitude and longitude), written without the
    cancellation of ``acos`` near zero."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    lat0, lon0 = math.radians(home[0]), math.radians(home[1])
    dlat, dlon = lat - lat0, lon - lon0
    hav = math.sin(dlat / 2) ** 2 + math.cos(lat0) * math.cos(lat) * math.sin(dlon / 2) ** 2
    c = 2.0 * math.atan2(math.sqrt(hav), math.sqrt(max(0.0, 1.0 - hav)))  # the central angle
    k = c / math.sin(c) if c > 1e-12 else 1.0
    # cos(lat0)·sin(lat) − sin(lat0)·cos(lat)·cos(dlon), rearranged so small offsets stay exact.
    north = math.sin(dlat) + math.sin(lat0) * math.cos(lat) * 2.0 * math.sin(dlon / 2) ** 2
    east = math.cos(lat) * math.sin(dlon)
    return k * north * EARTH_RADIUS, k * east * EARTH_RADIUS, -(alt_m - home[2])


SMOOTHING_TAU = 0.1  # s over which a position is drawn toward the quantised one (1.1 cm steps → 1 mm)
SMOOTHING_RESET_S = 0.2  # s without a sample, or a position this far (m, below), starts afresh
SMOOTHING_RESET_M = 0.1


class Smoothed:
    """A vehicle's position between quantised samples: carried by its velocity, drawn toward each sample."""

    def __init__(self) -> None:
        self._t_ns: int | None = None
        self._p: wire.Vec3 = (0.0, 0.0, 0.0)

    def update(self, t_ns: int, p: wire.Vec3, v: wire.Vec3) -> wire.Vec3:
        """The position at ``t_ns`` given the sample ``p`` and velocity ``v`` that arrived then."""
        last, self._t_ns = self._t_ns, t_ns
        if last is not None and 0.0 <= (dt := (t_ns - last) * 1e-9) <= SMOOTHING_RESET_S:
            ahead = (self._p[0] + v[0] * dt, self._p[1] + v[1] * dt, self._p[2] + v[2] * dt)
            if math.dist(ahead, p) <= SMOOTHING_RESET_M:
                a = min(1.0, dt / SMOOTHING_TAU)
                self._p = (
                    ahead[0] + a * (p[0] - ahead[0]),
                    ahead[1] + a * (p[1] - ahead[1]),
                    ahead[2] + a * (p[2] - ahead[2]),
                )
                return self._p
        self._p = p  # the first sample, after a pause, or a jump (PX4 booted again): no smoothing across
        return p


@dataclass(frozen=True, slots=True)
class TruthFrame:
    """How SIH's world maps onto the arena: its home, and where and how the vehicle starts in the arena."""

    home: tuple[float, float, float]  # lat °, lon °, ground altitude m (float32, as PX4 holds it)
    start: tuple[float, float] = (0.0, 0.0)  # north, east in the arena [m]
    yaw: float = 0.0  # rad, the arena heading of SIH's north

    def pose(self, msg: Any, t_ns: int) -> wire.Pose:
        """The arena pose of a HIL_STATE_QUATERNION message received at ``t_ns``."""
        n, e, d = geodetic_to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3, self.home)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        vn, ve, vd = msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01
        q = quat_normalize(msg.attitude_quaternion)
        if self.yaw:
            q = quat_multiply(quat_from_yaw(self.yaw), q)
        return wire.Pose(
            t=t_ns,
            p=(self.start[0] + c * n - s * e, self.start[1] + s * n + c * e, d),
            q=quat_canonical(q),
            ok=True,
            v=(c * vn - s * ve, s * vn + c * ve, vd),
            w=(float(msg.rollspeed), float(msg.pitchspeed), float(msg.yawspeed)),
            vok=True,
            tp=wire.now_ns(),
        )


def truth_frame(cfg: ArenaConfig, vehicle: str) -> TruthFrame:
    """The :class:`TruthFrame` of a PX4 SITL vehicle: SIH's home from its boot parameters (else the
    build's defaults), its arena start and heading from ``sim.start`` / ``sim.yaw_deg``."""
    spec = sitl_vehicle(cfg, vehicle)
    try:
        build = find_build()
    except Px4SitlError:
        build = None  # the bridge can run without the build: SIH's documented defaults
    home = sih_home(boot_params(cfg, spec), os.environ, build)
    return TruthFrame(home, spec.sim.start, math.radians(spec.sim.yaw_deg))


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicle: str,
    host: str | None = None,
    stop: threading.Event | None = None,
    rate: float = RATE,
) -> None:
    """Bridge ``vehicle``'s SIH ground truth to ``arena/<vehicle>/truth`` until ``stop`` is set."""
    if not 0 < rate <= 250:
        raise ConfigError(f"truth rate must be in (0, 250] Hz (SIH runs at 250 Hz), got {rate}")
    spec = sitl_vehicle(cfg, vehicle)
    assert spec.px4_instance is not None
    frame = truth_frame(cfg, vehicle)
    port = ports(spec.px4_instance)
    try:
        conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port.truth}",
            source_system=255,
            source_component=mavlink2.MAV_COMP_ID_MISSIONPLANNER,
            dialect="common",
        )
    except OSError as exc:
        raise ConfigError(f"cannot listen on udp 127.0.0.1:{port.truth}: {exc.strerror or exc}") from None
    with running(SERVICE, cfg, options, vehicle=vehicle, host=host, stop=stop) as svc:
        pub = svc.bus.stream_publisher(keys.truth(vehicle), wire.Pose)
        svc.log.info(
            "udp 127.0.0.1:%d (PX4 SITL instance %d) → %s at %g Hz; home %.7f° %.7f° %.3f m, "
            "start %s, yaw %.1f°",
            port.truth,
            port.instance,
            keys.truth(vehicle),
            rate,
            *frame.home,
            frame.start,
            math.degrees(frame.yaw),
        )
        window_start, in_window, last_request = time.monotonic(), 0, -math.inf
        smoothed = Smoothed()
        try:
            while not svc.stopped:
                msg = conn.recv_match(type="HIL_STATE_QUATERNION", blocking=True, timeout=0.2)
                now = time.monotonic()
                if msg is not None:
                    svc.stats.count("in")
                    in_window += 1
                    try:
                        pose = frame.pose(msg, wire.now_ns())
                        pub.put(msgspec.structs.replace(pose, p=smoothed.update(pose.t, pose.p, pose.v)))
                        svc.stats.count("out")
                    except (ValueError, ZeroDivisionError) as exc:
                        svc.reject("bad_sample", str(exc))
                if now - window_start >= 1.0:
                    slow = 0 < in_window < 0.8 * rate * (now - window_start)
                    if slow and now - last_request >= 2.0:
                        # Asked only once PX4 has been heard: the request goes back to where it sends from.
                        conn.mav.command_long_send(
                            spec.system_id, 1, px4.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                            mavlink2.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, 1e6 / rate, 0, 0, 0, 0, 0,
                        )  # fmt: skip
                        svc.stats.count("requests")
                        last_request = now
                    window_start, in_window = now, 0
        finally:
            conn.close()


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The PX4 SITL vehicle.")],
    rate: Annotated[float, typer.Option("--rate", help="Truth samples per second asked of PX4.")] = RATE,
) -> None:
    """SIH's ground truth of one PX4 SITL vehicle → arena/<drone>/truth (for the Motive emulator)."""
    main(shared.config, shared.bus, vehicle=vehicle, host=shared.host, rate=rate)


if __name__ == "__main__":
    typer.run(cli)
