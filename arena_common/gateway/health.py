"""What one gateway refuses or fails at without stopping: counted, logged once, said in events (:class:`Health`).

When the vehicle's config names a ``signing_key_file``, the link uses MAVLink 2 signing
(:mod:`arena_common.mavlink.signing`): everything we send is signed (link id 0), and every frame of the vehicle
must be signed with the same key and carry a fresh timestamp, except RADIO_STATUS; refused frames are
counted as rejects (``mavlink: unsigned``, ``mavlink: bad signature``, ``mavlink: replayed``…) and
reported in a ``link`` event (``data.signing``: the reasons) at most every 10 s.  Frames forwarded from a
ground station go out as they are.

What the link drops otherwise (another system's frames, bad CRCs, garbage, frames from another address
than the pinned peer…) is counted once a second, as are the host's clock events (:class:`ClockWatch`).
"""

from __future__ import annotations

import collections
import logging
import time

from arena_common.gateway.clockwatch import ClockWatch
from arena_common.gateway.events import EventSink
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink.link import Frame, MavlinkLink, mavlink2
from arena_common.runtime.service import Stats

__all__ = ["Health"]


class Health:
    """The rejects and failures of one gateway, as counters (``stats``), log lines and events.

    It counts the frames the link drops (:meth:`every_second`) or refuses for their signature
    (:meth:`rejected`, the link's ``on_reject``), the samples of the bus that are not what their key
    carries (:meth:`vision_reject`, :meth:`fleet_reject`, :meth:`estop_reject`), and the samples that
    made a loop fail (:meth:`failed`); once a second it also has the clock's events said (:attr:`clock`).
    """

    def __init__(
        self,
        link: MavlinkLink,
        vision: VisionSender,
        clock: ClockWatch,
        stats: Stats,
        events: EventSink,
        log: logging.Logger,
    ) -> None:
        self.link = link
        self.vision = vision
        self.clock = clock
        self.stats = stats
        self.events = events
        self.log = log
        self._rejects: collections.Counter[tuple[str, str, int]] = collections.Counter()
        self._rejects_report = 0.0
        self._link_counts: dict[str, int] = {}
        self._failures: set[tuple[str, str]] = set()

    def every_second(self) -> None:
        """Count what the link dropped since the last call; say what changed of the clock."""
        self._count_link_rejects()
        self.clock.check()

    def rejected(self, reason: str, frame: Frame) -> None:
        """A frame of the vehicle failed the signature check (reader thread)."""
        self.stats.reject(f"mavlink: {reason}")
        spec = mavlink2.mavlink_map.get(frame.msgid)
        self._rejects[(reason, spec.msgname if spec is not None else str(frame.msgid), frame.compid)] += 1
        now = time.monotonic()
        if now < self._rejects_report:
            return
        self._rejects_report = now + 10.0
        total = sum(self._rejects.values())
        reasons: dict[str, int] = {}
        for (r, _, _), n in self._rejects.items():
            reasons[r] = reasons.get(r, 0) + n
        detail = ", ".join(
            f"{r} {name} (component {c}) ×{n}" for (r, name, c), n in self._rejects.most_common(4)
        )
        self._rejects.clear()
        signing = self.link.signing
        fingerprint = signing.key.fingerprint if signing is not None else "?"
        self.events.emit(
            "link",
            f"signing: dropped {total} frame(s) of system {self.link.system_id}: {detail}; the vehicle must "
            f"sign with the key {fingerprint} (PX4: MAV_SIGN_CFG and its key)",
            4,
            dropped=total,
            signing=reasons,
        )

    def _count_link_rejects(self) -> None:
        """Publish what the link dropped since the last call as rejects with a reason."""
        link = self.link
        totals = {
            "mavlink: foreign system": link.foreign,
            "mavlink: bad crc": link.bad_crc,
            "mavlink: unchecked frame": link.unchecked,
            "mavlink: undecodable": link.decode_errors,
            "mavlink: cannot pack": link.pack_errors,
            "mavlink: wrong source": link.wrong_source,
            "mavlink: over budget": link.over_budget,
            "mavlink: dropped by the system": link.kernel_drops(),
        }
        flooded = link.over_budget + totals["mavlink: dropped by the system"]
        if flooded > self._link_counts.get("flooded", 0):
            self.events.emit(
                "link",
                f"the link is flooded: datagrams dropped beyond its budget of {link.budget}/s "
                "(or the system's receive buffer); see 'mavlink: over budget' in its stats",
                4,
                every=10.0,
                dropped=flooded - self._link_counts.get("flooded", 0),
            )
            self._link_counts["flooded"] = flooded
        if link.wrong_source > self._link_counts.get("mavlink: wrong source", 0):
            self.events.emit(
                "link",
                f"frames from {link.last_wrong_source} dropped: the link is pinned to {link.peer}",
                4,
                every=10.0,
            )
        for reason, total in totals.items():
            self.stats.reject(reason, total - self._link_counts.get(reason, 0))
            self._link_counts[reason] = total
        garbage = link.garbage - self._link_counts.get("garbage", 0)
        self._link_counts["garbage"] = link.garbage
        if garbage > 0:
            self.stats.count("mavlink_garbage_bytes", garbage)
            self.stats.reject("mavlink: garbage")

    def vision_reject(self, kind: str, detail: str, carries: str = "Pose") -> None:
        """A sample on the vehicle's vision key that is no Pose (or on the frames' key that is no
        ``carries``)."""
        reason = "undecodable" if kind == "bad_payload" else f"not a {carries}"
        self.vision.refused(reason)
        self.stats.reject(f"vision: {reason}")

    def fleet_reject(self, kind: str, detail: str) -> None:
        """A sample on the fleet key that is no Fleet."""
        self.stats.reject(f"fleet: {kind}")

    def estop_reject(self, kind: str, detail: str) -> None:
        """A sample on the estop key that is no Estop."""
        self.stats.reject("estop: undecodable" if kind == "bad_payload" else "estop: not an Estop")

    def failed(self, what: str, exc: BaseException) -> None:
        """One sample made a loop fail: count it, log the first of each kind, and go on."""
        self.stats.reject(f"{what}: error")
        key = (what, type(exc).__name__)
        if key not in self._failures:
            self._failures.add(key)
            self.log.error(
                "%s: %s: %s (counted as '%s: error'; going on)", what, key[1], exc, what, exc_info=exc
            )
