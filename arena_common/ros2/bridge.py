"""The arena as ROS 2 topics, and ROS 2 commands as the arena's: the ``ros2`` service's work.

Out (arena → ROS 2, on the Zenoh threads that receive the arena's samples): see the topic table of
:mod:`arena_common.ros2.messages`.

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from arena_common.bus.session import Bus, Handler, Received
from arena_common.client.arena import Arena
from arena_common.client.offboard import OffboardStream, setpoint_problem
from arena_common.client.vehicle import Vehicle
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ArenaError
from arena_common.geometry.quat import quat_yaw
from arena_common.ros2 import frames, messages, names, types
from arena_common.ros2.node import Node, RosPublisher

__all__ = ["CMD_VEL_TIMEOUT", "Bridge", "BridgeOptions"]

CMD_VEL_TIMEOUT = 0.5  # s without a Twist before the velocity stream ends (the vehicle then holds)
GOTO_TIMEOUT = 10.0  # s the gateway has to accept a goto
WARN = 30  # rcl_interfaces/msg/Log levels
INFO = 20


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
        self.queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=16)
        self.stream: OffboardStream | None = None
        self._lock = threading.Lock()
        self._twist: tuple[float, tuple[float, float, float], float] | None = None  # arrival, body, yr
        self.last_twist = -math.inf  # arrival (monotonic) of the newest accepted Twist
        self.engaged = 0  # velocity streams started (each engages OFFBOARD once)
        self.thread = threading.Thread(target=self._run, name=f"ros2:{vehicle.name}", daemon=True)
        self.thread.start()

    def put(self, kind: str, msg: Any) -> None:
        if kind == "twist":
            self._offer_twist(msg)
            return
        try:
            self.queue.put_nowait((kind, msg))
        except queue.Full:
            self.bridge.refuse(self.vehicle.name, kind, "too many commands waiting: dropped")

    def _offer_twist(self, msg: Any) -> None:
        """On the subscriber's thread: check the Twist at once; keep it as the newest, or refuse it."""
        now = time.monotonic()
        body = (msg.linear.x, -msg.linear.y, -msg.linear.z)  # FLU → FRD
        yr = -msg.angular.z
        problem = None
        if not all(math.isfinite(x) for x in (*body, yr)):
            problem = "velocity not finite"
        else:
            problem = setpoint_problem(self.vehicle, {"v": body, "yr": yr})
        with self._lock:
            if problem is None:
                self._twist, self.last_twist = (now, body, yr), now
            elif self.stream is not None:  # hover rather than fly on; the stream still ends on time
                self._twist = (now, (0.0, 0.0, 0.0), 0.0)
        if problem is not None:
            self.bridge.refuse(self.vehicle.name, "cmd_vel", problem)

    def _run(self) -> None:
        while not self.bridge.stopping.is_set():
            try:
                kind, msg = self.queue.get(timeout=0.02)
            except queue.Empty:
                kind, msg = "", None
            try:
                if kind == "goto":
                    self._goto(msg)
                with self._lock:
                    twist, self._twist = self._twist, None
                if twist is not None:
                    self._fly(twist)
                self._watchdog()
            except Exception as exc:  # one bad command must not end the vehicle's command thread
                self.bridge.refuse(self.vehicle.name, kind or "stream", f"{type(exc).__name__}: {exc}")
        self._end_stream()

    # -- goto ------------------------------------------------------------------------------------------
    def _goto(self, msg: Any) -> None:
        name = self.vehicle.name
        frame = msg.header.frame_id or messages.MAP
        pos = (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z)
        o = msg.pose.orientation
        q = (o.w, o.x, o.y, o.z)
        if frame == messages.MAP:
            p = frames.enu_to_ned(pos)
            yaw = None if not any(q) else frames.ros_yaw_to_heading(quat_yaw(q))
        elif frame == messages.NED_FRAME:
            p = (float(pos[0]), float(pos[1]), float(pos[2]))
            yaw = None if not any(q) else quat_yaw(q)
        else:
            self.bridge.refuse(name, "goto", f"frame {frame!r} unknown: use {messages.MAP!r} or 'arena_ned'")
            return
        if not all(math.isfinite(x) for x in (*p, *q)):
            self.bridge.refuse(name, "goto", "position or orientation not finite")
            return
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
    def _fly(self, twist: tuple[float, tuple[float, float, float], float]) -> None:
        """Fly the newest Twist: on the running stream, or by starting one (engaged once)."""
        name = self.vehicle.name
        _, body, yr = twist
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
    ) -> None:
        self.cfg = cfg
        self.bus = bus
        self.options = options
        self.log = log or logging.getLogger("arena.ros2")
        self.stats = stats
        self.stopping = threading.Event()
        self.vehicles: tuple[str, ...] = options.vehicles or tuple(cfg.vehicles)
        for v in self.vehicles:
            cfg.vehicle(v)  # a ConfigError names the known vehicles
        self.node = Node(bus.session, options.node, domain=options.domain)
        self.rosout = self.node.publisher("/rosout", types.LOG, names.ROSOUT)
        self.tf = self.node.publisher("/tf", types.TF_MESSAGE, names.TF)
        self.tf_static = self.node.publisher("/tf_static", types.TF_MESSAGE, names.TF_STATIC)
        self.diag = self.node.publisher("/diagnostics", types.DIAGNOSTIC_ARRAY, names.DEFAULT)
        self.pubs: dict[tuple[str, str], RosPublisher] = {}
        for v in self.vehicles:
            self.pubs[v, "pose"] = self.node.publisher(
                messages.topic(v, "pose"), types.POSE_STAMPED, names.SENSOR_DATA
            )
            self.pubs[v, "odom"] = self.node.publisher(
                messages.topic(v, "odom"), types.ODOMETRY, names.SENSOR_DATA
            )
            self.pubs[v, "battery"] = self.node.publisher(
                messages.topic(v, "battery"), types.BATTERY_STATE, names.DEFAULT
            )
        self.tf_static.publish(messages.static_frames(time.time_ns()))
        self.arena: Arena | None = None
        self.commands: dict[str, _Commands] = {}
        if options.commands:
            self.arena = Arena(cfg, bus=bus, name=src)
            for v in self.vehicles:
                self.commands[v] = _Commands(self, self.arena.vehicle(v))
                self.node.subscription(
                    messages.topic(v, "goto"), types.POSE_STAMPED, self._cmd(v, "goto"), names.DEFAULT
                )
                self.node.subscription(
                    messages.topic(v, "cmd_vel"), types.TWIST, self._cmd(v, "twist"), names.DEFAULT
                )
        self._subs = [
            bus.subscribe(expr, channel=Handler(fn, self._on_error))
            for expr, fn in (
                ("arena/*/pose", self._on_pose),
                ("arena/*/vision", self._on_vision),
                ("arena/*/state", self._on_state),
                ("arena/*/events", self._on_event),
            )
        ]

    def _cmd(self, vehicle: str, kind: str) -> Any:
        def handle(msg: Any, _att: names.Attachment) -> None:
            self._count("commands")
            self.commands[vehicle].put(kind, msg)

        return handle

    # -- arena → ROS 2 -------------------------------------------------------------------------------------
    def _count(self, what: str) -> None:
        if self.stats is not None:
            self.stats.count(what)

    def _on_error(self, exc: BaseException) -> None:
        self.log.warning("sample not bridged: %s: %s", type(exc).__name__, exc)
        self._count("errors")

    def _vehicle_of(self, item: Received[Any]) -> str | None:
        self._count("in")
        v = keys.parse(item.key).drone
        return v if v in self.vehicles else None

    def _on_pose(self, item: Received[Any]) -> None:
        p, v = item.payload, self._vehicle_of(item)
        if v is None or not isinstance(p, wire.Pose) or not p.ok:
            return
        self.pubs[v, "pose"].publish(messages.pose_stamped(p))
        self.tf.publish(messages.tf(v, p))
        self._count("out")

    def _on_vision(self, item: Received[Any]) -> None:
        p, v = item.payload, self._vehicle_of(item)
        if v is None or not isinstance(p, wire.Pose) or not p.ok:
            return
        self.pubs[v, "odom"].publish(messages.odometry(v, p))
        self._count("out")

    def _on_state(self, item: Received[Any]) -> None:
        s, v = item.payload, self._vehicle_of(item)
        if v is None or not isinstance(s, wire.State):
            return
        self.pubs[v, "battery"].publish(messages.battery(v, s))
        self.diag.publish(messages.diagnostics(v, s))
        self._count("out")

    def _on_event(self, item: Received[Any]) -> None:
        e, v = item.payload, self._vehicle_of(item)
        if v is None or not isinstance(e, wire.Event):
            return
        self.rosout.publish(messages.log(v, e, self.options.node))
        self._count("out")

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
            self.rosout.publish(messages.text_log(time.time_ns(), level, self.options.node, text, function))
        except Exception as exc:  # the session may be closing
            self.log.debug("not on /rosout: %s", exc)

    @property
    def publishers(self) -> Sequence[RosPublisher]:
        """Every ROS 2 publisher of the bridge."""
        return [self.rosout, self.tf, self.tf_static, self.diag, *self.pubs.values()]

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
