"""The arena as a Foxglove 3D scene, built from the bus's payloads: for recordings and the live view.

**Frames.**  The arena frame is NED (x north, y east, z down) and vehicle bodies are FRD; Foxglove's
3D panel, like ROS, expects a z-up world.  The scene therefore has a fixed ENU root frame ``world``
(x east, y north, z up) and, under it, the frame ``arena_ned`` — the arena's own NED frame — by the
constant rotation :data:`WORLD_FROM_NED` (180° about the horizontal axis between north and east:
``(n, e, d)`` in ``arena_ned`` is ``(e, n, -d)`` in ``world``).  Every payload is then used as it
travelled, with no conversion of our own:

- ``arena_ned → <d>``: the mocap pose of vehicle ``<d>`` (``arena/<d>/pose``, body FRD);
- ``arena_ned → <d>/estimate``: the autopilot's estimate (``arena/<d>/state`` p and q);
- entities (room, safe volume, trails, setpoints) are drawn in ``arena_ned`` with NED coordinates.

**Topics** (each message kind on its own topic so that Foxglove's seek, which shows the latest message
of each topic, always finds a whole picture; static content is repeated every second for viewers that
join late and for seeks):

=============================== ================== ===============================================
topic                           schema             content
=============================== ================== ===============================================
``/arena/tf``                   FrameTransforms    ``world → arena_ned`` (repeated every second)
``/arena/<d>/tf``               FrameTransforms    ``arena_ned → <d>``, mocap pose, ≤ ``tf_rate``
``/arena/<d>/estimate/tf``      FrameTransforms    ``arena_ned → <d>/estimate``, ≤ ``tf_rate``
``/arena/scene/room``           SceneUpdate        ``room`` (walls, floor) and ``safe_volume``
``/arena/scene/vehicles``       SceneUpdate        ``<d>`` body + label, ``<d>/estimate`` ghost
``/arena/scene/trails``         SceneUpdate        ``<d>/trail`` and ``<d>/estimate_trail`` paths
``/arena/scene/setpoints``      SceneUpdate        ``<d>/setpoint``, alive for the setpoint's lease
``/arena/log``                  Log                the vehicles' events (status text, failsafes…)
=============================== ================== ===============================================

Messages are encoded with the official Foxglove SDK (``foxglove-sdk``) in its protobuf schemas.
"""

from __future__ import annotations

import math
import tomllib
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache

import foxglove
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CubePrimitive,
    Duration,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.errors import ConfigError, InvalidName

NS = 1_000_000_000
WORLD = "world"
ARENA_FRAME = "arena_ned"
_H = math.sqrt(0.5)
WORLD_FROM_NED = (0.0, _H, _H, 0.0)  # quaternion (w, x, y, z): arena NED → world ENU

TOPIC_TF = "/arena/tf"
TOPIC_ROOM = "/arena/scene/room"
TOPIC_VEHICLES = "/arena/scene/vehicles"
TOPIC_TRAILS = "/arena/scene/trails"
TOPIC_SETPOINTS = "/arena/scene/setpoints"
TOPIC_LOG = "/arena/log"
FRAME_TRANSFORMS = "foxglove.FrameTransforms"
SCENE_UPDATE = "foxglove.SceneUpdate"
LOG = "foxglove.Log"
ENCODING = "protobuf"

# The same colours as the PNG plots (matplotlib's tab10), in the order vehicles appear.
PALETTE = (
    (0.122, 0.467, 0.706),
    (1.000, 0.498, 0.055),
    (0.173, 0.627, 0.173),
    (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741),
    (0.549, 0.337, 0.294),
    (0.890, 0.467, 0.761),
    (0.737, 0.741, 0.133),
)


def pose_tf_topic(drone: str) -> str:
    """``/arena/<d>/tf``: the vehicle's mocap pose as the transform ``arena_ned → <d>``."""
    return f"/arena/{drone}/tf"


def estimate_tf_topic(drone: str) -> str:
    """``/arena/<d>/estimate/tf``: the autopilot's estimate as ``arena_ned → <d>/estimate``."""
    return f"/arena/{drone}/estimate/tf"


def estimate_frame(drone: str) -> str:
    """The frame of a vehicle's autopilot estimate."""
    return f"{drone}/estimate"


@cache
def schemas() -> dict[str, foxglove.Schema]:
    """The Foxglove schemas the scene uses, by name (protobuf ``FileDescriptorSet`` from the SDK)."""
    return {s.name: s for s in (FrameTransforms.get_schema(), SceneUpdate.get_schema(), Log.get_schema())}


@dataclass(frozen=True, slots=True)
class SceneMessage:
    """One encoded Foxglove message: its topic, schema name, protobuf bytes and log time (ns)."""

    topic: str
    schema: str
    data: bytes
    log_time: int


def arena_from_config_text(text: str, path: str = "<recorded config>") -> config_mod.ArenaSpec:
    """The ``[arena]`` of a config file's text (the default arena when absent or unreadable)."""
    if not text:
        return config_mod.ArenaSpec()
    try:
        return config_mod.parse(tomllib.loads(text), path or "<recorded config>").arena
    except (tomllib.TOMLDecodeError, ConfigError):
        return config_mod.ArenaSpec()


def log_level(severity: int) -> LogLevel:
    """MAV_SEVERITY (0 emergency … 7 debug) → Foxglove's log level."""
    if severity <= 1:
        return LogLevel.Fatal
    if severity <= 3:
        return LogLevel.Error
    if severity == 4:
        return LogLevel.Warning
    if severity <= 6:
        return LogLevel.Info
    return LogLevel.Debug


# -- small builders -------------------------------------------------------------------------------------


def _ts(ns: int) -> Timestamp:
    sec, nsec = divmod(max(0, ns), NS)
    return Timestamp(sec, nsec)


def _duration(s: float) -> Duration:
    ns = max(0, round(s * NS))
    return Duration(ns // NS, ns % NS)


def _color(rgb: Sequence[float], a: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def _pose(p: Sequence[float] = (0.0, 0.0, 0.0), q: Sequence[float] = (1.0, 0.0, 0.0, 0.0)) -> Pose:
    return Pose(
        position=Vector3(x=p[0], y=p[1], z=p[2]),
        orientation=Quaternion(x=q[1], y=q[2], z=q[3], w=q[0]),
    )


def _transform(t: int, parent: str, child: str, p: Sequence[float], q: Sequence[float]) -> FrameTransform:
    return FrameTransform(
        timestamp=_ts(t),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=p[0], y=p[1], z=p[2]),
        rotation=Quaternion(x=q[1], y=q[2], z=q[3], w=q[0]),
    )


def _box_edges(lo: Sequence[float], hi: Sequence[float]) -> list[Point3]:
    """The 12 edges of an axis-aligned box, as point pairs (a LINE_LIST)."""
    corners = [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    out: list[Point3] = []
    for i, a in enumerate(corners):
        for b in corners[i + 1 :]:
            if sum(1 for u, v in zip(a, b, strict=True) if u != v) == 1:
                out += [Point3(x=a[0], y=a[1], z=a[2]), Point3(x=b[0], y=b[1], z=b[2])]
    return out


def _yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """A rotation about Down by ``yaw`` (NED heading) as (w, x, y, z)."""
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def _finite(v: Sequence[float] | None) -> bool:
    return v is not None and all(math.isfinite(x) for x in v)


# -- the scene ------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Vehicle:
    name: str
    color: tuple[float, float, float]
    pose_seen: bool = False
    tracked: bool = True
    p: tuple[float, float, float] | None = None  # latest mocap position, NED
    q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    t: int = 0  # measurement time of p and q
    last_tf: int = -(2**62)
    last_est_tf: int = -(2**62)
    trail: deque[tuple[int, tuple[float, float, float]]] = field(default_factory=deque)
    est_trail: deque[tuple[int, tuple[float, float, float]]] = field(default_factory=deque)
    state: wire.State | None = None
    label: str = ""
    setpoint: wire.Setpoint | None = None
    setpoint_recv: int = 0


class Scene:
    """Turns the arena's payloads into Foxglove messages (see the module doc for frames and topics).

    Feed it every sample with :meth:`add` and call :meth:`tick` with the current time (ns, the clock of
    the samples' receive times) to get the periodic messages.  Not thread-safe.
    """

    def __init__(
        self,
        arena: config_mod.ArenaSpec | None = None,
        *,
        tf_rate: float = 60.0,
        trail_s: float = 120.0,
        trail_rate: float = 5.0,
        trail_period_s: float = 0.5,
        static_period_s: float = 1.0,
        setpoint_rate: float = 10.0,
    ) -> None:
        self.arena = arena or config_mod.ArenaSpec()
        self._tf_gap = round(NS / tf_rate) if tf_rate > 0 else 0
        self._trail_ns = round(trail_s * NS)
        self._trail_gap = round(NS / trail_rate)
        self._trail_period = round(trail_period_s * NS)
        self._static_period = round(static_period_s * NS)
        self._setpoint_gap = round(NS / setpoint_rate)
        self.vehicles: dict[str, _Vehicle] = {}
        self._next_static: int | None = None
        self._next_trails = 0
        self._next_setpoints = 0
        self._setpoints_dirty = False
        self._vehicles_dirty = False
        self.messages = 0

    # -- input ------------------------------------------------------------------------------------------
    def add(self, key: str, payload: wire.Payload, t_recv: int) -> list[SceneMessage]:
        """Messages caused by one decoded sample (often none: rates are limited)."""
        try:
            parsed = keys.parse(key)
        except InvalidName:
            return []
        drone = parsed.drone
        if drone is None:
            return []
        out: list[SceneMessage] = []
        if isinstance(payload, wire.Pose) and parsed.kind in ("pose", "vision"):
            v = self._vehicle(drone)
            if parsed.kind == "vision" and v.pose_seen:
                return []  # the full-rate pose already draws this vehicle
            v.pose_seen = v.pose_seen or parsed.kind == "pose"
            self._on_pose(v, payload, t_recv, out)
        elif isinstance(payload, wire.State):
            self._on_state(self._vehicle(drone), payload, t_recv, out)
        elif isinstance(payload, wire.Setpoint):
            v = self._vehicle(drone)
            v.setpoint, v.setpoint_recv = payload, t_recv
            self._setpoints_dirty = True
        elif isinstance(payload, wire.Event):
            msg = Log(
                timestamp=_ts(payload.t),
                level=log_level(payload.sev),
                message=f"[{payload.kind}] {payload.text}",
                name=drone,
            )
            out.append(self._msg(TOPIC_LOG, LOG, msg.encode(), t_recv))
        return out

    def tick(self, now: int) -> list[SceneMessage]:
        """The periodic messages due at ``now``: static scene, trails, vehicles, pending setpoints."""
        out: list[SceneMessage] = []
        if self._next_static is None or now >= self._next_static:
            self._next_static = now + self._static_period
            out += self.static(now)
            self._vehicles_dirty = bool(self.vehicles)
        if self._vehicles_dirty:
            self._vehicles_dirty = False
            out.append(self._msg(TOPIC_VEHICLES, SCENE_UPDATE, self._vehicles_update(now), now))
        if now >= self._next_trails and self.vehicles:
            self._next_trails = now + self._trail_period
            out.append(self._msg(TOPIC_TRAILS, SCENE_UPDATE, self._trails_update(now), now))
        if self._setpoints_dirty and now >= self._next_setpoints:
            self._setpoints_dirty = False
            self._next_setpoints = now + self._setpoint_gap
            out.append(self._msg(TOPIC_SETPOINTS, SCENE_UPDATE, self._setpoints_update(now), now))
        return out

    def flush(self, now: int) -> list[SceneMessage]:
        """The vehicles and their whole trails now, due or not (a recording's last word on its paths)."""
        if not self.vehicles:
            return []
        out: list[SceneMessage] = []
        for v in self.vehicles.values():
            if v.p is not None and v.last_tf != v.t:  # the last pose, should the rate limit have held it
                v.last_tf = v.t
                tf = FrameTransforms(transforms=[_transform(v.t, ARENA_FRAME, v.name, v.p, v.q)])
                out.append(self._msg(pose_tf_topic(v.name), FRAME_TRANSFORMS, tf.encode(), now))
        self._next_trails = now + self._trail_period
        self._vehicles_dirty = False
        return [
            *out,
            self._msg(TOPIC_VEHICLES, SCENE_UPDATE, self._vehicles_update(now), now),
            self._msg(TOPIC_TRAILS, SCENE_UPDATE, self._trails_update(now), now),
        ]

    def static(self, now: int) -> list[SceneMessage]:
        """``world → arena_ned`` and the room with its safe volume, stamped ``now``."""
        tf = FrameTransforms(
            transforms=[_transform(now, WORLD, ARENA_FRAME, (0.0, 0.0, 0.0), WORLD_FROM_NED)]
        )
        return [
            self._msg(TOPIC_TF, FRAME_TRANSFORMS, tf.encode(), now),
            self._msg(TOPIC_ROOM, SCENE_UPDATE, self._room_update(now), now),
        ]

    # -- internals --------------------------------------------------------------------------------------
    def _msg(self, topic: str, schema: str, data: bytes, t: int) -> SceneMessage:
        self.messages += 1
        return SceneMessage(topic, schema, data, t)

    def _vehicle(self, drone: str) -> _Vehicle:
        v = self.vehicles.get(drone)
        if v is None:
            v = self.vehicles[drone] = _Vehicle(drone, PALETTE[len(self.vehicles) % len(PALETTE)])
            self._vehicles_dirty = True
        return v

    def _append_trail(
        self, trail: deque[tuple[int, tuple[float, float, float]]], t: int, p: tuple[float, float, float]
    ) -> None:
        if trail:
            t_last, p_last = trail[-1]
            if t - t_last < self._trail_gap:
                return
            if t - t_last < NS and math.dist(p, p_last) < 0.01:
                return  # standing still: one point a second is enough
        trail.append((t, p))
        while trail and t - trail[0][0] > self._trail_ns:
            trail.popleft()

    def _on_pose(self, v: _Vehicle, pose: wire.Pose, t_recv: int, out: list[SceneMessage]) -> None:
        if v.tracked != pose.ok:
            v.tracked = pose.ok
            self._vehicles_dirty = True
        if not pose.ok or not _finite(pose.p) or not _finite(pose.q):
            return  # an untracked body keeps its last drawn pose; its label says "lost"
        p = (pose.p[0], pose.p[1], pose.p[2])
        v.p, v.q, v.t = p, (pose.q[0], pose.q[1], pose.q[2], pose.q[3]), pose.t
        self._append_trail(v.trail, pose.t, p)
        if pose.t - v.last_tf >= self._tf_gap or pose.t < v.last_tf:
            v.last_tf = pose.t
            tf = FrameTransforms(transforms=[_transform(pose.t, ARENA_FRAME, v.name, p, pose.q)])
            out.append(self._msg(pose_tf_topic(v.name), FRAME_TRANSFORMS, tf.encode(), t_recv))

    def _on_state(self, v: _Vehicle, state: wire.State, t_recv: int, out: list[SceneMessage]) -> None:
        first_estimate = state.p is not None and (v.state is None or v.state.p is None)
        v.state = state
        label = self._label(v)
        if label != v.label or first_estimate:
            v.label = label
            self._vehicles_dirty = True
        if not _finite(state.p) or not _finite(state.q):
            return
        assert state.p is not None and state.q is not None
        p = (state.p[0], state.p[1], state.p[2])
        self._append_trail(v.est_trail, state.t, p)
        if state.t - v.last_est_tf >= self._tf_gap or state.t < v.last_est_tf:
            v.last_est_tf = state.t
            tf = FrameTransforms(
                transforms=[_transform(state.t, ARENA_FRAME, estimate_frame(v.name), p, state.q)]
            )
            out.append(self._msg(estimate_tf_topic(v.name), FRAME_TRANSFORMS, tf.encode(), t_recv))

    @staticmethod
    def _label(v: _Vehicle) -> str:
        parts = [v.name]
        s = v.state
        if s is not None:
            if not s.link:
                parts.append("NO LINK")
            parts.append(s.mode or "?")
            parts.append("armed" if s.armed else "disarmed")
            if s.bat is not None:
                parts.append(f"{s.bat * 100:.0f}%")
        if not v.tracked:
            parts.append("LOST")
        return " · ".join(parts)

    def _room_update(self, now: int) -> bytes:
        n, e, h = self.arena.size
        (sn0, sn1), (se0, se1), (sd0, sd1) = self.arena.safe_box()
        room = SceneEntity(
            timestamp=_ts(now),
            frame_id=ARENA_FRAME,
            id="room",
            metadata=[],
            lines=[
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    pose=_pose(),
                    thickness=2.0,
                    scale_invariant=True,
                    points=_box_edges((-n / 2, -e / 2, -h), (n / 2, e / 2, 0.0)),
                    color=_color((0.85, 0.85, 0.85), 1.0),
                )
            ],
            cubes=[  # the floor, a thin slab just below z = 0 (down is +z)
                CubePrimitive(
                    pose=_pose((0.0, 0.0, 0.005)),
                    size=Vector3(x=n, y=e, z=0.01),
                    color=_color((0.55, 0.55, 0.6), 0.35),
                )
            ],
            texts=[
                TextPrimitive(
                    pose=_pose((n / 2, -e / 2, -h)),
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=_color((0.9, 0.9, 0.9)),
                    text=f"{self.arena.name} {n:g} × {e:g} × {h:g} m (N, E, up)",
                )
            ],
        )
        safe = SceneEntity(
            timestamp=_ts(now),
            frame_id=ARENA_FRAME,
            id="safe_volume",
            lines=[
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    pose=_pose(),
                    thickness=1.0,
                    scale_invariant=True,
                    points=_box_edges((sn0, se0, sd0), (sn1, se1, sd1)),
                    color=_color((0.2, 0.8, 0.3), 0.9),
                )
            ],
            cubes=[
                CubePrimitive(
                    pose=_pose(((sn0 + sn1) / 2, (se0 + se1) / 2, (sd0 + sd1) / 2)),
                    size=Vector3(x=sn1 - sn0, y=se1 - se0, z=sd1 - sd0),
                    color=_color((0.2, 0.8, 0.3), 0.06),
                )
            ],
        )
        return SceneUpdate(entities=[room, safe]).encode()

    def _vehicles_update(self, now: int) -> bytes:
        entities: list[SceneEntity] = []
        for v in self.vehicles.values():
            entities.append(
                SceneEntity(
                    timestamp=_ts(now),
                    frame_id=v.name,
                    id=v.name,
                    frame_locked=True,
                    cubes=[
                        CubePrimitive(
                            pose=_pose(), size=Vector3(x=0.22, y=0.22, z=0.05), color=_color(v.color, 0.9)
                        )
                    ],
                    arrows=[  # forward: +x of the FRD body
                        ArrowPrimitive(
                            pose=_pose(),
                            shaft_length=0.2,
                            shaft_diameter=0.02,
                            head_length=0.08,
                            head_diameter=0.06,
                            color=_color(v.color),
                        )
                    ],
                    texts=[
                        TextPrimitive(
                            pose=_pose((0.0, 0.0, -0.2)),  # above the body (z is down)
                            billboard=True,
                            font_size=13.0,
                            scale_invariant=True,
                            color=_color((1.0, 1.0, 1.0)),
                            text=self._label(v),
                        )
                    ],
                )
            )
            if v.state is not None and v.state.p is not None:
                entities.append(
                    SceneEntity(
                        timestamp=_ts(now),
                        frame_id=estimate_frame(v.name),
                        id=estimate_frame(v.name),
                        frame_locked=True,
                        spheres=[
                            SpherePrimitive(
                                pose=_pose(), size=Vector3(x=0.18, y=0.18, z=0.18), color=_color(v.color, 0.3)
                            )
                        ],
                        arrows=[
                            ArrowPrimitive(
                                pose=_pose(),
                                shaft_length=0.15,
                                shaft_diameter=0.01,
                                head_length=0.05,
                                head_diameter=0.04,
                                color=_color(v.color, 0.5),
                            )
                        ],
                    )
                )
        return SceneUpdate(entities=entities).encode()

    def _trails_update(self, now: int) -> bytes:
        entities: list[SceneEntity] = []
        for v in self.vehicles.values():
            for ident, trail, thick, alpha in (
                (f"{v.name}/trail", v.trail, 3.0, 1.0),
                (f"{v.name}/estimate_trail", v.est_trail, 1.5, 0.5),
            ):
                points = [Point3(x=p[0], y=p[1], z=p[2]) for _, p in trail]
                if v.p is not None and trail is v.trail:
                    points.append(Point3(x=v.p[0], y=v.p[1], z=v.p[2]))  # up to where it is now
                if len(points) < 2:
                    continue
                entities.append(
                    SceneEntity(
                        timestamp=_ts(now),
                        frame_id=ARENA_FRAME,
                        id=ident,
                        lines=[
                            LinePrimitive(
                                type=LinePrimitiveLineType.LineStrip,
                                pose=_pose(),
                                thickness=thick,
                                scale_invariant=True,
                                points=points,
                                color=_color(v.color, alpha),
                            )
                        ],
                    )
                )
        return SceneUpdate(entities=entities).encode()

    def _setpoints_update(self, now: int) -> bytes:
        entities: list[SceneEntity] = []
        for v in self.vehicles.values():
            sp = v.setpoint
            if sp is None:
                continue
            left = sp.lease - (now - v.setpoint_recv) / NS
            if left <= 0:
                continue
            spheres: list[SpherePrimitive] = []
            arrows: list[ArrowPrimitive] = []
            lines: list[LinePrimitive] = []
            if _finite(sp.p):
                assert sp.p is not None
                spheres.append(
                    SpherePrimitive(
                        pose=_pose(sp.p), size=Vector3(x=0.1, y=0.1, z=0.1), color=_color(v.color, 0.8)
                    )
                )
                if sp.yaw is not None and math.isfinite(sp.yaw):
                    arrows.append(
                        ArrowPrimitive(
                            pose=_pose(sp.p, _yaw_quat(sp.yaw)),
                            shaft_length=0.15,
                            shaft_diameter=0.01,
                            head_length=0.05,
                            head_diameter=0.03,
                            color=_color(v.color, 0.8),
                        )
                    )
                if v.p is not None:
                    lines.append(
                        LinePrimitive(
                            type=LinePrimitiveLineType.LineStrip,
                            pose=_pose(),
                            thickness=1.0,
                            scale_invariant=True,
                            points=[
                                Point3(x=v.p[0], y=v.p[1], z=v.p[2]),
                                Point3(x=sp.p[0], y=sp.p[1], z=sp.p[2]),
                            ],
                            color=_color(v.color, 0.5),
                        )
                    )
            elif _finite(sp.v) and v.p is not None:
                assert sp.v is not None
                speed = math.sqrt(sum(x * x for x in sp.v))
                if speed > 1e-6:
                    # an arrow along the commanded velocity, from the vehicle, 1 s long
                    yaw = math.atan2(sp.v[1], sp.v[0])
                    pitch = -math.asin(max(-1.0, min(1.0, sp.v[2] / speed)))
                    cy, sy, cp, spi = (
                        math.cos(yaw / 2),
                        math.sin(yaw / 2),
                        math.cos(pitch / 2),
                        math.sin(pitch / 2),
                    )
                    q = (cy * cp, -sy * spi, cy * spi, sy * cp)
                    arrows.append(
                        ArrowPrimitive(
                            pose=_pose(v.p, q),
                            shaft_length=speed * 0.8,
                            shaft_diameter=0.015,
                            head_length=speed * 0.2,
                            head_diameter=0.04,
                            color=_color(v.color, 0.8),
                        )
                    )
            if not (spheres or arrows or lines):
                continue
            entities.append(
                SceneEntity(
                    timestamp=_ts(now),
                    frame_id=ARENA_FRAME,
                    id=f"{v.name}/setpoint",
                    lifetime=_duration(left),
                    spheres=spheres,
                    arrows=arrows,
                    lines=lines,
                )
            )
        return SceneUpdate(entities=entities).encode()
