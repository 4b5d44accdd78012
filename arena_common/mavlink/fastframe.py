"""MAVLink 2 frames packed straight from values: the vision hot path without pymavlink's message objects.

pymavlink builds a message object per frame (its fields, a header object, a CRC object, then the bytes).
At hundreds of poses a second that churn is most of what the gateway's own Python costs per pose; here a
frame is one ``struct`` pack of the payload, the header and the CRC (``fastcrc``, the C implementation
pymavlink itself uses when it is installed).  The output is byte-identical to pymavlink's (tested), for
unsigned links; a signed link goes through pymavlink.
"""

from __future__ import annotations

import struct
from typing import Any

from pymavlink.dialects.v20 import all as mavlink2

try:
    from fastcrc import crc16 as _crc16

    def _crc(data: bytes, extra: int) -> int:
        return int(_crc16.mcrf4xx(bytes((extra,)), _crc16.mcrf4xx(data, 0xFFFF)))

except ImportError:  # pragma: no cover - fastcrc comes with the project's dependencies
    from pymavlink.generator.mavcrc import x25crc

    def _crc(data: bytes, extra: int) -> int:
        c = x25crc(data)
        c.accumulate(bytes((extra,)))
        return int(c.crc)


__all__ = ["ODOMETRY", "FrameType", "odometry_payload"]

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")


class FrameType:
    """One MAVLink 2 message type: its id, CRC extra and payload layout (wire order)."""

    def __init__(self, cls: Any) -> None:
        self.name = str(cls.msgname)
        self.msgid = int(cls.id)
        self.crc_extra = int(cls.crc_extra)
        self.payload = struct.Struct(cls.unpacker.format)

    def frame(self, payload: bytes, seq: int, system: int, component: int) -> bytes:
        """The whole unsigned frame around ``payload`` (trailing zero bytes trimmed, as MAVLink 2 does)."""
        body = payload.rstrip(b"\0") or payload[:1]
        head = _HEADER.pack(
            0xFD, len(body), 0, 0, seq, system, component, self.msgid & 0xFFFF, self.msgid >> 16
        )
        data = head + body
        return data + _CRC.pack(_crc(data[1:], self.crc_extra))


ODOMETRY = FrameType(mavlink2.MAVLink_odometry_message)


def odometry_payload(args: dict[str, Any]) -> bytes:
    """ODOMETRY's payload from :func:`~arena_common.mavlink.px4.odometry_args`.

    Raises ``struct.error`` for a value beyond its field's type, as pymavlink does.
    """
    q = args["q"]
    return ODOMETRY.payload.pack(
        args["time_usec"],
        args["x"],
        args["y"],
        args["z"],
        q[0],
        q[1],
        q[2],
        q[3],
        args["vx"],
        args["vy"],
        args["vz"],
        args["rollspeed"],
        args["pitchspeed"],
        args["yawspeed"],
        *args["pose_covariance"],
        *args["velocity_covariance"],
        args["frame_id"],
        args["child_frame_id"],
        args["reset_counter"],
        args["estimator_type"],
        args["quality"],
    )
