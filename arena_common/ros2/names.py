"""rmw_zenoh's names on the wire: topic key expressions, liveliness tokens, QoS strings, GIDs, attachments.

Everything here follows ``ros2/rmw_zenoh`` (the ``rmw_zenoh_cpp`` of ROS 2 Jazzy, Kilted and Rolling) as
its ``docs/design.md`` and ``liveliness_utils.cpp`` state it (commits cited in ``docs/ros2.md``):

- a topic's data travel on ``<domain>/<fully qualified name without its leading slash>/<type>/<hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``;
- each entity declares a liveliness token ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`` with every ``/`` of a name replaced by ``%``;
- the QoS is written relative to rmw_zenoh's defaults (reliable, volatile, keep-last 42, infinite
  deadline, lifespan and lease, automatic liveliness): an empty field means "the default";
- an entity's GID is the XXH3-128 of its liveliness key expression (low 64 bits first, little-endian);
- every publication carries an attachment: sequence number (int64 LE), source timestamp (int64 LE, ns
  since the epoch), the GID's length (one byte, 16) and the 16 GID bytes (zenoh-ext serialization).
"""

from __future__ import annotations

import enum
import re
import struct
from dataclasses import dataclass

import xxhash

__all__ = [
    "ADMIN_SPACE",
    "GID_SIZE",
    "Attachment",
    "Durability",
    "EntityKind",
    "History",
    "QoS",
    "Reliability",
    "decode_attachment",
    "encode_attachment",
    "entity_token",
    "gid",
    "mangle",
    "node_token",
    "parse_token",
    "ros_name",
    "topic_keyexpr",
]

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Jazzy


class EntityKind(enum.Enum):
    """The entity kinds of a liveliness token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(enum.IntEnum):
    """``rmw_qos_reliability_policy_e``."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):
    """``rmw_qos_durability_policy_e``."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(enum.IntEnum):
    """``rmw_qos_history_policy_e``."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2


@dataclass(frozen=True, slots=True)
class QoS:
    """The QoS of one publisher or subscription, as far as it travels in a liveliness token.

    ``lifespan`` is ``(sec, nsec)`` or ``None`` for infinite (rmw_zenoh's default).  Deadline and the
    liveliness lease are always infinite here, liveliness always automatic.
    """

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10
    lifespan: tuple[int, int] | None = None

    def keyexpr(self) -> str:
        """rmw_zenoh's ``qos_to_keyexpr``:
        ``<rel>:<dur>:<hist>,<depth>:<dl s>,<dl ns>:<ls s>,<ls ns>:<lv>,<lease s>,<lease ns>``, each field
        empty where it equals rmw_zenoh's default."""
        rel = "" if self.reliability == Reliability.RELIABLE else str(int(self.reliability))
        dur = "" if self.durability == Durability.VOLATILE else str(int(self.durability))
        hist = "" if self.history == History.KEEP_LAST else str(int(self.history))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        ls = ("", "") if self.lifespan is None else (str(self.lifespan[0]), str(self.lifespan[1]))
        return f"{rel}:{dur}:{hist},{depth}:,:{ls[0]},{ls[1]}:,,"

    @property
    def reliable(self) -> bool:
        """Whether Zenoh should carry it reliably."""
        return self.reliability != Reliability.BEST_EFFORT


DEFAULT_DEPTH = 42  # rmw_zenoh's default depth (qos.cpp)

#: The QoS profiles the arena uses, named after their rclcpp counterparts.
SENSOR_DATA = QoS(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 5)
DEFAULT = QoS(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 10)
TF = QoS(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 100)  # tf2_ros::DynamicBroadcasterQoS
TF_STATIC = QoS(
    Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1
)  # StaticBroadcasterQoS
ROSOUT = QoS(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1000, (10, 0))  # rcl's

_TOKEN = re.compile(r"[^A-Za-z0-9_]")


def ros_name(name: str) -> str:
    """An arena name (letters, digits, ``_``, ``-``, ``.``) as a valid ROS 2 name token: every other
    character becomes ``_``, and a token that would start with a digit gets a leading ``_``."""
    token = _TOKEN.sub("_", name)
    return f"_{token}" if token[:1].isdigit() else token


def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def topic_keyexpr(domain: int, topic: str, type_name: str, type_hash: str) -> str:
    """The key expression a topic's data travel on (``TopicInfo``: leading and trailing ``/`` stripped)."""
    return f"{domain}/{topic.strip('/')}/{type_name}/{type_hash}"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    """The liveliness token of a node (its entity id is its node id)."""
    head = (ADMIN_SPACE, str(domain), zid, str(node_id), str(node_id), EntityKind.NODE.value)
    return "/".join((*head, mangle(enclave), mangle(namespace), mangle(node)))


def entity_token(
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: EntityKind,
    namespace: str,
    node: str,
    topic: str,
    type_name: str,
    type_hash: str,
    qos: QoS,
    enclave: str = "/",
) -> str:
    """The liveliness token of a publisher, subscription, service or client."""
    head = (ADMIN_SPACE, str(domain), zid, str(node_id), str(entity_id), kind.value)
    names = (mangle(enclave), mangle(namespace), mangle(node), mangle(topic), mangle(type_name))
    return "/".join((*head, *names, mangle(type_hash), qos.keyexpr()))


@dataclass(frozen=True, slots=True)
class ParsedToken:
    """A liveliness token taken apart (names demangled)."""

    domain: int
    zid: str
    node_id: str
    entity_id: str
    kind: EntityKind
    enclave: str
    namespace: str
    node: str
    topic: str = ""
    type_name: str = ""
    type_hash: str = ""
    qos: str = ""


def parse_token(key: str) -> ParsedToken:
    """Take a liveliness token apart as rmw_zenoh's ``Entity::make(keyexpr)`` does; ``ValueError`` if it
    is not one."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise ValueError(f"not an rmw_zenoh liveliness token: {key!r}")
    kind = EntityKind(parts[5])
    enclave, namespace, node = (p.replace("%", "/") for p in parts[6:9])
    head = (int(parts[1]), parts[2], parts[3], parts[4], kind, enclave, namespace, node)
    if kind == EntityKind.NODE:
        return ParsedToken(*head)
    if len(parts) != 13:
        raise ValueError(f"a {kind.name.lower()} token has 13 parts: {key!r}")
    return ParsedToken(*head, parts[9].replace("%", "/"), parts[10].replace("%", "/"), parts[11], parts[12])


def gid(token: str) -> bytes:
    """An entity's GID: XXH3-128 of its liveliness key expression, low 64 bits then high 64 bits, each in
    the host's (little-endian) byte order, as ``liveliness::Entity`` computes it."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


@dataclass(frozen=True, slots=True)
class Attachment:
    """What rmw_zenoh attaches to every publication."""

    sequence: int
    timestamp: int  # ns since the Unix epoch, when it was published
    gid: bytes


_ATTACHMENT = struct.Struct("<qqB")


def encode_attachment(sequence: int, timestamp: int, source_gid: bytes) -> bytes:
    """The attachment's bytes: int64 LE, int64 LE, then the GID as a zenoh-ext sequence (LEB128 length
    16, which is one byte, then the bytes)."""
    if len(source_gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(source_gid)}")
    return _ATTACHMENT.pack(sequence, timestamp, GID_SIZE) + source_gid


def decode_attachment(data: bytes) -> Attachment:
    """Read an attachment; ``ValueError`` if it is not one."""
    if len(data) != _ATTACHMENT.size + GID_SIZE:
        raise ValueError(f"an rmw_zenoh attachment has {_ATTACHMENT.size + GID_SIZE} bytes, not {len(data)}")
    seq, ts, n = _ATTACHMENT.unpack_from(data)
    if n != GID_SIZE:
        raise ValueError(f"GID length {n}, not {GID_SIZE}")
    return Attachment(seq, ts, bytes(data[_ATTACHMENT.size :]))
