"""The transform's stage: a mocap frame's bodies (Motive's frame) → :class:`~arena_common.core.wire.Pose`
(arena NED, body FRD), with velocities, and — when the transform decimates — each vehicle's vision.

:func:`frame_transform` is the configured Motive → arena transform (``mocap.up_axis`` then the
``[calibration]`` table); :class:`PoseConverter` converts one body with it and a
:class:`~arena_common.geometry.filters.VelocityEstimator` per vehicle (plain float math: several times
cheaper than numpy for a single pose); :class:`Decimators` runs each configured vehicle's
:class:`~arena_common.pipeline.vision.VisionFilter` (``[pipeline] decimate = "transform"``).  The frame
transform service (``services/frame_transform.py``) is their wiring.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from arena_common.bus.session import Lane, Publisher
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.geometry.filters import VelocityEstimator
from arena_common.geometry.frames import IDENTITY_QUAT, Calibration, FrameError, FrameTransform, UpAxis
from arena_common.pipeline.vision import VisionFilter, account
from arena_common.runtime.service import Service

__all__ = ["FLEET_RATE", "Decimators", "FleetPublisher", "PoseConverter", "frame_transform"]

FLEET_RATE = 10.0  # Hz of arena/sys/fleet: every vehicle's position, for the gateways' separation
VELOCITY_CUTOFF_HZ = 15.0
VELOCITY_MAX_GAP_S = 0.1
_ZERO3: wire.Vec3 = (0.0, 0.0, 0.0)


def frame_transform(cfg: ArenaConfig) -> FrameTransform:
    """The configured Motive → arena transform (``mocap.up_axis`` and the ``[calibration]`` table)."""
    cal = Calibration.from_degrees(cfg.calibration.yaw_deg, cfg.calibration.offset)
    return FrameTransform(UpAxis.parse(cfg.mocap.up_axis), cal)


@dataclass
class PoseConverter:
    """A mocap frame's bodies → Poses: the frame transform plus one velocity estimator per vehicle.

    Not thread-safe: one converter is driven by one thread.
    """

    transform: FrameTransform
    cutoff_hz: float = VELOCITY_CUTOFF_HZ
    max_gap_s: float = VELOCITY_MAX_GAP_S
    _velocity: dict[str, VelocityEstimator] = field(default_factory=dict, init=False, repr=False)

    def estimator(self, drone: str) -> VelocityEstimator:
        """The velocity estimator of ``drone`` (created on first use)."""
        est = self._velocity.get(drone)
        if est is None:
            est = self._velocity[drone] = VelocityEstimator(self.cutoff_hz, self.max_gap_s)
        return est

    def convert(self, frame: wire.MocapFrame, m: wire.MocapBody, tp: int | None = None) -> wire.Pose:
        """Convert body ``m`` (vehicle ``m.v``) of ``frame``; raises
        :class:`~arena_common.geometry.frames.FrameError` on bad numbers.

        A valid sample needs a unit quaternion (to within 1 %). An invalid one (``ok`` false) keeps its
        converted position, and its converted attitude when the quaternion is usable (identity otherwise),
        and restarts the velocity estimate.
        """
        est = self.estimator(m.v)
        tf = self.transform
        if m.ok:
            p, q = tf.pose(m.p, m.q)
            vel = est.update(frame.t, p, q, True)
        else:
            p = tf.position(m.p)
            try:
                q = tf.quaternion(m.q)
            except FrameError:
                q = IDENTITY_QUAT
            est.reset()
            vel = est.last
        if vel.valid:
            v, w, vok = vel.linear_ned, vel.angular_frd, True
        else:  # unknown velocities travel as zeros with vok false (the wire carries no NaN here)
            v, w, vok = _ZERO3, _ZERO3, False
        return wire.Pose(
            t=frame.t,
            p=p,
            q=q,
            ok=m.ok,
            fn=frame.fn,
            v=v,
            w=w,
            vok=vok,
            tp=wire.now_ns() if tp is None else tp,
        )

    def __len__(self) -> int:
        return len(self._velocity)


class Decimators:
    """The vision filters the transform runs when it decimates (one per configured vehicle).

    A vehicle's vision goes out on its own ``vision`` key while anyone subscribes to it (a gateway of its
    own), and every vehicle's vision of one mocap frame together as one
    :class:`~arena_common.core.wire.VisionFrame` on ``arena/sys/vision`` while anyone subscribes to that
    (a gateway serving several vehicles: one wake-up per frame, not one per vehicle); what nobody reads is
    counted (``vision_unwatched``, ``vision_frames_unwatched``), not sent.
    """

    def __init__(self, svc: Service, cfg: ArenaConfig) -> None:
        self.svc = svc
        self.filters = {name: VisionFilter(v.vision_rate) for name, v in cfg.vehicles.items()}
        self.publishers = {
            name: svc.bus.stream_publisher(keys.vision(name), wire.Pose, Lane.VISION) for name in self.filters
        }
        self.frames = svc.bus.stream_publisher(keys.VISIONS, wire.VisionFrame, Lane.VISION)
        self._frame: list[wire.VisionBody] = []  # this frame's vision, while anyone reads the frames' key
        self._unwatched = False  # this frame had vision that nobody reads as a frame

    def offer(self, drone: str, pose: wire.Pose) -> None:
        """Publish ``pose`` as ``drone``'s vision if its filter passes it (unknown bodies have none)."""
        filt = self.filters.get(drone)
        if filt is None:
            return
        d = filt.process(pose, pose.tp)
        account(self.svc, drone, pose, d, filt.rc, prefix="vision_")
        if d.vision is not None:
            self.svc.stats.count("vision")
            pub = self.publishers[drone]
            if pub.matching:
                pub.put(d.vision)
            else:
                self.svc.stats.count("vision_unwatched")
            if self.frames.matching:
                self._frame.append(wire.VisionBody.of(drone, d.vision))
            else:
                self._unwatched = True

    def end_frame(self, fn: int) -> None:
        """Publish the frame's vision (``fn``: its Motive frame number) as one message, if any passed."""
        if self._frame:
            bodies, self._frame = tuple(self._frame), []
            self.frames.put(wire.VisionFrame(fn, bodies, wire.now_ns()))
            self.svc.stats.count("vision_frames")
        elif self._unwatched:
            self.svc.stats.count("vision_frames_unwatched")
        self._unwatched = False


class FleetPublisher:
    """Gathers each vehicle's newest tracked pose and publishes them all as one
    :class:`~arena_common.core.wire.Fleet` on ``arena/sys/fleet`` at ``rate`` Hz: what every gateway
    reads to keep its vehicle apart from the others (one subscription each, whatever the fleet's size)."""

    def __init__(self, publisher: Publisher[wire.Fleet], rate: float = FLEET_RATE) -> None:
        self.publisher = publisher
        self.period_ns = int(1e9 / rate)
        self._latest: dict[str, wire.Pose] = {}
        self._next_ns = 0
        self.published = 0

    def offer(self, drone: str, pose: wire.Pose) -> None:
        """Note ``drone``'s pose (an untracked one removes the vehicle until it is tracked again)."""
        if pose.ok:
            self._latest[drone] = pose
        else:
            self._latest.pop(drone, None)

    def tick(self, now_ns: int) -> wire.Fleet | None:
        """Publish when due (``now_ns`` on any monotonic-enough clock); the message sent, or None."""
        if now_ns < self._next_ns or not self._latest:
            return None
        self._next_ns = now_ns + self.period_ns
        latest = self._latest
        fleet = wire.Fleet(
            t=max(p.t for p in latest.values()),
            b=tuple(wire.FleetVehicle(n, p.p, p.v if p.vok else _ZERO3) for n, p in latest.items()),
        )
        self.publisher.put(fleet)
        self.published += 1
        return fleet
