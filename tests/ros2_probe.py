"""A test-only ROS 2 subscriber built from rmw_zenoh's design (docs/design.md), independent of
``arena_common.ros2``: it finds publishers by their liveliness tokens, subscribes to the key expression
the design derives from a token, reads the attachment with zenoh-ext's own deserializer and decodes CDR
with ``pycdr2`` (not ``rosbags``, which the arena serializes with).

No ``from __future__ import annotations`` here: pycdr2 resolves the field types at class creation.
"""

# mypy: disable-error-code="type-arg,valid-type"
# (pycdr2's array[T, n] and sequence[T] are its own annotations, not generics mypy knows)

import threading
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext
from pycdr2 import IdlStruct
from pycdr2.types import array, float32, float64, int32, sequence, uint8, uint32


@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs/msg/Vector3"):
    x: float64
    y: float64
    z: float64


@dataclass
class Point(IdlStruct, typename="geometry_msgs/msg/Point"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs/msg/Quaternion"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs/msg/Pose"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs/msg/PoseStamped"):
    header: Header
    pose: Pose


@dataclass
class Twist(IdlStruct, typename="geometry_msgs/msg/Twist"):
    linear: Vector3
    angular: Vector3


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs/msg/PoseWithCovariance"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs/msg/TwistWithCovariance"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename="nav_msgs/msg/Odometry"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class Transform(IdlStruct, typename="geometry_msgs/msg/Transform"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs/msg/TransformStamped"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs/msg/TFMessage"):
    transforms: sequence[TransformStamped]


@dataclass
class BatteryState(IdlStruct, typename="sensor_msgs/msg/BatteryState"):
    header: Header
    voltage: float32
    temperature: float32
    current: float32
    charge: float32
    capacity: float32
    design_capacity: float32
    percentage: float32
    power_supply_status: uint8
    power_supply_health: uint8
    power_supply_technology: uint8
    present: bool
    cell_voltage: sequence[float32]
    cell_temperature: sequence[float32]
    location: str
    serial_number: str


@dataclass
class Log(IdlStruct, typename="rcl_interfaces/msg/Log"):
    stamp: Time
    level: uint8
    name: str
    msg: str
    file: str
    function: str
    line: uint32


CLASSES: dict[str, Any] = {
    "geometry_msgs::msg::dds_::PoseStamped_": PoseStamped,
    "geometry_msgs::msg::dds_::Twist_": Twist,
    "nav_msgs::msg::dds_::Odometry_": Odometry,
    "tf2_msgs::msg::dds_::TFMessage_": TFMessage,
    "sensor_msgs::msg::dds_::BatteryState_": BatteryState,
    "rcl_interfaces::msg::dds_::Log_": Log,
}


@dataclass
class Endpoint:
    """One publisher or subscription as its liveliness token describes it (design.md's format)."""

    token: str
    kind: str
    node: str
    topic: str
    type_name: str
    type_hash: str
    qos: str

    def keyexpr(self, domain: int = 0) -> str:
        """``<domain>/<fully qualified name>/<type_name>/<type_hash>`` (design.md)."""
        return f"{domain}/{self.topic.lstrip('/')}/{self.type_name}/{self.type_hash}"


def parse(token: str) -> Endpoint | None:
    """``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/<node>/<topic>/<type>/<hash>/<qos>``."""
    parts = token.split("/")
    if len(parts) != 13 or parts[0] != "@ros2_lv":
        return None
    return Endpoint(token, parts[5], parts[8], parts[9].replace("%", "/"), parts[10], parts[11], parts[12])


class Probe:
    """Discovers endpoints (liveliness tokens, with history) and collects the samples of subscribed topics."""

    def __init__(self, session: zenoh.Session, domain: int = 0) -> None:
        self.session = session
        self.domain = domain
        self.tokens: dict[str, bool] = {}
        self.samples: dict[str, list[tuple[Any, tuple[int, int, bytes]]]] = {}
        self.cond = threading.Condition()
        self._subs: list[Any] = []
        self._liveliness = session.liveliness().declare_subscriber(
            f"@ros2_lv/{domain}/**", self._on_token, history=True
        )

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self.cond:
            self.tokens[str(sample.key_expr)] = sample.kind == zenoh.SampleKind.PUT
            self.cond.notify_all()

    def endpoints(self, kind: str = "MP") -> list[Endpoint]:
        with self.cond:
            alive = [t for t, up in self.tokens.items() if up]
        return [e for e in map(parse, alive) if e is not None and e.kind == kind]

    def nodes(self) -> list[str]:
        with self.cond:
            return [t for t, up in self.tokens.items() if up and t.split("/")[5:6] == ["NN"]]

    def find(self, topic: str, kind: str = "MP", timeout: float = 10.0) -> Endpoint:
        """Wait for an endpoint of ``topic``."""
        found: list[Endpoint] = []

        def there() -> bool:
            found[:] = [e for e in self.endpoints(kind) if e.topic == topic]
            return bool(found)

        with self.cond:
            if not self.cond.wait_for(lambda: there(), timeout):
                raise AssertionError(f"no {kind} token for {topic}: {sorted(self.tokens)}")
        return found[0]

    def subscribe(self, ep: Endpoint, transient_local: bool = False) -> None:
        """Subscribe to ``ep``'s key expression; TRANSIENT_LOCAL as rmw_zenoh does (advanced subscriber
        that detects late publishers and queries their cache)."""
        cls = CLASSES[ep.type_name]
        key = ep.keyexpr(self.domain)
        self.samples.setdefault(ep.topic, [])

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            assert att is not None, "rmw_zenoh drops samples without an attachment"
            seq, ts, gid = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], att)
            msg = cls.deserialize(sample.payload.to_bytes())
            with self.cond:
                self.samples[ep.topic].append((msg, (int(seq), int(ts), gid)))
                self.cond.notify_all()

        if transient_local:
            self._subs.append(
                zenoh.ext.declare_advanced_subscriber(
                    self.session,
                    key,
                    on_sample,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
                    subscriber_detection=True,
                )
            )
        else:
            self._subs.append(self.session.declare_subscriber(key, on_sample))

    def wait(self, topic: str, n: int = 1, timeout: float = 10.0) -> list[tuple[Any, tuple[int, int, bytes]]]:
        """The first ``n`` samples of ``topic``."""
        with self.cond:
            if not self.cond.wait_for(lambda: len(self.samples.get(topic, [])) >= n, timeout):
                raise AssertionError(f"{topic}: {len(self.samples.get(topic, []))} of {n} samples")
            return list(self.samples[topic])

    def wait_for(self, topic: str, pred: Any, timeout: float = 10.0) -> Any:
        """The first sample of ``topic`` for which ``pred(msg)``."""
        out: list[Any] = []

        def there() -> bool:
            out[:] = [m for m, _ in self.samples.get(topic, []) if pred(m)]
            return bool(out)

        with self.cond:
            if not self.cond.wait_for(there, timeout):
                got = [m for m, _ in self.samples.get(topic, [])][-3:]
                raise AssertionError(f"{topic}: no matching sample; last: {got}")
        return out[0]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._liveliness.undeclare()


def open_session(endpoint: str, mode: str = "peer") -> zenoh.Session:
    """A Zenoh session of a ROS 2 node on the test's router (``mode`` peer or client), no scouting."""
    conf = zenoh.Config()
    conf.insert_json5("mode", f'"{mode}"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def publish(session: zenoh.Session, key: str, cdr: bytes, seq: int, gid: bytes) -> None:
    """Publish as an rmw_zenoh publisher would: the CDR payload with its attachment."""
    import time

    att = zenoh.ext.z_serialize((zenoh.ext.Int64(seq), zenoh.ext.Int64(time.time_ns()), gid))
    session.put(key, cdr, attachment=att)
