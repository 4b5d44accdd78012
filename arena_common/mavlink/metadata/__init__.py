"""PX4's own parameter metadata: from the vehicle (component metadata + MAVLink FTP) or a build's file.

Which parameters need a reboot (``rebootRequired``), their types, defaults and units are PX4's facts, not
ours: this module reads them where PX4 publishes them, never from a hand-kept list.

From the vehicle (:class:`MetadataClient`):

1. ``MAV_CMD_REQUEST_MESSAGE`` (512) for COMPONENT_METADATA (397), alternating with the older
   COMPONENT_INFORMATION (395), without waiting for COMMAND_ACK (the gateway's commander takes those);
   PX4 v1.16 answers both with the MAVLink FTP URI of its general metadata file,
   ``mftp://etc/extras/component_general.json.xz`` (a CRC32 of the *uncompressed* file beside it).
2. That file (xz-compressed JSON) lists the metadata types; type 1 (COMP_METADATA_TYPE_PARAMETER) is
   ``mftp://etc/extras/parameters.json.xz`` (PX4 v1.16 SITL: 68,036 bytes, 721,427 uncompressed; its
   ``fileCrc`` is the CRC32 of the *compressed* file).
3. Both files are read with MAVLink FTP (FILE_TRANSFER_PROTOCOL, 110): OpenFileRO, BurstReadFile (PX4
   streams 239-byte chunks, about 35 kB per burst, then sets ``burst_complete``; a NAK EOF ends the file),
   ReadFile for the holes a lossy link leaves (its ``size`` field says how much: PX4 v1.16 reads exactly
   that), TerminateSession.  Replies are matched by sequence number (reply = request + 1; a burst's
   packets continue from there), requests are resent with the same sequence number (PX4 then repeats
   its cached reply), stale, duplicated and out-of-order packets are dropped or placed by their offset.
   PX4 serves one FTP session per MAVLink link.  Against PX4 v1.16 SITL the whole fetch takes ~0.15 s.

The gateway's reader thread owns the link: it hands FILE_TRANSFER_PROTOCOL, COMPONENT_METADATA and
COMPONENT_INFORMATION (:data:`HANDLED_MESSAGES`) to :meth:`MetadataClient.on_message`, while another
thread blocks in :meth:`MetadataClient.fetch` (the pattern of
:class:`~arena_common.mavlink.protocols.ParamClient`).  :func:`fetch_parameter_metadata` runs its own
reader on a :class:`~arena_common.mavlink.link.MavlinkLink` nobody else reads.

From a file (:func:`load_parameters_json`): the build's ``parameters.json`` (or ``.json.xz``).

Both give ``{name: {"type", "rebootRequired", "default", "units"}}``; :func:`reboot_required` picks the
names that need a reboot.

pymavlink (2.4.x) knows neither COMPONENT_METADATA nor COMPONENT_INFORMATION: importing this module adds
both to the MAVLink 2 dialect :mod:`arena_common.mavlink.link` uses (:func:`register_messages`), so
their CRCs are checked and :meth:`~arena_common.mavlink.link.MavlinkLink.decode` returns them.

Modules: :mod:`.messages` (ids, the two messages), :mod:`.ftp` (MAVLink FTP payloads), :mod:`.parameters`
(the files), :mod:`.client` (the fetch).
"""

from __future__ import annotations

from arena_common.mavlink.metadata._errors import MetadataError, MetadataFormatError, MetadataTimeout
from arena_common.mavlink.metadata.client import FetchInfo, MetadataClient, fetch_parameter_metadata
from arena_common.mavlink.metadata.ftp import (
    ERR_EOF,
    ERR_FAIL,
    ERR_FAIL_ERRNO,
    ERR_FILE_NOT_FOUND,
    ERR_INVALID_SESSION,
    ERR_NO_SESSIONS_AVAILABLE,
    ERR_UNKNOWN_COMMAND,
    ERROR_NAMES,
    FTP_DATA_MAX,
    FTP_HEADER_LEN,
    FTP_PAYLOAD_LEN,
    OP_ACK,
    OP_BURST_READ_FILE,
    OP_NAK,
    OP_NONE,
    OP_OPEN_FILE_RO,
    OP_READ_FILE,
    OP_RESET_SESSIONS,
    OP_TERMINATE_SESSION,
    OPCODE_NAMES,
    FtpError,
    FtpNak,
    FtpReply,
    decode_ftp_payload,
    encode_ftp_payload,
)
from arena_common.mavlink.metadata.messages import (
    COMP_METADATA_TYPE_PARAMETER,
    COMPONENT_INFORMATION,
    COMPONENT_METADATA,
    FILE_TRANSFER_PROTOCOL,
    HANDLED_MESSAGES,
    MAV_CMD_REQUEST_MESSAGE,
    MAVLink_component_information_message,
    MAVLink_component_metadata_message,
    register_messages,
)
from arena_common.mavlink.metadata.parameters import (
    MetadataType,
    ParamMeta,
    load_parameters_json,
    parse_general_metadata,
    parse_mftp_uri,
    parse_parameters_json,
    px4_crc32,
    reboot_required,
)

__all__ = [
    "COMPONENT_INFORMATION",
    "COMPONENT_METADATA",
    "COMP_METADATA_TYPE_PARAMETER",
    "ERROR_NAMES",
    "ERR_EOF",
    "ERR_FAIL",
    "ERR_FAIL_ERRNO",
    "ERR_FILE_NOT_FOUND",
    "ERR_INVALID_SESSION",
    "ERR_NO_SESSIONS_AVAILABLE",
    "ERR_UNKNOWN_COMMAND",
    "FILE_TRANSFER_PROTOCOL",
    "FTP_DATA_MAX",
    "FTP_HEADER_LEN",
    "FTP_PAYLOAD_LEN",
    "HANDLED_MESSAGES",
    "MAV_CMD_REQUEST_MESSAGE",
    "OPCODE_NAMES",
    "OP_ACK",
    "OP_BURST_READ_FILE",
    "OP_NAK",
    "OP_NONE",
    "OP_OPEN_FILE_RO",
    "OP_READ_FILE",
    "OP_RESET_SESSIONS",
    "OP_TERMINATE_SESSION",
    "FetchInfo",
    "FtpError",
    "FtpNak",
    "FtpReply",
    "MAVLink_component_information_message",
    "MAVLink_component_metadata_message",
    "MetadataClient",
    "MetadataError",
    "MetadataFormatError",
    "MetadataTimeout",
    "MetadataType",
    "ParamMeta",
    "decode_ftp_payload",
    "encode_ftp_payload",
    "fetch_parameter_metadata",
    "load_parameters_json",
    "parse_general_metadata",
    "parse_mftp_uri",
    "parse_parameters_json",
    "px4_crc32",
    "reboot_required",
    "register_messages",
]
