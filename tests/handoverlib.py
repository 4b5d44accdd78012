"""Hand-overs of a vehicle, and the seconds after them: shared by the simulated hand-over tier
(tests/system/test_handover.py) and the same flows on PX4 SITL (tests/px4/test_px4_handover.py).

- :class:`DelayedPublisher` / :func:`delay_setpoints` — a program's setpoints reach the bus 50–300 ms
  late, each by its own random delay: they overtake one another and the commands sent after them (the
  key is delayed, as a congested link or a relay would);
- :func:`kinds` — every way a program hands a vehicle over, each with the mode it must leave;
- :class:`TwistBursts` — ROS 2 ``cmd_vel``: a burst of Twists, then silence (the simulated tier);
- :class:`Judge` — the ``WATCH`` s after each hand-over returned: no failsafe, no mode change nobody
  asked for, the mode it must be in.
"""

from __future__ import annotations

import heapq
import itertools
import random
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from arena_common import Arena, Trajectory
from arena_common.bus.session import Bus
from arena_common.client.vehicle import Vehicle
from arena_common.core import wire
from arena_common.core.errors import CommandRejected, SafetyRefused

WATCH = 3.0  # s judged after each hand-over returns


class DelayedPublisher:
    """A publisher whose every sample reaches the bus 50–300 ms late, by its own random delay: samples
    overtake one another and the commands sent after them."""

    def __init__(self, inner: Any, rng: random.Random) -> None:
        self.inner = inner
        self.rng = rng
        self._heap: list[tuple[float, int, Any]] = []
        self._n = itertools.count()
        self._cond = threading.Condition()
        self._closing = False
        self.delayed = 0
        self._thread = threading.Thread(target=self._run, name="delayed-setpoints", daemon=True)
        self._thread.start()

    def put(self, payload: Any) -> None:
        with self._cond:
            due = time.monotonic() + self.rng.uniform(0.05, 0.3)
            heapq.heappush(self._heap, (due, next(self._n), payload))
            self.delayed += 1
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._heap and not self._closing:
                    self._cond.wait()
                if not self._heap:
                    return
                due, _, payload = self._heap[0]
                left = due - time.monotonic()
                if left > 0:
                    self._cond.wait(left)
                    continue
                heapq.heappop(self._heap)
            self.inner.put(payload)

    def close(self) -> None:
        """Deliver what is in flight, then close (the stream's late samples still arrive)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(2.0)
        self.inner.close()


def delay_setpoints(bus: Bus, seed: int) -> list[DelayedPublisher]:
    """Make every setpoint publisher of ``bus`` a :class:`DelayedPublisher`."""
    made: list[DelayedPublisher] = []
    original = bus.stream_publisher
    rng = random.Random(seed)

    def stream_publisher(key: str, ptype: Any, *args: Any) -> Any:
        inner = original(key, ptype, *args)
        if not key.endswith("/setpoint"):
            return inner
        made.append(DelayedPublisher(inner, rng))
        return made[-1]

    bus.stream_publisher = stream_publisher  # type: ignore[method-assign,assignment]
    return made


class Judge:
    """Records each hand-over and what the ``WATCH`` s after it showed (the vehicle's own events and
    state, as a program sees them)."""

    def __init__(self) -> None:
        self.count: dict[str, int] = {}
        self.problems: list[str] = []
        self.lock = threading.Lock()

    def after(self, v: Vehicle, kind: str, expect_mode: str) -> None:
        """Watch the ``WATCH`` s after a hand-over of ``kind`` returned: no mode change, no failsafe."""
        t0 = wire.now_ns()
        time.sleep(WATCH)
        seen = [e for e in v.events() if e.t >= t0 and e.kind in ("mode", "failsafe")]
        mode = str(v.mode)
        with self.lock:
            self.count[kind] = self.count.get(kind, 0) + 1
            if seen:
                self.problems.append(f"{v.name} {kind}: within {WATCH} s after: {[e.text for e in seen]}")
            if mode != expect_mode:
                self.problems.append(f"{v.name} {kind}: mode {mode}, not {expect_mode}")

    @property
    def total(self) -> int:
        with self.lock:
            return sum(self.count.values())


def east(v: Vehicle, de: float) -> tuple[float, float, float]:
    p = v.position
    assert p is not None
    return (p[0], max(-1.0, min(1.0, p[1] + de)), -1.0)


def kinds(other: Arena) -> list[tuple[str, str, Callable[[Vehicle, float], None]]]:
    """(kind, the mode it leaves, what it does): every hand-over a program makes."""

    def follow(v: Vehicle, s: float) -> None:  # follow → the gateway's hold of its end point
        p = v.position
        assert p is not None
        v.follow(Trajectory.min_jerk(p, east(v, 0.3 * s), 1.5))

    def block_exit(v: Vehicle, s: float) -> None:  # an offboard velocity block, left: Hold
        with v.offboard() as ctl:
            ctl.velocity(0.0, 0.2 * s, 0.0)
            time.sleep(0.6)

    def goto_in_stream(v: Vehicle, s: float) -> None:  # the program's own goto inside its block
        with v.offboard() as ctl:
            ctl.position(*east(v, 0.1 * s))
            time.sleep(0.4)
            v.goto(*east(v, 0.2 * s), tolerance=0.5)

    def goto_by_another(v: Vehicle, s: float) -> None:  # another program's goto takes the vehicle
        with pytest.raises((CommandRejected, SafetyRefused), match="takes the vehicle"), v.offboard() as ctl:
            ctl.position(*east(v, 0.1 * s))
            time.sleep(0.4)
            other.vehicle(v.name).goto(*east(v, 0.2 * s), tolerance=0.5)
            time.sleep(0.3)
            ctl.position(*east(v, 0.1 * s))  # the next call says the vehicle was taken

    def stream_after_goto(v: Vehicle, s: float) -> None:  # a goto, then a stream takes over, then Hold
        v.goto(*east(v, 0.2 * s), tolerance=0.5)
        with v.offboard() as ctl:
            ctl.position(*east(v, 0.1 * s))
            time.sleep(0.8)

    return [
        ("follow → hold", "OFFBOARD", follow),
        ("offboard block exit", "AUTO.LOITER", block_exit),
        ("goto during a stream", "OFFBOARD", goto_in_stream),
        ("goto by another program during a stream", "OFFBOARD", goto_by_another),
        ("a stream after a goto", "AUTO.LOITER", stream_after_goto),
    ]


class TwistBursts:
    """ROS 2 ``cmd_vel`` as a ROS 2 node sends it (rmw_zenoh's key and attachment, :mod:`tests.ros2_probe`):
    a burst of Twists at 50 Hz, then silence.  The call returns once the vehicle holds (AUTO.LOITER): the
    designed end of a Twist stream, which must come once, after OFFBOARD engaged once, with no failsafe."""

    def __init__(self, probe: Any) -> None:
        from tests import ros2_probe

        self.rp = ros2_probe
        self.probe = probe
        probe.subscribe(probe.find("/rosout"))
        self._seq = itertools.count(1)
        self._lock = threading.Lock()

    def started(self, name: str) -> int:
        """How many velocity streams the bridge has said it started for ``name`` (on /rosout)."""
        with self.probe.cond:
            got = list(self.probe.samples.get("/rosout", []))
        return sum(1 for m, _ in got if m.msg.startswith(f"{name}: velocity stream started"))

    def __call__(self, v: Vehicle, s: float) -> None:
        rp = self.rp
        ep = self.probe.find(f"/arena/{v.name}/cmd_vel", kind="MS")
        gid = v.name.encode().ljust(16, b"\0")[:16]
        before, t0 = self.started(v.name), wire.now_ns()
        twist = rp.Twist(rp.Vector3(0.0, -0.2 * s, 0.0), rp.Vector3(0.0, 0.0, 0.0))  # FLU: east by s
        for _ in range(50):
            with self._lock:
                seq = next(self._seq)
            rp.publish(self.probe.session, ep.keyexpr(), twist.serialize(), seq, gid)
            time.sleep(0.02)
        deadline = time.monotonic() + 10.0
        while not (v.mode == "AUTO.LOITER" and self.started(v.name) > before):
            assert time.monotonic() < deadline, f"{v.name}: no Hold after the Twists stopped ({v.mode})"
            time.sleep(0.05)

        def modes() -> list[Any]:
            return [e.data.get("mode") for e in v.events() if e.t >= t0 and e.kind == "mode"]

        # The state (v.mode) and the events come on two keys, in either order: the Hold's event may follow.
        deadline = time.monotonic() + 10.0
        while modes()[-1:] != ["AUTO.LOITER"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert modes() in (["AUTO.LOITER"], ["OFFBOARD", "AUTO.LOITER"]), modes()  # engaged once, ended once
        assert self.started(v.name) == before + 1, f"{v.name}: the burst started more than one stream"
        assert not [e.text for e in v.events() if e.t >= t0 and e.kind == "failsafe"]
