"""No input, however odd, stops the simulated autopilot (a fuzz-ish barrage over a real MAVLink link).

Every MAV_CMD of the common dialect (and ids nobody defined) goes out as COMMAND_LONG and COMMAND_INT
with NaN, ±inf, huge, zero and PX4-magic parameters; then setpoints, vision, parameters, mission items
and origins with the same values. Afterwards the vehicle must still stream heartbeats, answer a
command, and no handler may have raised (``input_errors``), nothing failed to pack (``output_errors``)
and the flight logic had no arithmetic failure (``internal_errors``).
"""

from __future__ import annotations

import fcntl
import math
import os
import socket
import sys
import termios

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from arena_common.mavlink import px4
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot, SimClock
from tests.unit.sim.test_sim_autopilot import ARENA, SYSID, Gcs, free_port

ODD = (math.nan, math.inf, -math.inf, 1e38, -1e38, 3.4e38, 0.0, 1.0, 2.0, -1.0, 21196.0, 1e9)
ODD_INT = (0, 1, -1, 2**31 - 1, -(2**31), 123456789)


def all_commands() -> list[int]:
    known = sorted(mavutil.mavlink.enums["MAV_CMD"])
    return [c for c in known if c < 65536] + [0, 1, 31000, 65535]


def test_no_command_or_message_stops_the_vehicle() -> None:
    port = free_port()
    clock = SimClock(speed=1.0)
    gcs = Gcs(f"udpin:127.0.0.1:{port}", clock)
    ap = SimAutopilot(f"udpout:127.0.0.1:{port}", SYSID, clock=clock, params=ARENA)
    gcs.ap = ap
    # The barrage is fast: room for it in both sockets (a full non-blocking socket drops datagrams).
    ap.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    gcs.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
    loop = AutopilotLoop([ap]).start()
    try:
        gcs.wait_for(lambda: gcs.heartbeat is not None, 2.0, "first heartbeat")
        gcs.mocap = True
        gcs.set_origin()
        gcs.run_for(0.3)
        mav = gcs.conn.mav
        sent = 0

        def flush() -> None:
            nonlocal sent
            sent += 1
            if sent % 200 == 0:
                gcs.run_for(0.05)  # let the vehicle read (it takes 500 messages per step)

        for command in all_commands():
            for v in ODD:
                mav.command_long_send(SYSID, 1, command, 0, v, v, v, v, v, v, v)
                flush()
            for frame in (0, 1, 3, 5, 6, 8, 99):
                for v, xy in zip(ODD, ODD_INT * 2, strict=False):
                    mav.command_int_send(SYSID, 1, frame, command, 0, 0, v, v, v, v, xy, xy, v)
                    flush()
        for frame in (0, 1, 4, 5, 6, 7, 8, 9, 11, 12, 20, 21, 255):
            for mask in (0, 0xFFFF, px4.TYPEMASK_POS_YAW, px4.TYPEMASK_VEL_YAWRATE, 512 | 0x1C0):
                for v in ODD:
                    mav.set_position_target_local_ned_send(
                        0, SYSID, 1, frame, mask, v, v, v, v, v, v, v, v, v, v, v
                    )
                    flush()
                for v, xy in zip(ODD, ODD_INT * 2, strict=False):
                    mav.set_position_target_global_int_send(
                        0, SYSID, 1, frame, mask, xy, xy, v, v, v, v, v, v, v, v, v
                    )
                    flush()
        for frame in (0, 1, 4, 8, 12, 20, 21, 255):
            for v in ODD:
                mav.odometry_send(
                    0, frame, frame, v, v, v, [v, v, v, v], v, v, v, v, v, v, [v] * 21, [v] * 21, 255, 2, -1
                )
                mav.odometry_send(
                    2**63, frame, 12, v, v, v, [1.0, 0, 0, 0], v, v, v, v, v, v, [v] * 21, [v] * 21, 7, 2, 0
                )
                mav.vision_position_estimate_send(0, v, v, v, v, v, v, [v] * 21, 255)
                mav.att_pos_mocap_send(0, [v, v, v, v], v, v, v, [v] * 21)
                flush()
        for name in ap.params.names:
            if name == "MAV_SYS_ID":
                continue  # a different system id would make the vehicle deaf to this test (as PX4)
            for v in ODD:
                mav.param_set_send(SYSID, 1, name.encode(), v, ap.params.type_of(name))
                flush()
            mav.param_set_send(SYSID, 1, name.encode(), 1.0, 99)  # a type PX4 does not have
        for index in ODD_INT:
            mav.param_request_read_send(SYSID, 1, b"", max(-32768, min(32767, index)))
            mav.param_request_read_send(SYSID, 1, b"\xff\xfe", -1)
        for count in (0, 1, 65535, 5):
            mav.mission_count_send(SYSID, 1, count, 0)
            for seq in (0, 1, 65535):
                for v, xy in zip(ODD, ODD_INT * 2, strict=False):
                    mav.mission_item_int_send(SYSID, 1, seq, 6, 16, 0, 1, v, v, v, v, xy, xy, v, 0)
                    flush()
            mav.mission_request_int_send(SYSID, 1, 65535, 0)
            mav.mission_set_current_send(SYSID, 1, 65535)
        for xy in ODD_INT:
            mav.set_gps_global_origin_send(SYSID, xy, xy, xy, 2**63)
            mav.timesync_send(-(2**62), 2**62)
            mav.timesync_send(2**62, -(2**62))
            mav.heartbeat_send(255, 255, 255, 2**32 - 1, 255)
            flush()
        # Still there: heartbeats flow, commands are answered, nothing raised inside.
        beats = gcs.heartbeats
        gcs.wait_for(lambda: gcs.heartbeats >= beats + 2, 5.0, "heartbeats after the barrage")

        # On a busy machine the vehicle may still be reading the barrage (or rebooting, as one of its
        # commands asked): the command is sent once nothing waits in the vehicle's socket.
        def read_all() -> bool:
            waiting = fcntl.ioctl(ap.conn.port.fileno(), termios.FIONREAD, b"\0\0\0\0")
            return int.from_bytes(waiting, sys.byteorder) == 0 and not ap.rebooting

        gcs.wait_for(read_all, 60.0, "the vehicle to have read the barrage")
        if ap.system_id == SYSID:
            assert gcs.command(px4.MAV_CMD_REQUEST_MESSAGE, 148) == px4.MAV_RESULT_ACCEPTED
        assert loop.alive
        assert ap.messages_in > 5_000  # (what arrived during a reboot it asked for was not read, as PX4)
        assert ap.boots >= 2  # PREFLIGHT_REBOOT_SHUTDOWN 1 rebooted it, and it came back
        assert not ap.input_errors, ap.input_errors
        assert not ap.output_errors, ap.output_errors
        assert not ap.internal_errors, ap.internal_errors
    finally:
        loop.stop()
        ap.close()
        gcs.close()
