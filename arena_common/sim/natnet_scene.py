"""Simulated rigid bodies as OptiTrack Motive would stream them (the Motive emulator's frame source)."""

from __future__ import annotations

import math
import random
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from arena_common.core.config import ArenaConfig
from arena_common.geometry.frames import FrameTransform, quat_multiply
from arena_common.mocap import natnet
from arena_common.mocap.natnet import Frame, ModelDefs, RigidBody, RigidBodyDef
from arena_common.sim.natnet_motive import NatNetServerError, TickClock

__all__ = [
    "ANGLE_NOISE_PER_M",
    "CAMERA_LATENCY",
    "OFFSET_WINDOW",
    "SOFTWARE_LATENCY",
    "TRUTH_TIMEOUT",
    "SampleClock",
    "SceneCounters",
    "SimScene",
]

#: Camera latency (mid-exposure → data received) and Motive's software latency (received → transmit),
#: the medians of the real Motive capture in tests/data/natnet.
CAMERA_LATENCY = 0.00457
SOFTWARE_LATENCY = 0.00081
#: A body whose last true pose is older than this (seconds) is streamed untracked.
TRUTH_TIMEOUT = 0.5
#: Attitude noise per metre of position noise: Motive's typical 0.05° for 0.3 mm.
ANGLE_NOISE_PER_M = math.radians(0.05) / 0.0003

_UNTRACKED_POSE: tuple[natnet.Vec3, natnet.Quat] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


# ------------------------------------------------------------------------------------------------------------
# Simulated scene
# ------------------------------------------------------------------------------------------------------------


#: How long the least delay of a body's true poses is remembered (seconds): what
#: :class:`SampleClock` takes as the offset between the truth's clock and this one.
OFFSET_WINDOW = 2.0


@dataclass(slots=True)
class SampleClock:
    """Places a truth source's own timestamps on ``perf_counter_ns``: the offset between the two clocks is
    the least ``arrival − stamp`` of the last :data:`OFFSET_WINDOW` seconds (the sample that was least
    delayed in transit), so that poses delayed together (a simulation catching up after a stall, a busy
    bus) keep their own instants instead of all taking their arrival's. A stamp is never placed after its
    arrival (a clock running fast, another host's skew)."""

    window_ns: int = round(OFFSET_WINDOW * 1e9)
    _least: deque[tuple[int, int]] = field(default_factory=deque)  # (arrival, offset), offsets increasing

    def place(self, stamp_ns: int, arrival_ns: int) -> int:
        """The ``perf_counter_ns`` instant of a pose stamped ``stamp_ns`` that arrived at ``arrival_ns``."""
        offset = arrival_ns - stamp_ns
        least = self._least
        while least and least[-1][1] >= offset:
            least.pop()
        least.append((arrival_ns, offset))
        while least[0][0] < arrival_ns - self.window_ns:
            least.popleft()
        return min(stamp_ns + least[0][1], arrival_ns)


@dataclass(slots=True)
class _Body:
    name: str
    id: int
    key: str
    # (perf_counter ns, Motive position, Motive quaternion x y z w, tracked, Motive velocity m/s)
    history: deque[tuple[int, natnet.Vec3, natnet.Quat, bool, natnet.Vec3]] = field(
        default_factory=lambda: deque(maxlen=64)
    )
    occlusions: list[tuple[int, int]] = field(default_factory=list)
    clock: SampleClock = field(default_factory=SampleClock)


@dataclass(slots=True)
class SceneCounters:
    """What a :class:`SimScene` did: frames built and dropped, bodies occluded or without fresh truth."""

    frames: int = 0
    dropped: int = 0
    occluded: int = 0  # body-frames untracked because of an occlusion
    untracked: int = 0  # body-frames untracked for lack of a fresh, valid true pose
    updates: int = 0


class SimScene:
    """Simulated rigid bodies as Motive would stream them.

    Feed true poses (arena NED/FRD) with :meth:`update`; :meth:`frame` builds the frame transmitted at
    ``transmit_ns``: the camera mid-exposure is ``camera_latency + software_latency`` earlier and each body's
    pose is its latest true pose at that instant carried on by its velocity to that instant (a pose the
    cameras see while the truth is late, as a real vehicle keeps moving while its simulation stalls),
    converted to Motive's frame with
    ``transform.inverse_pose`` and blurred by ``noise_m`` (Gaussian per axis, and a proportional attitude
    noise, :data:`ANGLE_NOISE_PER_M`). A body is streamed untracked (bit 0 clear, zero pose) before its
    first true pose, when the true pose says ``ok=False``, when it is older than ``truth_timeout``, or while
    occluded. A whole frame is dropped with probability ``dropout``. Randomness comes from ``seed``.
    """

    def __init__(
        self,
        transform: FrameTransform | None = None,
        *,
        noise_m: float = 0.0,
        dropout: float = 0.0,
        seed: int = 0,
        camera_latency: float = CAMERA_LATENCY,
        software_latency: float = SOFTWARE_LATENCY,
        truth_timeout: float = TRUTH_TIMEOUT,
    ) -> None:
        if not (noise_m >= 0 and 0 <= dropout <= 1 and camera_latency >= 0 and software_latency >= 0):
            raise NatNetServerError(
                f"noise ({noise_m} m), dropout ({dropout}) and latencies ({camera_latency}, "
                f"{software_latency} s) must be non-negative, dropout at most 1"
            )
        if not truth_timeout > 0:
            raise NatNetServerError(f"truth timeout must be positive, got {truth_timeout}")
        self.transform = transform or FrameTransform()
        self.noise_m = float(noise_m)
        self.dropout = float(dropout)
        self.camera_latency_ns = round(camera_latency * 1e9)
        self.software_latency_ns = round(software_latency * 1e9)
        self.truth_timeout_ns = round(truth_timeout * 1e9)
        self.counters = SceneCounters()
        self._rng = random.Random(seed)
        self._bodies: dict[str, _Body] = {}
        self._lock = threading.Lock()

    # -- bodies ------------------------------------------------------------------------------------
    def add_body(self, name: str, body_id: int, *, key: str | None = None) -> None:
        """Add rigid body ``name`` with ``body_id``; its true poses come under ``key`` (default: name)."""
        key = key or name
        with self._lock:
            if key in self._bodies:
                raise NatNetServerError(f"rigid body source {key!r} is already in the scene")
            taken = {b.id: b.name for b in self._bodies.values()}
            if body_id in taken:
                raise NatNetServerError(
                    f"rigid body id {body_id} of {name!r} is already used by {taken[body_id]!r}"
                )
            if not name or "\0" in name:
                raise NatNetServerError(f"invalid rigid body name {name!r}")
            self._bodies[key] = _Body(name, int(body_id), key)

    def remove_body(self, key: str) -> None:
        """Remove the body whose true poses come under ``key``."""
        with self._lock:
            if self._bodies.pop(key, None) is None:
                raise NatNetServerError(
                    f"no rigid body {key!r} in the scene (known: {', '.join(self._bodies)})"
                )

    @property
    def keys(self) -> list[str]:
        """The sources of the bodies, in streaming order."""
        return list(self._bodies)

    def model_defs(self) -> ModelDefs:
        """The rigid-body definitions of the scene (no markers; offsets zero)."""
        with self._lock:
            return ModelDefs(tuple(RigidBodyDef(b.name, b.id) for b in self._bodies.values()))

    def occlude(self, key: str, duration: float, start_ns: int | None = None) -> None:
        """Hide body ``key`` from the cameras for ``duration`` seconds from ``start_ns`` (default: now)."""
        if not duration > 0:
            raise NatNetServerError(f"occlusion of {key!r}: duration must be positive, got {duration}")
        start = time.perf_counter_ns() if start_ns is None else int(start_ns)
        with self._lock:
            body = self._bodies.get(key)
            if body is None:
                raise NatNetServerError(
                    f"cannot occlude {key!r}: not in the scene (known: {', '.join(self._bodies)})"
                )
            body.occlusions.append((start, start + round(duration * 1e9)))

    # -- input -------------------------------------------------------------------------------------
    def update(
        self,
        key: str,
        p_ned: Sequence[float],
        q_frd: Sequence[float],
        ok: bool = True,
        t_ns: int | None = None,
        *,
        stamp_ns: int | None = None,
        v_ned: Sequence[float] | None = None,
    ) -> bool:
        """Record a true pose of body ``key`` that arrived at ``t_ns`` (``perf_counter_ns``; default now).

        ``stamp_ns`` is the pose's own time on its source's clock (any epoch): the pose is then placed at
        that instant (:class:`SampleClock`), not at its arrival. ``v_ned`` is its velocity (m/s, arena
        NED), which carries it on to the instant a frame images it. Returns ``False`` for a key not in the
        scene. Raises :class:`~arena_common.geometry.frames.FrameError` for a non-finite position or a
        non-unit quaternion.
        """
        body = self._bodies.get(key)
        if body is None:
            return False
        p, (w, x, y, z) = self.transform.inverse_pose(p_ned, q_frd)
        v: natnet.Vec3 = (0.0, 0.0, 0.0)
        if v_ned is not None:
            ahead = self.transform.inverse_position([a + b for a, b in zip(p_ned, v_ned, strict=True)])
            v = (ahead[0] - p[0], ahead[1] - p[1], ahead[2] - p[2])
        t = time.perf_counter_ns() if t_ns is None else int(t_ns)
        with self._lock:
            if stamp_ns is not None:
                t = body.clock.place(int(stamp_ns), t)
            body.history.append((t, p, (x, y, z, w), bool(ok), v))
        self.counters.updates += 1
        return True

    # -- output ------------------------------------------------------------------------------------
    def frame(
        self, number: int, timestamp: float, transmit_ns: int, clock: TickClock, *, params: int = 0
    ) -> Frame | None:
        """The frame transmitted at ``transmit_ns`` (``perf_counter_ns``), or ``None`` if it is dropped."""
        self.counters.frames += 1
        if self.dropout and self._rng.random() < self.dropout:
            self.counters.dropped += 1
            return None
        received_ns = transmit_ns - self.software_latency_ns
        mid_ns = received_ns - self.camera_latency_ns
        bodies = []
        with self._lock:
            for body in self._bodies.values():
                bodies.append(self._body_at(body, mid_ns))
        wall = time.time()
        secs = int(wall)
        return Frame(
            frame_number=number,
            rigid_bodies=tuple(bodies),
            timestamp=timestamp,
            cam_mid_exposure=clock.at(mid_ns),
            data_received=clock.at(received_ns),
            transmit=clock.at(transmit_ns),
            precision_secs=secs,
            precision_fraction=min(int((wall - secs) * 2**32), 2**32 - 1),
            params=params,
        )

    def _body_at(self, body: _Body, mid_ns: int) -> RigidBody:
        occluded = False
        if body.occlusions:
            body.occlusions = [o for o in body.occlusions if o[1] > mid_ns]
            occluded = any(start <= mid_ns for start, _ in body.occlusions)
        sample = None
        for entry in reversed(body.history):
            sample = entry
            if entry[0] <= mid_ns:
                break
        fresh = sample is not None and sample[3] and mid_ns - sample[0] <= self.truth_timeout_ns
        if occluded or not fresh or sample is None:
            if occluded:
                self.counters.occluded += 1
            else:
                self.counters.untracked += 1
            return RigidBody(body.id, *_UNTRACKED_POSE, 0.0, False, 0)
        t, (px, py, pz), q, _, (vx, vy, vz) = sample
        if mid_ns > t:
            dt = (mid_ns - t) * 1e-9
            px, py, pz = px + vx * dt, py + vy * dt, pz + vz * dt
        if self.noise_m:
            gauss, sigma = self._rng.gauss, self.noise_m
            px, py, pz = px + gauss(0.0, sigma), py + gauss(0.0, sigma), pz + gauss(0.0, sigma)
            half = 0.5 * sigma * ANGLE_NOISE_PER_M
            dq = (1.0, gauss(0.0, half), gauss(0.0, half), gauss(0.0, half))
            qx, qy, qz, qw = q
            w, x, y, z = quat_multiply((qw, qx, qy, qz), dq)
            n = math.sqrt(w * w + x * x + y * y + z * z)
            q = (x / n, y / n, z / n, w / n)
        return RigidBody(body.id, (px, py, pz), q, self.noise_m, True, 1)


def rigid_bodies(cfg: ArenaConfig, names: Sequence[str] = ()) -> list[tuple[str, str, int]]:
    """``(vehicle, rigid-body name, id)`` of the selected vehicles (all by default), in config order.

    Integer ``rigid_body`` values are ids (the body is named after the vehicle); the others get
    ``index + 1``, or the next free id when another vehicle claims that one.
    """
    selected = [cfg.vehicle(n).name for n in names] if names else list(cfg.vehicles)
    every = list(cfg.vehicles.values())
    taken = {v.rigid_body for v in every if isinstance(v.rigid_body, int)}
    out: list[tuple[str, str, int]] = []
    used: set[int] = set()
    for index, v in enumerate(every):
        if isinstance(v.rigid_body, int):
            body_id, name = v.rigid_body, v.name
        else:
            body_id, name = index + 1, v.rigid_body
            while body_id in taken or body_id in used:
                body_id += 1
        used.add(body_id)
        if v.name in selected:
            out.append((v.name, name, body_id))
    return out
