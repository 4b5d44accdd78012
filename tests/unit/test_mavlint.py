"""MAVLink numbers live in arena_common/mavlink/px4.py alone (tools/mavlint.py): px4.py's equal pymavlink's,
the tree has no literal elsewhere, and the lint flags each kind of literal the tree once had (the snippets
are those literals as they stood) and passes the numbers that are no MAVLink number."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from tools import mavlint


def test_px4_is_the_one_home_of_the_mavlink_numbers() -> None:
    names = [n for n in dir(px4) if n.startswith(("MAV_", "MAVLINK_MSG_ID_", "ESTIMATOR_"))]
    newer = {"MAV_RESULT_CANCELLED"}  # MAVLink's common.xml has it (6); this pymavlink does not yet
    assert len(names) > 100
    for name in names:
        if name not in newer:
            assert getattr(px4, name) == getattr(mavlink2, name), name
    found = mavlint.check_tree()
    assert not found, "\n".join(map(str, found))


def flagged(source: str) -> list[mavlint.Finding]:
    return mavlint.check_source(textwrap.dedent(source))


# (what, snippet, the lines flagged, a word of each finding)
FLAGGED = [
    (
        "names given a MAVLink number (gateway, sim, signing, metadata, services, bench, tools)",
        """
        MAV_TYPE_GCS = 6
        MAV_AUTOPILOT_INVALID = 8
        MSG_ESTIMATOR_STATUS = 230
        _MSG_GPS_GLOBAL_ORIGIN = 49
        RADIO_STATUS, ADSB_VEHICLE, COLLISION = 109, 246, 247
        FILE_TRANSFER_PROTOCOL: Final = 110
        OP_READ_FILE: Final = 5
        ERR_EOF: Final = 6
        MAV_MISSION_ACCEPTED: Final = 0
        _NAV_WAYPOINT, _LOITER_UNLIM = 16, 17
        _DO_CHANGE_SPEED: Final = 178
        _POS_HORIZ_REL = 8
        CMD_SET_MESSAGE_INTERVAL = 511
        ODOMETRY_ID = 331
        MAVLINK_TIMESYNC = 1
        """,
        [2, 3, 4, 5, 6, 6, 6, 7, 8, 9, 10, 11, 11, 12, 13, 14, 15, 16],
        "MAVLink number",
    ),
    (
        "a message built with numbers in its enum fields, by position and by name",
        """
        mav.heartbeat_encode(6, 8, 0, 0, 4)
        link.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        mav.extended_sys_state_send(0, landed)
        mav.highres_imu_send(t, ax, ay, az, gx, gy, gz, mx, my, mz, p, dp, alt, temp, 0x1FFF)
        mav.battery_status_send(0, 1, 1, 0x7FFF, cells, amps, mah, joules, soc, 0, (1, 2, 3, 4)[level])
        mav.odometry_encode(frame_id=1, child_frame_id=12, estimator_type=2)
        mav.mission_request_int_send(sys, comp, seq, 0)
        mavlink2.MAVLink_command_ack_message(400, 0)
        """,
        [2, 2, 2, 3, 4, 5, 6, 6, 6, 6, 6, 6, 7, 7, 7, 8, 9, 9],
        " as ",
    ),
    (
        "fields and message ids read against numbers",
        """
        if msg.autopilot == 8:
            pass
        if hb.base_mode & 128 and msg.severity <= 4 and ack.result in (0, 5):
            pass
        if m.get_msgid() == 230 or msg.get_msgId() == 73 or mid == 245 or msgid == 0:
            pass
        frame = int(msg.frame)
        if frame == 11:
            pass
        self._cmd_frame = frame
        relative = self._cmd_frame in (3, 6)
        mtype = int(getattr(msg, "mission_type", 0))
        if mtype in (0, 255) or int(getattr(msg, "mission_type", 0)) != 0:
            pass
        match msg.command:
            case 400:
                pass
        def ack(target, result, mission_type: int = 0):
            pass
        flag = FLAGS.get(int(getattr(msg, "charge_state", 0)), "")
        """,
        [2, 4, 4, 4, 4, 6, 6, 6, 6, 9, 12, 12, 13, 14, 14, 14, 14, 17, 19, 21],
        "",
    ),
    (
        "tables of numbers read with a field or filling an enum field",
        """
        _BATTERY_FLAGS = {2: "battery_low", 3: "battery_critical"}
        STREAMS = {0: ("HEARTBEAT", 1.0), 245: ("EXTENDED_SYS_STATE", 5.0)}
        REQUESTABLE = frozenset({*STREAMS, 148, 49})
        _GLOBAL_FRAMES = frozenset({0, 3, 5, 6})
        CAPABILITIES = 4 | 8 | 8192
        _SENSORS = 0x01 | 0x80
        class A:
            def on(self, msg, item):
                handlers = self._handlers
                handler = handlers.get(msg.get_msgId())
                if item.frame in _GLOBAL_FRAMES and msgid not in REQUESTABLE and msgid not in STREAMS:
                    flag = _BATTERY_FLAGS.get(msg.charge_state)
                health = _SENSORS
                if bad:
                    health &= ~0x10000000
                if done:
                    state = 5
                else:
                    state = 2 if current == 0 else 4
                mav.sys_status_send(_SENSORS, _SENSORS, health, 250, 0, 0, 0, 0, 0, 0, 0, 0, 0)
                mav.mission_current_send(seq, total, state, 1)
                mav.autopilot_version_send(CAPABILITIES, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 1)
        A._handlers = {0: A.on, 76: A.on}
        """,
        [2, 2, 3, 3, 4, 4, 5, 5, 5, 5, 6, 6, 6, 7, 7, 16, 18, 20, 20, 24, 24],
        " in ",
    ),
    (
        "message ids asked for, numbers beside MAVLink names, component ids, tables of MAVLink names",
        """
        self._request_message(49)
        _FLOAT_TYPES = (px4.MAV_PARAM_TYPE_REAL32, 10, 11)
        conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=191)
        system, component = spec.system_id, 191
        OPCODE_NAMES = {0: "None", 1: "TerminateSession", 4: "OpenFileRO", 5: "ReadFile"}
        """,
        [2, 3, 3, 4, 5, 6, 7, 7, 7, 7],
        "",
    ),
]


@pytest.mark.parametrize(("what", "source", "lines", "word"), FLAGGED, ids=[f[0] for f in FLAGGED])
def test_each_kind_of_mavlink_literal_is_flagged(what: str, source: str, lines: list[int], word: str) -> None:
    found = flagged(source)
    assert sorted(f.line for f in found) == lines, "\n".join(map(str, found))
    assert all(word in f.what for f in found), "\n".join(map(str, found))


def test_numbers_that_are_no_mavlink_number_pass() -> None:
    source = """
    from arena_common.mavlink import px4
    link.mav.heartbeat_encode(px4.MAV_TYPE_GCS, px4.MAV_AUTOPILOT_INVALID, 0, 0, px4.MAV_STATE_ACTIVE)
    link.mav.command_long_encode(target, 1, px4.MAV_CMD_REQUEST_MESSAGE, 0, MSG["GPS_GLOBAL_ORIGIN"], 0, 0, 0)
    mav.timesync_send(0, ts)  # no enum field: 0 and any number pass
    mav.statustext_send(severity, text[:50], 7, 0)
    if msgid < 0:  # pymavlink's bad data
        pass
    ls = int(msg.landed_state)
    landed = _LANDED[ls] if 0 <= ls < len(_LANDED) else "undefined"
    head = pack(0xFD, len(body), 0, 0, seq, system, component, self.msgid & 0xFFFF, self.msgid >> 16)
    n = length({1: ">B", 2: ">H", 4: ">I"}[size], size)
    SYSTEM_DEFAULT = 0  # rclpy's QoS, not MAVLink's
    KEEP_ALL = 2
    NAV_OFFBOARD = 14  # PX4's uORB nav_state
    TIMESYNC_SOURCE_MAVLINK = 1
    if frame_number == 5 or msg_type == 7 or result == "ACCEPTED" or sev <= 4:
        pass
    _DLL_ACTIONS = {1: "hold", 2: "rtl", 3: "land", 5: "terminate", 6: "disarm"}  # a PX4 parameter's values
    system, component = 245, 1
    mav.mission_item_int_send(s, c, seq, item.frame, item.command, 0, 1, *item.params, x, y, z, 0)
    """
    assert flagged(source) == []


FILES = {
    "arena_common/mavlink/px4.py": "MAV_TYPE_GCS = 6\n",  # the home: never flagged
    "arena_common/gateway/gw.py": "import x\nMAV_TYPE_GCS = 6\n",
    "services/svc.py": "if msg.command == 400:\n    pass\n",
    "tests/test_x.py": "MAV_TYPE_GCS = 6\n",  # out of scope
}


def test_the_command_lists_each_literal_as_file_line_what_and_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for rel, text in FILES.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    with pytest.raises(SystemExit) as exc:
        mavlint.main([str(tmp_path)])
    assert exc.value.code == 1
    out = capsys.readouterr().out.splitlines()
    assert out == [
        "arena_common/gateway/gw.py:2: MAVLink number MAV_TYPE_GCS = 6: name it in "
        "arena_common/mavlink/px4.py or take pymavlink's",
        "services/svc.py:1: 400 compared with .command",
    ]
    (tmp_path / "arena_common/gateway/gw.py").write_text(
        "from arena_common.mavlink import px4\nT = px4.MAV_TYPE_GCS\n"
    )
    (tmp_path / "services/svc.py").write_text("if msg.command == px4.MAV_CMD_NAV_LAND:\n    pass\n")
    mavlint.main([str(tmp_path)])
    assert "no MAVLink literal" in capsys.readouterr().out
