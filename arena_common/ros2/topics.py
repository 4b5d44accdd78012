"""The arena's ROS 2 topics: one table that the bridge (:mod:`~arena_common.ros2.bridge`) and the bag export
(:mod:`~arena_common.ros2.export`) loop over, and that docs/ros2.md's topic table is generated from
(``python -m tools.rosdoc``; ``--check`` in ``make lint``).

A row names the topic (``<d>`` in it: one topic per vehicle, else one for all of them), its message type,
its QoS, the arena key it comes from (published topics) or goes to (subscribed ones), and the conversion:

- published (:attr:`Direction.OUT`): ``convert(vehicle, payload, node)`` → the ROS 2 message, from the
  arena payload of type :attr:`Topic.payload` read on ``arena/<d>/<key>``; ``node`` names the node (the
  logger of ``/rosout``).  A row without a key is the bridge's own: published once when it starts (the
  export: once at the bag's start), its ``payload`` the time in ns.
- subscribed (:attr:`Direction.IN`): ``convert(msg)`` → the arena's command
  (:class:`~arena_common.ros2.messages.Goto`, :class:`~arena_common.ros2.messages.Velocity`), or
  :class:`~arena_common.ros2.messages.RosInputError` naming what the arena cannot take.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from arena_common.core import wire
from arena_common.ros2 import messages, names, types
from arena_common.ros2.names import QoS, ros_name

__all__ = [
    "PROFILE_ORIGIN",
    "ROSOUT",
    "TOPICS",
    "VEHICLE",
    "Direction",
    "Topic",
    "endpoints",
    "published",
    "rows",
    "sources",
]

VEHICLE = "<d>"  # in a topic's name: the vehicle's name as a ROS name token (names.ros_name)


class Direction(enum.Enum):
    """Which way a topic carries the arena."""

    OUT = "published"  # arena → ROS 2: the bridge publishes it, the export writes it
    IN = "subscribed"  # ROS 2 → arena: the bridge subscribes, and commands the vehicle


@dataclass(frozen=True, slots=True)
class Topic:
    """One ROS 2 topic of the arena (see the module's docstring)."""

    name: str  # /arena/<d>/pose, or /tf
    msg_type: str  # pkg/msg/Name
    qos: QoS
    key: str | None  # the leaf of arena/<d>/<key>: where it comes from (OUT) or goes to (IN)
    direction: Direction
    payload: type[wire.Payload] | None  # the arena payload read on the key (OUT rows with a key)
    convert: Callable[..., Any]
    what: str  # for docs/ros2.md: what the topic carries

    @property
    def per_vehicle(self) -> bool:
        """One topic per vehicle (``<d>`` in the name), else one for all."""
        return VEHICLE in self.name

    @property
    def leaf(self) -> str:
        """The name's last part (``goto``, ``cmd_vel``, ``pose``…): how refusals name the topic."""
        return self.name.rsplit("/", 1)[1]

    def topic(self, vehicle: str = "") -> str:
        """The concrete topic name for ``vehicle`` (ignored by a topic for all vehicles)."""
        return self.name.replace(VEHICLE, ros_name(vehicle)) if self.per_vehicle else self.name

    @property
    def arena_key(self) -> str | None:
        """``arena/<drone>/<key>`` as the key table (:data:`arena_common.core.keys.KEYS`) writes it."""
        return None if self.key is None else f"arena/<drone>/{self.key}"


def _out(
    name: str,
    type_name: str,
    qos: QoS,
    key: str | None,
    payload: type[wire.Payload] | None,
    convert: Callable[[str, Any, str], Any],
    what: str,
) -> Topic:
    return Topic(name, type_name, qos, key, Direction.OUT, payload, convert, what)


def _in(name: str, type_name: str, qos: QoS, key: str, convert: Callable[[Any], Any], what: str) -> Topic:
    return Topic(name, type_name, qos, key, Direction.IN, None, convert, what)


ROSOUT = "/rosout"  # where the bridge also says what it refused and did

TOPICS: tuple[Topic, ...] = (
    _out(
        "/arena/<d>/pose",
        types.POSE_STAMPED,
        names.SENSOR_DATA,
        "pose",
        wire.Pose,
        lambda v, p, n: messages.pose_stamped(p),
        "full mocap rate, frame `map`",
    ),
    _out(
        "/arena/<d>/odom",
        types.ODOMETRY,
        names.SENSOR_DATA,
        "vision",
        wire.Pose,
        lambda v, p, n: messages.odometry(v, p),
        "the pose the autopilot gets, with its velocity; twist in the body (`child_frame_id` = `<d>`)",
    ),
    _out(
        "/tf",
        types.TF_MESSAGE,
        names.TF,
        "pose",
        wire.Pose,
        lambda v, p, n: messages.tf(v, p),
        "`map` → `<d>`",
    ),
    _out(
        "/tf_static",
        types.TF_MESSAGE,
        names.TF_STATIC,
        None,
        None,
        lambda v, t_ns, n: messages.static_frames(t_ns),
        "the arena's frames: `map` → `arena_ned`",
    ),
    _out(
        "/arena/<d>/battery",
        types.BATTERY_STATE,
        names.DEFAULT,
        "state",
        wire.State,
        lambda v, s, n: messages.battery(v, s),
        "voltage, percentage (NaN when unknown)",
    ),
    _out(
        "/diagnostics",
        types.DIAGNOSTIC_ARRAY,
        names.DEFAULT,
        "state",
        wire.State,
        lambda v, s, n: messages.diagnostics(v, s),
        "`arena/<d>/link`, `…/estimator` (vision fused), `…/failsafe`, `…/offboard`",
    ),
    _out(
        ROSOUT,
        types.LOG,
        names.ROSOUT,
        "events",
        wire.Event,
        messages.log,
        "logger `<node>.<d>`, MAV_SEVERITY → level; and the bridge's own refusals",
    ),
    _in(
        "/arena/<d>/goto",
        types.POSE_STAMPED,
        names.DEFAULT,
        "cmd",
        messages.goto,
        "the gateway's `goto` (frame `map`, the default, or `arena_ned`)",
    ),
    _in(
        "/arena/<d>/cmd_vel",
        types.TWIST,
        names.DEFAULT,
        "setpoint",
        messages.velocity,
        "an offboard velocity stream (body FLU)",
    ),
)

#: Where each QoS profile of the table comes from (docs/ros2.md says it beside the QoS).
PROFILE_ORIGIN: dict[QoS, str] = {
    names.SENSOR_DATA: "rclcpp's SensorDataQoS",
    names.TF: "tf2's broadcaster",
    names.TF_STATIC: "tf2's static broadcaster",
    names.ROSOUT: "rcl's",
}


def rows(direction: Direction) -> tuple[Topic, ...]:
    """The rows of one direction, in the table's order."""
    return tuple(t for t in TOPICS if t.direction == direction)


def sources() -> dict[str | None, tuple[Topic, ...]]:
    """The published rows by the arena key they come from (``None``: the bridge's own), in order."""
    out: dict[str | None, tuple[Topic, ...]] = {}
    for t in rows(Direction.OUT):
        out[t.key] = (*out.get(t.key, ()), t)
    return out


def endpoints(vehicles: Sequence[str], direction: Direction) -> Iterator[tuple[str, Topic]]:
    """Every concrete topic of ``direction`` for ``vehicles``: ``(name, row)``, a topic for all vehicles
    once."""
    for t in rows(direction):
        if t.per_vehicle:
            for v in vehicles:
                yield t.topic(v), t
        else:
            yield t.name, t


def published(payload: Any) -> bool:
    """Whether a payload becomes ROS 2 messages at all: a pose that is not tracked does not."""
    return not isinstance(payload, wire.Pose) or payload.ok
