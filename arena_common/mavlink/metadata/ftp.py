"""MAVLink FTP (FILE_TRANSFER_PROTOCOL): opcodes, error codes, payload encode/decode, NAK errors.

https://mavlink.io/en/services/ftp.html"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from arena_common.mavlink.metadata._errors import MetadataError

# MAVLink FTP opcodes (MAV_FTP_OPCODE) and NAK error codes (MAV_FTP_ERR), https://mavlink.io/en/services/ftp.html
OP_NONE: Final = 0
OP_TERMINATE_SESSION: Final = 1
OP_RESET_SESSIONS: Final = 2
OP_OPEN_FILE_RO: Final = 4
OP_READ_FILE: Final = 5
OP_BURST_READ_FILE: Final = 15
OP_ACK: Final = 128
OP_NAK: Final = 129

OPCODE_NAMES: Final[Mapping[int, str]] = {
    0: "None",
    1: "TerminateSession",
    2: "ResetSessions",
    3: "ListDirectory",
    4: "OpenFileRO",
    5: "ReadFile",
    6: "CreateFile",
    7: "WriteFile",
    8: "RemoveFile",
    9: "CreateDirectory",
    10: "RemoveDirectory",
    11: "OpenFileWO",
    12: "TruncateFile",
    13: "Rename",
    14: "CalcFileCRC32",
    15: "BurstReadFile",
    128: "ACK",
    129: "NAK",
}

ERR_FAIL: Final = 1
ERR_FAIL_ERRNO: Final = 2
ERR_INVALID_SESSION: Final = 4
ERR_NO_SESSIONS_AVAILABLE: Final = 5
ERR_EOF: Final = 6
ERR_UNKNOWN_COMMAND: Final = 7
ERR_FILE_NOT_FOUND: Final = 10

ERROR_NAMES: Final[Mapping[int, str]] = {
    0: "None",
    1: "Fail",
    2: "FailErrno",
    3: "InvalidDataSize",
    4: "InvalidSession",
    5: "NoSessionsAvailable",
    6: "EOF",
    7: "UnknownCommand",
    8: "FileExists",
    9: "FileProtected",
    10: "FileNotFound",
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
