"""The EKF origin given to an autopilot that has none (SET_GPS_GLOBAL_ORIGIN)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Any

from arena_common.core import wire
from arena_common.core.errors import GatewayError
from arena_common.gateway.events import EventSink
from arena_common.mavlink import px4
from arena_common.mavlink.link import MSG, MavlinkLink


def check_origin(origin: Sequence[float]) -> tuple[float, float, float]:
    """A valid (lat, lon, alt) or :class:`GatewayError` naming the bad value."""
    if len(origin) != 3:
        raise GatewayError(f"origin must be (lat, lon, alt), got {tuple(origin)!r}")
    lat, lon, alt = (float(c) for c in origin)
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise GatewayError(f"origin latitude must be within -90..90 degrees, got {lat}")
    if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise GatewayError(f"origin longitude must be within -180..180 degrees, got {lon}")
    if not (math.isfinite(alt) and -1000.0 <= alt <= 10000.0):
        raise GatewayError(f"origin altitude must be within -1000..10000 m, got {alt}")
    return (lat, lon, alt)


class GlobalOrigin:
    """Gives an autopilot that has no EKF origin one with SET_GPS_GLOBAL_ORIGIN, as mavros's set_gp_origin.

    Without GPS, PX4 has no global reference, and its AUTO modes (takeoff, land, hold) need one.  An EKF
    that already has an origin (GNSS, or set before) must keep it: a new one re-bases its local frame.
    So :meth:`request` (link up, autopilot rebooted) first asks for GPS_GLOBAL_ORIGIN (REQUEST_MESSAGE;
    PX4 sends it only when its origin is valid) for ``ask_s`` s; only when none comes does it send ours
    to the vehicle's system id (never 0), every ``period`` s, until the autopilot reports it back, at
    most ``attempts`` times.
    """

    def __init__(
        self,
        link: MavlinkLink,
        target_system: int,
        origin: Sequence[float],
        events: EventSink,
        *,
        period: float = 1.0,
        attempts: int = 5,
        ask_s: float = 1.0,
    ) -> None:
        if not 1 <= int(target_system) <= 250:
            raise GatewayError(f"the origin's target system must be within 1..250, got {target_system}")
        self.link = link
        self.target = int(target_system)
        self.origin = check_origin(origin)
        lat, lon, alt = self.origin
        self._wire = (round(lat * 1e7), round(lon * 1e7), round(alt * 1000.0))
        self.events = events
        self.period = period
        self.attempts = attempts
        self.ask_s = ask_s
        self.sent = 0
        self.confirmed = False
        self.kept = False  # the autopilot had an origin of its own: left alone
        self.reported: tuple[float, float, float] | None = None
        self._asking_until = -math.inf
        self._left = 0
        self._next = math.inf
        self._settled = threading.Event()  # kept, confirmed, or given up: arming need not wait for it

    def wait_settled(self, deadline: float) -> bool:
        """Wait (until the monotonic ``deadline``) for the origin to be kept, confirmed or given up."""
        return self._settled.wait(max(0.0, deadline - time.monotonic()))

    def request(self, now: float) -> None:
        """Ask whether the autopilot has an origin; give it ours if it has none."""
        self._settled.clear()
        self.confirmed = self.kept = False
        self.reported = None
        self._asking_until = now + self.ask_s
        self._left = self.attempts
        self._next = now
        self.supervise(now)

    def supervise(self, now: float) -> None:
        """Ask or resend when due (the supervisor calls it)."""
        if self.confirmed or self.kept or now < self._next:
            return
        self._next = now + self.period / 2
        if now < self._asking_until:
            self.link.send(
                self.link.mav.command_long_encode(
                    self.target, 1, px4.MAV_CMD_REQUEST_MESSAGE, 0, MSG["GPS_GLOBAL_ORIGIN"], 0, 0, 0, 0, 0, 0
                )
            )
            return
        if self._left <= 0:
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.origin
            self.events.emit(
                "setup",
                f"the autopilot did not confirm the EKF origin {lat:.7f}, {lon:.7f}, {alt:.2f} m "
                f"after {self.attempts} SET_GPS_GLOBAL_ORIGIN",
                4,
            )
            return
        self._left -= 1
        self._next = now + self.period
        lat_e7, lon_e7, alt_mm = self._wire
        msg = self.link.mav.set_gps_global_origin_encode(
            self.target, lat_e7, lon_e7, alt_mm, wire.now_ns() // 1000
        )
        # Counted before the send: the autopilot's answer may be handled (by the link's thread) before send
        # returns, and must then be taken for the answer to ours, not for an origin of its own.
        self.sent += 1
        if not self.link.send(msg):
            self.sent -= 1

    def on_gps_global_origin(self, msg: Any, now: float) -> None:
        """The autopilot's origin (GPS_GLOBAL_ORIGIN): kept when it had one, else confirms ours."""
        self.reported = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        if self.sent == 0 and not self.kept and not self.confirmed:
            if now >= self._asking_until + self.period:
                return  # not asked for (a stream); our request decides
            self.kept = True
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.reported
            self.events.emit(
                "setup",
                f"the autopilot has an EKF origin ({lat:.7f}, {lon:.7f}, {alt:.2f} m): left as it is",
                6,
                origin=list(self.reported),
            )
            return
        lat_e7, lon_e7, alt_mm = self._wire
        match = msg.latitude == lat_e7 and msg.longitude == lon_e7 and abs(msg.altitude - alt_mm) <= 10
        if match and not self.confirmed:
            self.confirmed = True
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.origin
            self.events.emit(
                "setup", f"EKF origin set: {lat:.7f}, {lon:.7f}, {alt:.2f} m", 6, origin=list(self.origin)
            )
