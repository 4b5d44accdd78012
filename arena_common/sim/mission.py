"""The MAVLink mission protocol of the simulated PX4, and what AUTO.MISSION flies.

Upload (MISSION_COUNT → MISSION_REQUEST_INT for each item → MISSION_ITEM_INT → MISSION_ACK), download
(MISSION_REQUEST_LIST → MISSION_COUNT, MISSION_REQUEST_INT/MISSION_REQUEST → MISSION_ITEM_INT),
MISSION_CLEAR_ALL, MISSION_SET_CURRENT, MISSION_CURRENT and MISSION_ITEM_REACHED, for the mission type
only (geofence and rally points are answered MAV_MISSION_UNSUPPORTED unless cleared).

Flown items: NAV_WAYPOINT (hold time param1, acceptance radius param2, else NAV_ACC_RAD), NAV_LOITER_UNLIM,
NAV_LOITER_TIME, NAV_TAKEOFF, NAV_LAND, NAV_RETURN_TO_LAUNCH and DO_CHANGE_SPEED, in the global frames
(absolute or relative to home altitude) projected around the EKF origin; other DO_/CONDITION_ items are
passed over. After the last item the vehicle holds there (MISSION_CURRENT says COMPLETE).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from arena_common.sim.base import AutopilotState, Vec3, as_int, finite
from arena_common.sim.physics import Setpoint

__all__ = ["MissionItem", "MissionMixin"]

NAN = math.nan

MAX_ITEMS: Final = 500
_RELATIVE_FRAMES: Final = frozenset(
    {mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
)
_GLOBAL_FRAMES: Final = _RELATIVE_FRAMES | {mavlink2.MAV_FRAME_GLOBAL, mavlink2.MAV_FRAME_GLOBAL_INT}
_NAV_WAYPOINT: Final = mavlink2.MAV_CMD_NAV_WAYPOINT
_LOITER_UNLIM: Final = mavlink2.MAV_CMD_NAV_LOITER_UNLIM
_LOITER_TIME: Final = mavlink2.MAV_CMD_NAV_LOITER_TIME
_RTL: Final = px4.MAV_CMD_NAV_RETURN_TO_LAUNCH
_LAND: Final = px4.MAV_CMD_NAV_LAND
_TAKEOFF: Final = px4.MAV_CMD_NAV_TAKEOFF
_NAV_ITEMS: Final = frozenset({_NAV_WAYPOINT, _LOITER_UNLIM, _LOITER_TIME, _RTL, _LAND, _TAKEOFF})
_DO_CHANGE_SPEED: Final = px4.MAV_CMD_DO_CHANGE_SPEED
_MISSION: Final = mavlink2.MAV_MISSION_TYPE_MISSION  # the one mission type flown (no fence, no rally)
UPLOAD_RETRY_S: Final = 0.5
UPLOAD_RETRIES: Final = 5


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One stored mission item (MISSION_ITEM_INT fields; ``lat``/``lon`` in degrees)."""

    seq: int
    frame: int
    command: int
    autocontinue: int
    params: tuple[float, float, float, float]
    lat: float
    lon: float
    alt: float

    def wire_xy(self) -> tuple[int, int]:
        """``x``, ``y`` as MISSION_ITEM_INT carries them (1e7 degrees in global frames)."""
        if self.frame in _GLOBAL_FRAMES and finite(self.lat) and finite(self.lon):
            return round(self.lat * 1e7), round(self.lon * 1e7)
        x = self.lat if finite(self.lat) else 0.0
        y = self.lon if finite(self.lon) else 0.0
        return int(max(-(2**31), min(2**31 - 1, round(x)))), int(max(-(2**31), min(2**31 - 1, round(y))))


class MissionMixin(AutopilotState):
    """Mission storage, protocol and flight of :class:`~arena_common.sim.autopilot.SimAutopilot`."""

    _upload: dict[str, Any] | None

    def _mission_boot(self, keep: bool) -> None:
        """Boot: PX4 keeps its mission in the dataman (a file), so a reboot keeps it too."""
        if not keep:
            self._mission = []
        self._mission_current = 0
        self._mission_done = False
        self._upload = None

    # ------------------------------------------------------------------ protocol

    def _mission_ack(self, target: tuple[int, int], result: int, mission_type: int = _MISSION) -> None:
        self.conn.mav.mission_ack_send(target[0], target[1], result, mission_type)

    def _on_mission_count(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        mtype = int(getattr(msg, "mission_type", _MISSION))
        count = int(msg.count)
        if mtype != _MISSION:
            self._mission_ack(
                src, mavlink2.MAV_MISSION_ACCEPTED if count == 0 else mavlink2.MAV_MISSION_UNSUPPORTED, mtype
            )
            return
        if count == 0:
            self._mission_clear()
            self._mission_ack(src, mavlink2.MAV_MISSION_ACCEPTED)
            return
        if count > MAX_ITEMS:
            self._mission_ack(src, mavlink2.MAV_MISSION_NO_SPACE)
            return
        self._upload = {"src": src, "items": [], "count": count, "next_at": t, "tries": 0}
        self._request_next_item(t)

    def _request_next_item(self, t: float) -> None:
        up = self._upload
        if up is None:
            return
        seq = len(up["items"])
        self.conn.mav.mission_request_int_send(up["src"][0], up["src"][1], seq, _MISSION)
        up["next_at"] = t + UPLOAD_RETRY_S
        up["tries"] += 1

    def _mission_tick(self, t: float) -> None:
        """Resend an unanswered item request; give up after :data:`UPLOAD_RETRIES`."""
        up = self._upload
        if up is None or t < up["next_at"]:
            return
        if up["tries"] >= UPLOAD_RETRIES:
            self._mission_ack(up["src"], mavlink2.MAV_MISSION_ERROR)
            self._upload = None
            return
        self._request_next_item(t)

    def _on_mission_item(self, msg: Any, t: float) -> None:
        """MISSION_ITEM_INT (73) or the float MISSION_ITEM (39) of an upload in progress."""
        up = self._upload
        if up is None or not self._addressed(msg.target_system, msg.target_component, False):
            return
        if int(getattr(msg, "mission_type", _MISSION)) != _MISSION:
            return
        seq = int(msg.seq)
        expected = len(up["items"])
        if seq != expected:
            if seq < expected:
                return  # a repeat of one already stored
            self._request_next_item(t)
            return
        frame = int(msg.frame)
        x, y = float(msg.x), float(msg.y)
        if msg.get_msgId() == mavlink2.MAVLINK_MSG_ID_MISSION_ITEM_INT and frame in _GLOBAL_FRAMES:
            x, y = x * 1e-7, y * 1e-7  # MISSION_ITEM_INT: 1e7 degrees in every global frame
        params = (float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4))
        up["items"].append(
            MissionItem(seq, frame, int(msg.command), int(msg.autocontinue), params, x, y, float(msg.z))
        )
        up["tries"] = 0
        if len(up["items"]) < up["count"]:
            self._request_next_item(t)
            return
        self._mission = list(up["items"])
        self._mission_current = 0
        self._mission_done = False
        self._upload = None
        self._mission_ack(up["src"], mavlink2.MAV_MISSION_ACCEPTED)
        self._request_message(mavlink2.MAVLINK_MSG_ID_MISSION_CURRENT)

    def _on_mission_request_list(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        mtype = int(getattr(msg, "mission_type", _MISSION))
        count = len(self._mission) if mtype == _MISSION else 0
        self.conn.mav.mission_count_send(msg.get_srcSystem(), msg.get_srcComponent(), count, mtype)

    def _on_mission_request(self, msg: Any, t: float) -> None:
        """MISSION_REQUEST_INT (51) or MISSION_REQUEST (40): answered with MISSION_ITEM_INT."""
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        seq = int(msg.seq)
        mtype = int(getattr(msg, "mission_type", _MISSION))
        if mtype != _MISSION or not 0 <= seq < len(self._mission):
            self._mission_ack(src, mavlink2.MAV_MISSION_INVALID_SEQUENCE, mtype)
            return
        item = self._mission[seq]
        x, y = item.wire_xy()
        self.conn.mav.mission_item_int_send(
            src[0], src[1], seq, item.frame, item.command, int(seq == self._mission_current),
            item.autocontinue, *item.params, x, y, item.alt, _MISSION,
        )  # fmt: skip

    def _on_mission_clear_all(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        mtype = int(getattr(msg, "mission_type", _MISSION))
        if mtype in (_MISSION, mavlink2.MAV_MISSION_TYPE_ALL):
            self._mission_clear()
        self._mission_ack((msg.get_srcSystem(), msg.get_srcComponent()), mavlink2.MAV_MISSION_ACCEPTED, mtype)

    def _on_mission_set_current(self, msg: Any, t: float) -> None:
        if self._addressed(msg.target_system, msg.target_component, False):
            self._mission_set_current(int(msg.seq))

    def _mission_set_current(self, seq: int) -> bool:
        if not 0 <= seq < len(self._mission):
            return False
        self._mission_current = seq
        self._mission_done = False
        self._nav.pop("reached_at", None)
        self._request_message(mavlink2.MAVLINK_MSG_ID_MISSION_CURRENT)
        return True

    def _mission_clear(self) -> None:
        self._mission = []
        self._mission_current = 0
        self._mission_done = False
        if self._user_mode == (px4.MAIN_AUTO, px4.AUTO_MISSION) and self.armed:
            self._user_mode = (px4.MAIN_AUTO, px4.AUTO_LOITER)
            self._enter_nav()
        self._request_message(mavlink2.MAVLINK_MSG_ID_MISSION_CURRENT)

    # ------------------------------------------------------------------ flight

    def _mission_valid(self) -> bool:
        """A mission the vehicle can fly: items, each navigation item in a global frame with a position."""
        if not self._mission or self.gps_origin is None:
            return False
        for item in self._mission:
            if item.command in (_NAV_WAYPOINT, _LOITER_UNLIM, _LOITER_TIME) and not (
                item.frame in _GLOBAL_FRAMES and finite(item.lat) and finite(item.lon) and finite(item.alt)
            ):
                return False
        return True

    def _mission_start(self, t: float) -> None:
        """Entering AUTO.MISSION: a finished mission starts again from its first item."""
        if self._mission_done:
            self._mission_current = 0
            self._mission_done = False
        self._nav.pop("reached_at", None)

    def _item_target(self, item: MissionItem, here: Vec3) -> Vec3:
        """Local NED target of an item (NaN latitude/longitude/altitude: where the vehicle is)."""
        proj = self.projection()
        north, east, down = here
        if proj is not None and item.frame in _GLOBAL_FRAMES and finite(item.lat) and finite(item.lon):
            north, east = proj.project(item.lat, item.lon)
        if finite(item.alt) and item.frame in _GLOBAL_FRAMES:
            down = (
                self._home[2] - item.alt
                if item.frame in _RELATIVE_FRAMES
                else proj.alt - item.alt
                if proj
                else down
            )
        return north, east, down

    def _advance(self) -> None:
        self._nav.pop("reached_at", None)
        self._nav.pop("item_target", None)
        if self._mission_current + 1 >= len(self._mission):
            self._mission_done = True
            self._nav["hold"] = self.sim.estimator.out_position
        else:
            self._mission_current += 1
        self._request_message(mavlink2.MAVLINK_MSG_ID_MISSION_CURRENT)

    def _mission_navigate(self, t: float) -> None:
        """Fly AUTO.MISSION one control period."""
        sim = self.sim
        nav = self._nav
        est = sim.estimator
        for _ in range(len(self._mission) + 1):  # pass over DO items in one go
            if self._mission_done or not self._mission:
                sim.setpoint = Setpoint.hold(nav["hold"], nav["yaw"])
                return
            item = self._mission[self._mission_current]
            if item.command == _DO_CHANGE_SPEED:
                if finite(item.params[1]) and item.params[1] > 0:
                    self._cruise_speed = item.params[1]
                self._advance()
                continue
            if item.command not in _NAV_ITEMS:
                self._advance()
                continue
            break
        if item.command == _RTL:
            self._user_mode = (px4.MAIN_AUTO, px4.AUTO_RTL)
            self._enter_nav()
            return
        here = est.out_position
        target = nav.get("item_target")
        if target is None:
            if item.command == _TAKEOFF:
                alt = item.alt if finite(item.alt) else float(self.params.get("MIS_TAKEOFF_ALT"))
                base = nav["hold"]
                down = (
                    self._home[2] - alt
                    if item.frame in _RELATIVE_FRAMES or item.frame not in _GLOBAL_FRAMES
                    else self._item_target(item, here)[2]
                )
                target = (base[0], base[1], down)
            else:
                target = self._item_target(item, nav["hold"])
            nav["item_target"] = target
        yaw = item.params[3] if item.command == _NAV_WAYPOINT and finite(item.params[3]) else nav["yaw"]
        if item.command == _LAND:
            if math.hypot(target[0] - here[0], target[1] - here[1]) > 0.3 and not nav.get("landing"):
                sim.setpoint = self._carrot((target[0], target[1], here[2]), yaw)
            else:
                nav["landing"] = True
                speed = self._land_speed()
                sim.setpoint = Setpoint(
                    position=(target[0], target[1], NAN), velocity=(NAN, NAN, speed), yaw=yaw
                )
            return
        sim.setpoint = self._carrot(target, yaw)
        radius = (
            item.params[1]
            if item.command == _NAV_WAYPOINT and finite(item.params[1]) and item.params[1] > 0.01
            else float(self.params.get("NAV_ACC_RAD"))
        )
        reached = (
            math.hypot(target[0] - here[0], target[1] - here[1]) <= radius and abs(target[2] - here[2]) < 0.3
        )
        if not reached:
            return
        if "reached_at" not in nav:
            nav["reached_at"] = t
            self.conn.mav.mission_item_reached_send(item.seq)
        hold_s = (
            item.params[0]
            if item.command in (_NAV_WAYPOINT, _LOITER_TIME) and finite(item.params[0])
            else 0.0
        )
        if item.command == _LOITER_UNLIM:
            return
        if t - nav["reached_at"] >= max(0.0, hold_s):
            nav["hold"] = target
            self._advance()

    def _cmd_mission_start(self, p: tuple[float, ...], t: float) -> int:
        """MAV_CMD_MISSION_START (300): param1 first item."""
        if not self._mission_valid():
            self._statustext(px4.MAV_SEVERITY_CRITICAL, "Mission start denied! No valid mission", tab=True)
            return px4.MAV_RESULT_DENIED
        first = as_int(p[0], 0, len(self._mission) - 1)
        if first is not None and first > 0:
            self._mission_set_current(first)
        return self._change_mode((px4.MAIN_AUTO, px4.AUTO_MISSION), t)
