"""MAVLink ids of component metadata, and the two messages pymavlink (2.4.x) lacks: COMPONENT_METADATA and
COMPONENT_INFORMATION, added to the dialect by :func:`register_messages`."""

from __future__ import annotations

import struct
from typing import Any, Final

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2

# --- MAVLink ids and enums --------------------------------------------------------------------------
FILE_TRANSFER_PROTOCOL: Final = mavlink2.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL
COMPONENT_INFORMATION: Final = 395
COMPONENT_METADATA: Final = 397
MAV_CMD_REQUEST_MESSAGE: Final = px4.MAV_CMD_REQUEST_MESSAGE
#: The messages :meth:`MetadataClient.on_message` wants from the link's reader.
HANDLED_MESSAGES: Final = frozenset({FILE_TRANSFER_PROTOCOL, COMPONENT_INFORMATION, COMPONENT_METADATA})

COMP_METADATA_TYPE_PARAMETER: Final = 1


# --- the two messages pymavlink lacks ---------------------------------------------------------------
def _c_string(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("ascii", errors="replace")


class MAVLink_component_metadata_message(mavlink2.MAVLink_message):
    """COMPONENT_METADATA (397, common.xml): the MAVLink FTP URI and CRC32 of the general metadata file."""

    id = COMPONENT_METADATA
    msgname = "COMPONENT_METADATA"
    fieldnames = ["time_boot_ms", "file_crc", "uri"]  # noqa: RUF012 - pymavlink's class layout
    ordered_fieldnames = ["time_boot_ms", "file_crc", "uri"]  # noqa: RUF012
    fieldtypes = ["uint32_t", "uint32_t", "char"]  # noqa: RUF012
    fielddisplays_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldenums_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldunits_by_name: dict[str, str] = {"time_boot_ms": "ms"}  # noqa: RUF012
    native_format = bytearray(b"<IIc")
    orders = [0, 1, 2]  # noqa: RUF012
    lengths = [1, 1, 1]  # noqa: RUF012
    array_lengths = [0, 0, 100]  # noqa: RUF012
    crc_extra = 182
    unpacker = struct.Struct("<II100s")
    instance_field = None
    instance_offset = -1

    def __init__(self, time_boot_ms: int, file_crc: int, uri: bytes) -> None:
        super().__init__(COMPONENT_METADATA, "COMPONENT_METADATA")
        self._fieldnames = self.fieldnames
        self.time_boot_ms = time_boot_ms
        self.file_crc = file_crc
        self._uri_raw = uri
        self.uri = _c_string(uri)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.time_boot_ms, self.file_crc, self._uri_raw)
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


class MAVLink_component_information_message(mavlink2.MAVLink_message):
    """COMPONENT_INFORMATION (395, common.xml, deprecated for COMPONENT_METADATA): the same URI and CRC."""

    id = COMPONENT_INFORMATION
    msgname = "COMPONENT_INFORMATION"
    fieldnames = [  # noqa: RUF012 - pymavlink's class layout
        "time_boot_ms",
        "general_metadata_file_crc",
        "general_metadata_uri",
        "peripherals_metadata_file_crc",
        "peripherals_metadata_uri",
    ]
    ordered_fieldnames = [  # noqa: RUF012
        "time_boot_ms",
        "general_metadata_file_crc",
        "peripherals_metadata_file_crc",
        "general_metadata_uri",
        "peripherals_metadata_uri",
    ]
    fieldtypes = ["uint32_t", "uint32_t", "char", "uint32_t", "char"]  # noqa: RUF012
    fielddisplays_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldenums_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldunits_by_name: dict[str, str] = {"time_boot_ms": "ms"}  # noqa: RUF012
    native_format = bytearray(b"<IIIcc")
    orders = [0, 1, 3, 2, 4]  # noqa: RUF012
    lengths = [1, 1, 1, 1, 1]  # noqa: RUF012
    array_lengths = [0, 0, 100, 0, 100]  # noqa: RUF012
    crc_extra = 0
    unpacker = struct.Struct("<III100s100s")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        time_boot_ms: int,
        general_metadata_file_crc: int,
        general_metadata_uri: bytes,
        peripherals_metadata_file_crc: int = 0,
        peripherals_metadata_uri: bytes = b"",
    ) -> None:
        super().__init__(COMPONENT_INFORMATION, "COMPONENT_INFORMATION")
        self._fieldnames = self.fieldnames
        self.time_boot_ms = time_boot_ms
        self.general_metadata_file_crc = general_metadata_file_crc
        self.peripherals_metadata_file_crc = peripherals_metadata_file_crc
        self._general_raw = general_metadata_uri
        self._peripherals_raw = peripherals_metadata_uri
        self.general_metadata_uri = _c_string(general_metadata_uri)
        self.peripherals_metadata_uri = _c_string(peripherals_metadata_uri)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(
            self.time_boot_ms,
            self.general_metadata_file_crc,
            self.peripherals_metadata_file_crc,
            self._general_raw,
            self._peripherals_raw,
        )
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def register_messages(dialect: Any = mavlink2) -> None:
    """Teach a pymavlink dialect module COMPONENT_METADATA and COMPONENT_INFORMATION (if it lacks them).

    Idempotent; a dialect that defines them already keeps its own.  Done at import for the dialect of
    :mod:`arena_common.mavlink.link`, whose frame splitter would otherwise drop them in byte streams
    (unknown id) and never decode them on UDP (CRC not checkable).
    """
    for cls in (MAVLink_component_metadata_message, MAVLink_component_information_message):
        dialect.mavlink_map.setdefault(cls.id, cls)


register_messages()
