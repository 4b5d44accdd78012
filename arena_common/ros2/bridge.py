"""The arena as ROS 2 topics, and ROS 2 commands as the arena's: the ``ros2`` service's work.

Every topic, its QoS, its arena key and its conversion is a row of :data:`arena_common.ros2.topics.TOPICS`;
the bridge loops over that table.

Out (arena → ROS 2, on the Zenoh threads that receive the arena's samples): each arena key the table names
is read with the typed reader every service uses (:func:`~arena_common.bus.session.typed`); a sample that
does not decode, or carries another payload type, is counted and reported (``reject``) with its key and
why, never published.

In (ROS 2 → arena), per vehicle, each handled on the vehicle's own command thread, through the client
library (:class:`~arena_common.client.vehicle.Vehicle`), so the gateway's safety rules, leases and the
``command_hosts`` rule apply exactly as to any program:

- ``/arena/<d>/goto`` (geometry_msgs/msg/PoseStamped, ``header.frame_id`` ``map`` — ENU, the default
  when empty — or ``arena_ned``): the gateway's ``goto`` command to that position, with the pose's yaw
  (none when the orientation is all zeros).  Refused before it is sent when it lies outside the safe
  volume; the gateway refuses what it refuses.
- ``/arena/<d>/cmd_vel`` (geometry_msgs/msg/Twist, body FLU as REP 103 wants: ``linear.x`` forward,
  ``linear.y`` left, ``linear.z`` up, ``angular.z`` yaw rate counter-clockwise): an offboard velocity
  stream (:class:`~arena_common.client.offboard.OffboardStream`, body velocity, 20 Hz, 0.5 s leases)
  that engages OFFBOARD once, at the first Twist; the newest Twist only is flown (one slot, never a
  queue: a Twist that waited behind a slow engage is replaced, not replayed).  When no Twist has
  *arrived* for :data:`CMD_VEL_TIMEOUT` s (arrival times, taken as each Twist comes in, whatever the
  engage takes) the stream ends once and the vehicle holds where it is (AUTO.LOITER); only a Twist that
  arrives after that starts a new stream.  A Twist beyond ``max_speed``, ``max_climb`` or the yaw-rate
  limit is refused the moment it arrives and the stream flies zero velocity instead.

Every refusal is logged with its reason, counted (``refused``) and published on ``/rosout`` (WARN).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from arena_common.bus.session import Bus, Handler, Received, typed
from arena_common.client.arena import Arena
from arena_common.client.offboard import OffboardStream, setpoint_problem
from arena_common.client.vehicle import Vehicle
from arena_common.core import keys
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ArenaError
from arena_common.ros2 import names, topics
from arena_common.ros2.messages import Goto, RosInputError, Velocity, text_log
from arena_common.ros2.node import Node, RosPublisher
from arena_common.ros2.topics import Direction, Topic

__all__ = ["CMD_VEL_TIMEOUT", "Bridge", "BridgeOptions"]

CMD_VEL_TIMEOUT = 0.5  # s without a Twist before the velocity stream ends (the vehicle then holds)
GOTO_TIMEOUT = 10.0  # s the gateway has to accept a goto
WARN = 30  # rcl_interfaces/msg/Log levels
INFO = 20
_HOVER = Velocity((0.0, 0.0, 0.0), 0.0)


@dataclass(frozen=True, slots=True)
class BridgeOptions:
    """What the bridge serves: ROS domain, node name, vehicles (all of the config's when empty), and
    whether it takes commands from ROS 2."""

    domain: int = 0
    node: str = "arena_bridge"
    vehicles: tuple[str, ...] = ()
    commands: bool = True


class _Commands:
    """One vehicle's ROS 2 commands, handled in order on its own thread: gotos in a short queue, Twists
    in one slot that keeps the newest (checked as it arrives)."""

    def __init__(self, bridge: Bridge, vehicle: Vehicle) -> None:
        self.bridge = bridge
        self.vehicle = vehicle
        self.queue: queue.Queue[Goto] = queue.Queue(maxsize=16)
        self.stream: OffboardStream | None = None
        self._lock = threading.Lock()
        self._twist: tuple[float, Velocity] | None = None  # arrival (monotonic), velocity
        self.last_twist = -math.inf  # arrival (monotonic) of the newest accepted Twist
        self.engaged = 0  # velocity streams started (each engages OFFBOARD once)
        self.thread = threading.Thread(target=self._run, name=f"ros2:{vehicle.name}", daemon=True)
        self.thread.start()

    def put(self, command: Goto | Velocity) -> None:
        """On the subscriber's thread: queue a goto, or check a Twist and keep it as the newest."""
        if isinstance(command, Velocity):
            self._offer_twist(command)
            return
        try:
            self.queue.put_nowait(command)
        except queue.Full:
            self.bridge.refuse(self.vehicle.name, "goto", "too many commands waiting: dropped")

    def refuse(self, what: str, reason: str) -> None:
        """Refuse a command; a refused Twist makes a running stream hover (it still ends on time)."""
        if what == "cmd_vel":
            with self._lock:
                if self.stream is not None:
                    self._twist = (time.monotonic(), _HOVER)
        self.bridge.refuse(self.vehicle.name, what, reason)

    def _offer_twist(self, v: Velocity) -> None:
        now = time.monotonic()
        problem = setpoint_problem(self.vehicle, {"v": v.body, "yr": v.yaw_rate})
        if problem is not None:
            self.refuse("cmd_vel", problem)
            return
        with self._lock:
            self._twist, self.last_twist = (now, v), now

    def _run(self) -> None:
        while not self.bridge.stopping.is_set():
            try:
                goto: Goto | None = self.queue.get(timeout=0.02)
            except queue.Empty:
                goto = None
            try:
                if goto is not None:
                    self._goto(goto)
                with self._lock:
                    twist, self._twist = self._twist, None
                if twist is not None:
                    self._fly(twist[1])
                self._watchdog()
            except Exception as exc:  # one bad command must not end the vehicle's command thread
                what = "goto" if goto is not None else "stream"
                self.bridge.refuse(self.vehicle.name, what, f"{type(exc).__name__}: {exc}")
        self._end_stream()

    # -- goto ------------------------------------------------------------------------------------------
    def _goto(self, goto: Goto) -> None:
        name = self.vehicle.name
        p, yaw = goto.p, goto.yaw
        fields: dict[str, Any] = {"p": p} if yaw is None else {"p": p, "yaw": yaw}
        problem = setpoint_problem(self.vehicle, fields)
        if problem is not None:
            self.bridge.refuse(name, "goto", problem)
            return
        self._end_stream()  # a goto replaces a velocity stream
        args: dict[str, Any] = {"p": list(p)}
        if yaw is not None:
            args["yaw"] = yaw
        try:
            res = self.vehicle.command("goto", GOTO_TIMEOUT, **args)
        except ArenaError as exc:
            self.bridge.refuse(name, "goto", str(exc))
            return
        self.bridge.accepted(name, "goto", f"goto {p[0]:.2f} {p[1]:.2f} {p[2]:.2f} (NED): {res.result}")

    # -- cmd_vel ---------------------------------------------------------------------------------------
    def _fly(self, v: Velocity) -> None:
        """Fly the newest Twist: on the running stream, or by starting one (engaged once)."""
        name = self.vehicle.name
        body, yr = v.body, v.yaw_rate
        if self.stream is not None:
            try:
                self.stream.velocity_body(*body, yaw_rate=yr)
            except ArenaError as exc:
                self.bridge.refuse(name, "cmd_vel", str(exc))
                self.stream.velocity_body(0.0, 0.0, 0.0, yaw_rate=0.0)
            return
        stream = self.vehicle.offboard(rate=20.0, lease=0.5, engage=True)
        try:
            stream.velocity_body(*body, yaw_rate=yr)
            stream.__enter__()  # streams, then engages this stream (mode OFFBOARD naming it)
        except ArenaError as exc:
            stream.close()
            self.bridge.refuse(name, "cmd_vel", str(exc))
            return
        self.stream = stream
        self.engaged += 1
        self.bridge.accepted(name, "cmd_vel", "velocity stream started: OFFBOARD")

    def _watchdog(self) -> None:
        if self.stream is None:
            return
        if self.vehicle.mode != "OFFBOARD":
            mode = self.vehicle.mode
            self._end_stream()
            self.bridge.refuse(
                self.vehicle.name, "cmd_vel", f"the vehicle left OFFBOARD ({mode}): stream ended"
            )
        elif time.monotonic() - self.last_twist > CMD_VEL_TIMEOUT:
            self._end_stream()
            self.bridge.accepted(self.vehicle.name, "cmd_vel", "no Twist for 0.5 s: holding")

    def _end_stream(self) -> None:
        with self._lock:
            stream, self.stream = self.stream, None
            self._twist = None  # a Twist that arrived before the stream's end starts nothing
        if stream is not None:
            try:
                stream.__exit__(None, None, None)  # Hold where it is, then stop streaming
            except ArenaError as exc:
                stream.close()
                self.bridge.refuse(self.vehicle.name, "cmd_vel", f"hold at the stream's end failed: {exc}")


class Bridge:
    """Serves one arena's keys as ROS 2 topics on ``bus`` (see the module's docstring)."""

    def __init__(
        self,
        cfg: ArenaConfig,
        bus: Bus,
        options: BridgeOptions = BridgeOptions(),
        *,
        src: str = "ros2",
        stats: Any = None,
        log: logging.Logger | None = None,
        reject: Callable[[str, str], None] | None = None,
    ) -> None:
        """``reject(reason, detail)`` counts and reports an arena sample that is not bridged (a service's
        :meth:`~arena_common.runtime.service.Service.reject`); by default it is logged and counted in
        ``stats``."""
        self.cfg = cfg
        self.bus = bus
        self.options = options
        self.log = log or logging.getLogger("arena.ros2")
        self.stats = stats
        self._reject = reject or self._log_reject
        self.stopping = threading.Event()
        self.vehicles: tuple[str, ...] = options.vehicles or tuple(cfg.vehicles)
        for v in self.vehicles:
            cfg.vehicle(v)  # a ConfigError names the known vehicles
        self.node = Node(bus.session, options.node, domain=options.domain)
        #: Every publisher, by its concrete topic name.
        self.pubs: dict[str, RosPublisher] = {
            name: self.node.publisher(name, row.msg_type, row.qos)
            for name, row in topics.endpoints(self.vehicles, Direction.OUT)
        }
        self.rosout = self.pubs[topics.ROSOUT]
        now = time.time_ns()
        for row in topics.sources().get(None, ()):  # the bridge's own (the arena's static frames)
            self.pubs[row.topic()].publish(row.convert("", now, options.node))
        self.arena: Arena | None = None
        self.commands: dict[str, _Commands] = {}
        if options.commands:
            self.arena = Arena(cfg, bus=bus, name=src)
            for v in self.vehicles:
                self.commands[v] = _Commands(self, self.arena.vehicle(v))
                for row in topics.rows(Direction.IN):  # each a vehicle's own (<d> in its name)
                    self.node.subscription(row.topic(v), row.msg_type, self._command(v, row), row.qos)
        self._subs = [
            bus.subscribe(f"arena/*/{key}", channel=Handler(self._bridge(key, rows), self._on_error))
            for key, rows in topics.sources().items()
            if key is not None
        ]

    def _command(self, vehicle: str, row: Topic) -> Callable[[Any, names.Attachment], None]:
        def handle(msg: Any, _att: names.Attachment) -> None:
            self._count("commands")
            commands = self.commands[vehicle]
            try:
                command = row.convert(msg)
            except RosInputError as exc:
                commands.refuse(row.leaf, str(exc))
                return
            commands.put(command)

        return handle

    # -- arena → ROS 2 -------------------------------------------------------------------------------------
    def _count(self, what: str) -> None:
        if self.stats is not None:
            self.stats.count(what)

    def _on_error(self, exc: BaseException) -> None:
        self.log.warning("sample not bridged: %s: %s", type(exc).__name__, exc)
        self._count("errors")

    def _log_reject(self, reason: str, detail: str) -> None:
        self.log.warning("rejected (%s): %s", reason, detail)
        if self.stats is not None:
            self.stats.reject(reason)

    def _bridge(self, key: str, rows: tuple[Topic, ...]) -> Callable[[Received[Any]], None]:
        """The handler of ``arena/*/<key>``: each sample of a served vehicle becomes every row's message."""
        ptype = rows[0].payload
        assert ptype is not None and all(r.payload is ptype for r in rows), (
            f"arena/<d>/{key}: one payload type"
        )

        def reject(kind: str, detail: str) -> None:
            self._reject(f"{key}: {kind}", detail)

        def handle(item: Received[Any]) -> None:
            self._count("in")
            v = keys.parse(item.key).drone
            if v not in self.vehicles:
                return
            payload = typed(item, ptype, reject)
            if payload is None or not topics.published(payload):
                return
            for row in rows:
                self.pubs[row.topic(v)].publish(row.convert(v, payload, self.options.node))
            self._count("out")

        return handle

    # -- reports -------------------------------------------------------------------------------------------
    def refuse(self, vehicle: str, what: str, reason: str) -> None:
        """Log, count and publish on ``/rosout`` why a ROS 2 command was not carried out."""
        text = f"{vehicle}: {what} refused: {reason}"
        self.log.warning("%s", text)
        self._count("refused")
        self._rosout(WARN, text, what)

    def accepted(self, vehicle: str, what: str, text: str) -> None:
        """Log and publish on ``/rosout`` what a ROS 2 command did."""
        self.log.info("%s: %s", vehicle, text)
        self._rosout(INFO, f"{vehicle}: {text}", what)

    def _rosout(self, level: int, text: str, function: str) -> None:
        try:
            self.rosout.publish(text_log(time.time_ns(), level, self.options.node, text, function))
        except Exception as exc:  # the session may be closing
            self.log.debug("not on /rosout: %s", exc)

    @property
    def publishers(self) -> Sequence[RosPublisher]:
        """Every ROS 2 publisher of the bridge."""
        return list(self.pubs.values())

    def close(self) -> None:
        """Stop taking commands (holding any velocity stream), undeclare everything."""
        self.stopping.set()
        for c in self.commands.values():
            c.thread.join(5.0)
        for s in self._subs:
            s.close()
        if self.arena is not None:
            self.arena.close()
        self.node.close()
