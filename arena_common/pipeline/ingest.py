"""The ingest's stage: rigid bodies of a mocap frame → the arena's :class:`~arena_common.core.wire.MocapFrame`.

:class:`Ingest` maps each rigid body to its vehicle by the name or id the config gives
(``vehicles.<name>.rigid_body``) and publishes, still in Motive's frame and with its measurement time,
one :class:`~arena_common.core.wire.MocapFrame` per frame with every claimed body on
``arena/sys/frames`` and, while someone subscribes to it, a :class:`~arena_common.core.wire.MocapPose` per
body on its vehicle's ``mocap`` key.  Untracked bodies travel with ``ok=False``; unclaimed ones are
counted and, with ``mocap.publish_unknown``, published on ``arena/sys/bodies/<body>``.  The mocap
ingest service (``services/mocap_ingest.py``) feeds it from a mocap source.
"""

from __future__ import annotations

import math
import re
import time

from arena_common.bus.session import Lane, Publisher
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import InvalidName
from arena_common.mocap.client import TimedFrame
from arena_common.mocap.natnet import RigidBody
from arena_common.runtime.service import Service

__all__ = ["MAX_UNKNOWN_KEYS", "Ingest", "body_key_name", "body_numbers", "encode_pose"]

MAX_UNKNOWN_KEYS = 256  # publishers created for unclaimed bodies, at most
_BAD_KEY_CHARS = re.compile(r"[^A-Za-z0-9_.\-]")


class _Route:
    """Where one rigid body's poses go."""

    __slots__ = ("name", "pub", "vehicle")

    def __init__(self, pub: Publisher[wire.MocapPose], name: str, vehicle: str) -> None:
        self.pub = pub
        self.name = name
        self.vehicle = vehicle


_SKIP = object()  # a body nobody wants (cached until the model definitions change)
_WAIT = object()  # a body whose name is not known yet (model definitions not received)


def body_key_name(name: str, body_id: int) -> str:
    """A key chunk for an unclaimed body: its name with unusable characters replaced, else ``id<N>``."""
    chunk = _BAD_KEY_CHARS.sub("_", name)[:63]
    try:
        return keys.validate_name(chunk, "rigid-body name")
    except InvalidName:
        return f"id{body_id}" if body_id >= 0 else f"id_{-body_id}"


def body_numbers(body: RigidBody, ok: bool) -> tuple[wire.Vec3, wire.Quat, float]:
    """Position, quaternion (Motive's x, y, z, w becomes the wire's w, x, y, z) and marker error of
    ``body`` as the wire carries them: an untracked body's pose is kept when finite, else zeroed
    (receivers refuse non-finite numbers); an unknown or non-finite marker error is sent as NaN."""
    qx, qy, qz, qw = body.quat_xyzw
    err = body.mean_error
    p = body.pos
    q = (qw, qx, qy, qz)
    if not ok and not all(map(math.isfinite, (*p, *q))):
        p, q = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)  # an untracked body's numbers may be anything
    if err is None or not math.isfinite(err):
        err = math.nan
    return p, q, err


def encode_pose(
    t: int,
    fn: int,
    body: RigidBody,
    ok: bool,
    name: str,
    lat: int,
    mts: float,
    tsrc: str,
    tp: int,
) -> bytes:
    """The msgpack bytes of the :class:`~arena_common.core.wire.MocapPose` for ``body`` (see
    :func:`body_numbers`)."""
    p, q, err = body_numbers(body, ok)
    return wire.MocapPose(t, fn, body.id, p, q, ok, name, err, lat, mts, tsrc, tp).encode()


def _valid(body: RigidBody) -> bool:
    """A tracked body whose numbers a receiver will accept (finite, unit quaternion)."""
    x, y, z = body.pos
    qx, qy, qz, qw = body.quat_xyzw
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    norm = qx * qx + qy * qy + qz * qz + qw * qw
    return abs(norm - 1.0) < 2e-3  # |q| within 1e-3 of 1 (NaN fails too)


class Ingest:
    """Maps rigid bodies to vehicles and publishes each frame (and, while watched, each vehicle's pose)."""

    def __init__(self, svc: Service, cfg: ArenaConfig) -> None:
        self.svc = svc
        self.publish_unknown = cfg.mocap.publish_unknown
        self.by_id: dict[int, str] = {}
        self.by_name: dict[str, str] = {}
        for body, vehicle in cfg.body_map().items():
            if isinstance(body, int):
                self.by_id[body] = vehicle
            else:
                self.by_name[body] = vehicle
        self.pubs = {
            v: svc.bus.stream_publisher(keys.mocap(v), wire.MocapPose, Lane.CONTROL) for v in cfg.vehicles
        }
        self.frames = svc.bus.stream_publisher(keys.FRAMES, wire.MocapFrame, Lane.CONTROL)
        self.unknown_pubs: dict[str, Publisher[wire.MocapPose]] = {}
        self.tracked: dict[str, bool] = {}
        self._logged: dict[str, float] = {}
        self.published = 0
        self._routes: dict[int, _Route | object] = {}
        self._models = -1
        self._count = svc.stats.count

    def _resolve(self, body_id: int, frame: TimedFrame) -> _Route | object:
        name = frame.names.get(body_id)
        vehicle = self.by_id.get(body_id)
        if vehicle is None and name is not None:
            vehicle = self.by_name.get(name)
        if vehicle is not None:
            claimed = _Route(self.pubs[vehicle], name or "", vehicle)
            self._routes[body_id] = claimed
            return claimed
        if name is None and frame.models == 0 and self.by_name:
            self._count("awaiting_modeldef")
            return _WAIT  # not cached: the names may arrive with the next frame
        label = name if name is not None else str(body_id)
        self.svc.log.info("rigid body %r (id %d) belongs to no vehicle", label, body_id)
        route: _Route | object = _SKIP
        if self.publish_unknown:
            chunk = body_key_name(label, body_id)
            pub = self.unknown_pubs.get(chunk)
            if pub is None and len(self.unknown_pubs) < MAX_UNKNOWN_KEYS:
                pub = self.unknown_pubs[chunk] = self.svc.bus.stream_publisher(
                    keys.body(chunk), wire.MocapPose
                )
            if pub is not None:
                route = _Route(pub, name or "", "")
        self._routes[body_id] = route
        return route

    def _tracking_changed(self, vehicle: str, ok: bool) -> None:
        """Count and log (at most every 2 s per vehicle: tracking may flicker) a change of tracking."""
        first = vehicle not in self.tracked
        self.tracked[vehicle] = ok
        if not ok:
            self._count("tracking_lost")
        if first and ok:
            return
        now = time.monotonic()
        if now - self._logged.get(vehicle, -10.0) >= 2.0:
            self._logged[vehicle] = now
            self.svc.log.info("%s: tracking %s", vehicle, "regained" if ok else "lost")

    def handle(self, frame: TimedFrame) -> int:
        """Publish one frame (and the watched vehicles' poses); return how many poses went out."""
        if frame.models != self._models:
            self._routes.clear()
            self._models = frame.models
        routes = self._routes
        tp = time.time_ns()
        fn, t, lat, mts, tsrc = frame.frame_number, frame.t, frame.lat, frame.mts, frame.tsrc
        # Encoding does not validate: what the wire contract refuses must not leave here.
        if fn < 0:
            self.svc.reject("bad_frame", f"frame number {fn}")
            return 0
        if not math.isfinite(mts):
            self.svc.reject("bad_timestamp", f"Motive timestamp {mts} in frame {fn}; sent as 0")
            mts = 0.0
        out = unknown = unwatched = 0
        bodies: list[wire.MocapBody] = []
        for body in frame.bodies:
            route = routes.get(body.id)
            if route is None:
                route = self._resolve(body.id, frame)
            if not isinstance(route, _Route):
                if route is _SKIP:
                    unknown += 1
                continue
            vehicle = route.vehicle
            if not vehicle:
                unknown += 1
            ok = body.tracking_valid
            if ok and not _valid(body):
                ok = False
                self.svc.reject("bad_pose", f"body {body.id}: pos {body.pos}, quat {body.quat_xyzw}")
            p, q, err = body_numbers(body, ok)
            if vehicle:
                bodies.append(wire.MocapBody(vehicle, body.id, p, q, ok, route.name, err))
            if not vehicle or route.pub.matching:
                pose = wire.MocapPose(t, fn, body.id, p, q, ok, route.name, err, lat, mts, tsrc, tp)
                route.pub.put(pose)
            else:
                unwatched += 1
            out += 1
            if vehicle and self.tracked.get(vehicle) is not ok:
                self._tracking_changed(vehicle, ok)
        if bodies:
            self.frames.put(wire.MocapFrame(t, fn, tuple(bodies), lat, mts, tsrc, tp))
            self._count("frames")
        self._count("in")
        if out:
            self._count("out", out)
        if unknown:
            self._count("unknown", unknown)
        if unwatched:
            self._count("unwatched", unwatched)  # poses of vehicles whose mocap key nobody reads
        self.published += out
        self.svc.stats.latency((tp - t) / 1e9)
        return out
