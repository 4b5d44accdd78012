"""MAVLink FTP (FILE_TRANSFER_PROTOCOL): opcodes, error codes, payload encode/decode, NAK errors.

https://mavlink.io/en/services/ftp.html"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from arena_common.mavlink.link import mavlink2
from arena_common.mavlink.metadata._errors import MetadataError

# MAVLink FTP opcodes (MAV_FTP_OPCODE) and NAK error codes (MAV_FTP_ERR), https://mavlink.io/en/services/ftp.html
OP_NONE: Final = mavlink2.MAV_FTP_OPCODE_NONE
OP_TERMINATE_SESSION: Final = mavlink2.MAV_FTP_OPCODE_TERMINATESESSION
OP_RESET_SESSIONS: Final = mavlink2.MAV_FTP_OPCODE_RESETSESSION
OP_OPEN_FILE_RO: Final = mavlink2.MAV_FTP_OPCODE_OPENFILERO
OP_READ_FILE: Final = mavlink2.MAV_FTP_OPCODE_READFILE
OP_BURST_READ_FILE: Final = mavlink2.MAV_FTP_OPCODE_BURSTREADFILE
OP_ACK: Final = mavlink2.MAV_FTP_OPCODE_ACK
OP_NAK: Final = mavlink2.MAV_FTP_OPCODE_NAK

#: The opcodes' names as the FTP specification spells them.
OPCODE_NAMES: Final[Mapping[int, str]] = {
    mavlink2.MAV_FTP_OPCODE_NONE: "None",
    mavlink2.MAV_FTP_OPCODE_TERMINATESESSION: "TerminateSession",
    mavlink2.MAV_FTP_OPCODE_RESETSESSION: "ResetSessions",
    mavlink2.MAV_FTP_OPCODE_LISTDIRECTORY: "ListDirectory",
    mavlink2.MAV_FTP_OPCODE_OPENFILERO: "OpenFileRO",
    mavlink2.MAV_FTP_OPCODE_READFILE: "ReadFile",
    mavlink2.MAV_FTP_OPCODE_CREATEFILE: "CreateFile",
    mavlink2.MAV_FTP_OPCODE_WRITEFILE: "WriteFile",
    mavlink2.MAV_FTP_OPCODE_REMOVEFILE: "RemoveFile",
    mavlink2.MAV_FTP_OPCODE_CREATEDIRECTORY: "CreateDirectory",
    mavlink2.MAV_FTP_OPCODE_REMOVEDIRECTORY: "RemoveDirectory",
    mavlink2.MAV_FTP_OPCODE_OPENFILEWO: "OpenFileWO",
    mavlink2.MAV_FTP_OPCODE_TRUNCATEFILE: "TruncateFile",
    mavlink2.MAV_FTP_OPCODE_RENAME: "Rename",
    mavlink2.MAV_FTP_OPCODE_CALCFILECRC: "CalcFileCRC32",
    mavlink2.MAV_FTP_OPCODE_BURSTREADFILE: "BurstReadFile",
    mavlink2.MAV_FTP_OPCODE_ACK: "ACK",
    mavlink2.MAV_FTP_OPCODE_NAK: "NAK",
}

ERR_FAIL: Final = mavlink2.MAV_FTP_ERR_FAIL
ERR_FAIL_ERRNO: Final = mavlink2.MAV_FTP_ERR_FAILERRNO
ERR_INVALID_SESSION: Final = mavlink2.MAV_FTP_ERR_INVALIDSESSION
ERR_NO_SESSIONS_AVAILABLE: Final = mavlink2.MAV_FTP_ERR_NOSESSIONSAVAILABLE
ERR_EOF: Final = mavlink2.MAV_FTP_ERR_EOF
ERR_UNKNOWN_COMMAND: Final = mavlink2.MAV_FTP_ERR_UNKNOWNCOMMAND
ERR_FILE_NOT_FOUND: Final = mavlink2.MAV_FTP_ERR_FILENOTFOUND

#: The NAK error codes' names as the FTP specification spells them.
ERROR_NAMES: Final[Mapping[int, str]] = {
    mavlink2.MAV_FTP_ERR_NONE: "None",
    mavlink2.MAV_FTP_ERR_FAIL: "Fail",
    mavlink2.MAV_FTP_ERR_FAILERRNO: "FailErrno",
    mavlink2.MAV_FTP_ERR_INVALIDDATASIZE: "InvalidDataSize",
    mavlink2.MAV_FTP_ERR_INVALIDSESSION: "InvalidSession",
    mavlink2.MAV_FTP_ERR_NOSESSIONSAVAILABLE: "NoSessionsAvailable",
    mavlink2.MAV_FTP_ERR_EOF: "EOF",
    mavlink2.MAV_FTP_ERR_UNKNOWNCOMMAND: "UnknownCommand",
    mavlink2.MAV_FTP_ERR_FILEEXISTS: "FileExists",
    mavlink2.MAV_FTP_ERR_FILEPROTECTED: "FileProtected",
    mavlink2.MAV_FTP_ERR_FILENOTFOUND: "FileNotFound",
}

FTP_PAYLOAD_LEN: Final = 251
FTP_HEADER_LEN: Final = 12
#: Data bytes one FTP message carries (PX4 always reads this much per ReadFile / burst packet).
FTP_DATA_MAX: Final = FTP_PAYLOAD_LEN - FTP_HEADER_LEN
_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
_XZ_MAGIC = b"\xfd7zXZ\x00"


class FtpError(MetadataError):
    """A MAVLink FTP transfer failed (a protocol violation, a file too large or changing under us)."""


class FtpNak(FtpError):
    """The vehicle's FTP server refused a request.

    ``op`` / ``op_name`` the request, ``code`` / ``code_name`` its MAV_FTP_ERR, ``errno`` the server's
    errno (FailErrno only), ``path`` the file.
    """

    def __init__(self, op: int, code: int, errno: int | None, path: str, target: str) -> None:
        self.op = op
        self.op_name = OPCODE_NAMES.get(op, f"opcode {op}")
        self.code = code
        self.code_name = ERROR_NAMES.get(code, f"error {code}")
        self.errno = errno
        self.path = path
        detail = self.code_name + (f" (errno {errno}: {os.strerror(errno)})" if errno is not None else "")
        super().__init__(f"MAVLink FTP {self.op_name} {path!r} refused by {target}: NAK {detail}")


# --- FTP payloads -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class FtpReply:
    """One decoded FILE_TRANSFER_PROTOCOL payload (a reply, or a request in a test's responder)."""

    seq: int
    session: int
    opcode: int
    size: int
    req_opcode: int
    burst_complete: bool
    offset: int
    data: bytes

    @property
    def nak(self) -> bool:
        return self.opcode == OP_NAK

    @property
    def error(self) -> int:
        """The NAK's MAV_FTP_ERR (Fail when the NAK carries none)."""
        return self.data[0] if self.data else ERR_FAIL

    @property
    def errno(self) -> int | None:
        """The server's errno for a FailErrno NAK, else None."""
        return self.data[1] if self.error == ERR_FAIL_ERRNO and len(self.data) >= 2 else None


def decode_ftp_payload(payload: bytes | bytearray | list[int]) -> FtpReply:
    """Split a FILE_TRANSFER_PROTOCOL payload into its header fields and ``size`` data bytes."""
    raw = bytes(payload)
    if len(raw) < FTP_HEADER_LEN:
        raise FtpError(f"MAVLink FTP payload of {len(raw)} bytes, less than a {FTP_HEADER_LEN}-byte header")
    seq, session, opcode, size, req_opcode, burst_complete, _pad, offset = _HEADER.unpack_from(raw)
    size = min(size, FTP_DATA_MAX)
    data = raw[FTP_HEADER_LEN : FTP_HEADER_LEN + size].ljust(size, b"\x00")  # MAVLink 2 cuts trailing zeros
    return FtpReply(seq, session, opcode, size, req_opcode, bool(burst_complete), offset, data)


def encode_ftp_payload(
    seq: int,
    opcode: int,
    *,
    session: int = 0,
    offset: int = 0,
    data: bytes = b"",
    size: int | None = None,
    req_opcode: int = 0,
    burst_complete: bool = False,
) -> list[int]:
    """A 251-byte FILE_TRANSFER_PROTOCOL payload (``size`` defaults to ``len(data)``)."""
    if len(data) > FTP_DATA_MAX:
        raise FtpError(f"MAVLink FTP data of {len(data)} bytes exceeds {FTP_DATA_MAX}")
    n = len(data) if size is None else size
    head = _HEADER.pack(seq & 0xFFFF, session, opcode, n, req_opcode, int(burst_complete), 0, offset)
    return list((head + data).ljust(FTP_PAYLOAD_LEN, b"\x00"))
