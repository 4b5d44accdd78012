"""Frame transform: ``arena/sys/frames`` (Motive's frame) → ``arena/<drone>/pose`` (arena NED/FRD), full rate.

It reads one :class:`~arena_common.core.wire.MocapFrame` per mocap frame (every claimed body at once: one
wake-up per frame, not per body). Every body is converted with one precomputed
:class:`~arena_common.geometry.frames.FrameTransform` (``mocap.up_axis`` then the ``[calibration]`` table) and
republished as a :class:`~arena_common.core.wire.Pose` on its vehicle's ``pose`` key, with linear and
angular velocity from a :class:`~arena_common.geometry.filters.VelocityEstimator` per vehicle. The measurement time
``t`` and Motive's frame number ``fn`` are carried through; ``tp`` is the publish time. With the transform
decimating (below), a vehicle's full-rate ``pose`` is published only while someone subscribes to it;
otherwise the downsampler subscribes to every one.

Bodies Motive lost (``ok`` false) are passed on with ``ok=False`` so that consumers see the loss; they
restart the vehicle's velocity estimate and are never made valid here. Undecodable samples are counted
under ``rejected`` in the service's stats and skipped.

With ``[pipeline] decimate = "transform"`` it also runs each configured vehicle's
:class:`~arena_common.pipeline.vision.VisionFilter` (what the downsampler process does otherwise) and publishes
``arena/<drone>/vision`` at the vehicle's ``vision_rate``: one process and one hop less per vehicle.

The per-pose path uses plain float math (several times cheaper than numpy
for a single pose); the transform itself is a small share of the per-pose cost, which is dominated by
msgpack decoding and payload validation.
"""

from __future__ import annotations

import threading
import time

import typer

from arena_common.bus.session import BusOptions, Lane, Publisher, typed
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.geometry.frames import FrameError
from arena_common.pipeline.transform import Decimators, FleetPublisher, PoseConverter, frame_transform
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.frame_transform").name  # its one name: arena_common/core/services.py
SUBSCRIPTION = keys.FRAMES
# One sample per mocap frame: the FIFO absorbs over a second of frames (at 180 Hz) of a stall without ever
# dropping the frame a decimator needs.
QUEUE_CAPACITY = 256
MAX_VEHICLES = 256  # bounds the per-vehicle state a misbehaving publisher could make us create


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Transform every vehicle's mocap stream until ``stop`` is set (or SIGINT/SIGTERM)."""
    converter = PoseConverter(frame_transform(cfg))
    with running(SERVICE, cfg, options, host=host, stop=stop) as svc:
        svc.log.info(
            "Motive %s → arena NED: yaw %.3f°, offset %s",
            converter.transform.up_axis.value,
            cfg.calibration.yaw_deg,
            cfg.calibration.offset,
        )
        decimators = Decimators(svc, cfg) if cfg.pipeline.decimate == "transform" else None
        if decimators is not None:
            svc.log.info("decimating %d vehicles into vision in-process", len(decimators.filters))
        fleet = FleetPublisher(svc.bus.stream_publisher(keys.FLEET, wire.Fleet, Lane.CONTROL))
        sub = svc.bus.subscribe(SUBSCRIPTION, capacity=QUEUE_CAPACITY, ring=False)
        publishers: dict[str, Publisher[wire.Pose]] = {}
        shed_ns = int(cfg.pipeline.shed_after * 1e9)
        while not svc.stopped:
            item = svc.read(sub, 0.2, count="frames")  # dropped: frames the queue could not hold
            frame = typed(item, wire.MocapFrame, svc.reject) if item is not None else None
            if item is None or frame is None:
                continue
            svc.stats.count("in", len(frame.b))  # poses in: what the ingest counted out
            behind = decimators is not None and shed_ns and time.time_ns() - item.t_recv > shed_ns
            for body in frame.b:
                drone = body.v  # a valid vehicle name: the frame passed its checks when it was decoded
                pub = publishers.get(drone)
                if pub is None:
                    if len(publishers) >= MAX_VEHICLES:
                        svc.reject("too_many_vehicles", f"{drone}: already serving {MAX_VEHICLES} vehicles")
                        continue
                    pub = publishers[drone] = svc.bus.stream_publisher(
                        keys.pose(drone), wire.Pose, Lane.CONTROL
                    )
                    svc.log.info("serving %s", drone)
                try:
                    pose = converter.convert(frame, body)
                except FrameError as exc:
                    svc.reject("bad_pose", f"{item.key}, body {body.id} of {drone}: {exc}")
                    continue
                fleet.offer(drone, pose)
                if decimators is not None:
                    decimators.offer(drone, pose)  # vision first: it is the latency-critical output
                    if behind:
                        svc.stats.count("shed")  # behind: the full-rate pose goes, the vision did not
                        continue
                    if not pub.matching:
                        svc.stats.count("unwatched")  # nobody subscribes to the full-rate pose
                        continue
                pub.put(pose)
                svc.stats.count("out")
                if not pose.ok:
                    svc.stats.count("invalid")
            if decimators is not None:
                decimators.end_frame(frame.fn)
            if fleet.tick(time.monotonic_ns()) is not None:
                svc.stats.count("fleet")
            svc.stats.latency((time.time_ns() - item.t_recv) * 1e-9)


@service_command
def cli(
    shared: Shared,
) -> None:
    """Motive frames (arena/sys/frames) → arena-frame poses with velocities (arena/<drone>/pose)."""
    main(shared.config, shared.bus, host=shared.host)


if __name__ == "__main__":
    typer.run(cli)
