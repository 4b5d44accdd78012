"""The MAVLink command and parameter protocols as the gateway runs them, and the arena's parameter check.

:class:`MavCommander` runs COMMAND_LONG exchanges (retries with confirmation + 1, IN_PROGRESS, one
exchange per command id at a time); :class:`ParamClient` reads and writes parameters by name, INT32 values
travelling bytewise as PX4 wants; :class:`SetupChecker` compares the vehicle with
:data:`arena_common.mavlink.px4.ARENA_REQUIRED_PARAMS` and writes what differs.  The link reader feeds
``on_ack`` / ``on_param_value``; callers block in their own threads, each call bounded by a deadline
(:func:`time.monotonic` seconds).
"""

from __future__ import annotations

import collections
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Protocol

from arena_common.mavlink import px4
from arena_common.mavlink.link import MavlinkLink


class Events(Protocol):
    """Where the protocols report what happened (the gateway's :class:`~arena_common.gateway.events.EventSink`)."""

    def emit(self, kind: str, text: str, sev: int = 6, *, every: float = 0.0, **data: Any) -> Any: ...


__all__ = ["MavCommander", "ParamClient", "RebootRequired", "SetupChecker", "param_equal"]

_PARAM_TYPE_NAMES = {
    px4.MAV_PARAM_TYPE_UINT8: "UINT8",
    px4.MAV_PARAM_TYPE_INT8: "INT8",
    px4.MAV_PARAM_TYPE_UINT16: "UINT16",
    px4.MAV_PARAM_TYPE_INT16: "INT16",
    px4.MAV_PARAM_TYPE_UINT32: "UINT32",
    px4.MAV_PARAM_TYPE_INT32: "INT32",
    px4.MAV_PARAM_TYPE_REAL32: "REAL32",
}
#: Where the names of the parameters that take effect only after a reboot come from: a callable that
#: returns them (from the autopilot's own metadata) or None when it cannot tell.
RebootRequired = Callable[[float], "frozenset[str] | None"]


class MavCommander:
    """COMMAND_LONG with retries: one outstanding exchange per command id, matched to its COMMAND_ACK.

    Each attempt waits ``ack_timeout`` s; unanswered attempts are resent with confirmation + 1, up to
    ``attempts``; IN_PROGRESS extends the wait for the final answer (up to the caller's deadline).
    Returns the MAV_RESULT name, or ``"TIMEOUT"``.
    """

    def __init__(
        self,
        link: MavlinkLink,
        target_system: int,
        target_component: int = px4.MAV_COMP_ID_AUTOPILOT1,
        *,
        ack_timeout: float = 0.8,
        attempts: int = 3,
    ) -> None:
        self.link = link
        self.target = (target_system, target_component)
        self.ack_timeout = ack_timeout
        self.attempts = attempts
        self._cond = threading.Condition()
        self._acks: dict[int, tuple[int, int]] = {}  # command → (result, serial)
        self._serial = 0
        self._locks: dict[int, threading.Lock] = collections.defaultdict(threading.Lock)

    def on_ack(self, msg: Any, now: float) -> None:
        ts = getattr(msg, "target_system", 0)
        if ts not in (0, self.link.mav.srcSystem):
            return  # an answer to a ground station
        with self._cond:
            self._serial += 1
            self._acks[int(msg.command)] = (int(msg.result), self._serial)
            self._cond.notify_all()

    def send(self, command: int, params: Sequence[float] = (), confirmation: int = 0) -> bool:
        """Send once, expecting nothing back."""
        p = [float(x) for x in params][:7]
        p += [0.0] * (7 - len(p))
        msg = self.link.mav.command_long_encode(*self.target, command, confirmation, *p)
        return self.link.send(msg)

    def command(self, command: int, params: Sequence[float] = (), deadline: float | None = None) -> str:
        """Run one command to its final result (MAV_RESULT name) or ``"TIMEOUT"``."""
        deadline = time.monotonic() + self.ack_timeout * self.attempts if deadline is None else deadline
        with self._locks[command]:
            for attempt in range(self.attempts):
                with self._cond:
                    start = self._serial
                self.send(command, params, attempt)
                wait_until = min(deadline, time.monotonic() + self.ack_timeout)
                result = self._wait_ack(command, start, wait_until)
                while result == px4.MAV_RESULT_IN_PROGRESS:
                    with self._cond:
                        start = self._serial
                    result = self._wait_ack(command, start, deadline)
                    if result is None:
                        return "TIMEOUT"
                if result is not None:
                    return px4.result_name(result)
                if time.monotonic() >= deadline:
                    break
            return "TIMEOUT"

    def _wait_ack(self, command: int, after: int, until: float) -> int | None:
        with self._cond:
            while True:
                got = self._acks.get(command)
                if got is not None and got[1] > after:
                    return got[0]
                left = until - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)


class ParamClient:
    """The parameter protocol: read by name, write and read back; values decoded bytewise (INT32)."""

    def __init__(
        self, link: MavlinkLink, target_system: int, *, timeout: float = 0.8, attempts: int = 3
    ) -> None:
        self.link = link
        self.target_system = target_system
        self.timeout = timeout
        self.attempts = attempts
        self._cond = threading.Condition()
        self._values: dict[str, tuple[float, int, int]] = {}  # name → (wire float, type, serial)
        self._serial = 0

    def on_param_value(self, msg: Any, now: float) -> None:
        name = px4.param_name_from_field(msg.param_id)
        with self._cond:
            self._serial += 1
            self._values[name] = (float(msg.param_value), int(msg.param_type), self._serial)
            self._cond.notify_all()

    def read(self, names: Iterable[str], deadline: float) -> dict[str, tuple[px4.ParamValue, int]]:
        """Values and MAV_PARAM_TYPEs of the parameters that answered before ``deadline``."""
        pending = list(dict.fromkeys(names))
        got: dict[str, tuple[px4.ParamValue, int]] = {}
        for _ in range(self.attempts):
            if not pending or time.monotonic() >= deadline:
                break
            with self._cond:
                start = self._serial
            for name in pending:
                self.link.send(
                    self.link.mav.param_request_read_encode(
                        self.target_system, 1, px4.param_name_bytes(name), -1
                    )
                )
            until = min(deadline, time.monotonic() + self.timeout + 0.02 * len(pending))
            with self._cond:
                while True:
                    for name in list(pending):
                        value = self._values.get(name)
                        if value is not None and value[2] > start:
                            got[name] = (_decode(value[0], value[1]), value[1])
                            pending.remove(name)
                    left = until - time.monotonic()
                    if not pending or left <= 0:
                        break
                    self._cond.wait(left)
        return got

    def write(
        self, name: str, value: px4.ParamValue, param_type: int, deadline: float
    ) -> tuple[px4.ParamValue, int] | None:
        """Set one parameter; the value read back (PX4 answers a PARAM_SET with PARAM_VALUE), or None."""
        encoded = px4.encode_param_value(value, param_type)
        for _ in range(self.attempts):
            if time.monotonic() >= deadline:
                break
            with self._cond:
                start = self._serial
            self.link.send(
                self.link.mav.param_set_encode(
                    self.target_system, 1, px4.param_name_bytes(name), encoded, param_type
                )
            )
            until = min(deadline, time.monotonic() + self.timeout)
            with self._cond:
                while True:
                    got = self._values.get(name)
                    if got is not None and got[2] > start:
                        return _decode(got[0], got[1]), got[1]
                    left = until - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
        return None


def _decode(wire_value: float, param_type: int) -> px4.ParamValue:
    try:
        return px4.decode_param_value(wire_value, param_type)
    except px4.Px4Error:
        return wire_value


def param_equal(have: px4.ParamValue, want: px4.ParamValue, param_type: int) -> bool:
    """Whether a parameter read back equals the wanted value (REAL32 compared as float32)."""
    if param_type == px4.MAV_PARAM_TYPE_REAL32:
        f32 = struct.unpack("<f", struct.pack("<f", float(want)))[0]
        return bool(have == f32 or abs(float(have) - float(want)) <= 1e-6 * max(1.0, abs(float(want))))
    return float(have) == float(want)


class SetupChecker:
    """Checks (and sets) the parameters the arena requires (:data:`~arena_common.mavlink.px4.ARENA_REQUIRED_PARAMS`).

    :attr:`ok` is None until a check completed, then whether every parameter matched.  Which parameters
    need a reboot to take effect comes from ``reboot_required`` (the autopilot's own metadata); when it
    cannot tell, every parameter written is taken to need one.  :attr:`reboot_pending` names those written
    since the autopilot last rebooted: the vehicle must not fly before it reboots (PX4 v1.16 keeps using
    the old EKF2_HGT_REF, EKF2_EV_DELAY, EKF2_MAG_TYPE… and changes of the height reference at runtime
    make the local position jump).
    """

    def __init__(
        self,
        params: ParamClient,
        events: Events,
        required: Mapping[str, tuple[px4.ParamValue, int]] = px4.ARENA_REQUIRED_PARAMS,
        reboot_required: RebootRequired | None = None,
    ) -> None:
        self.params = params
        self.events = events
        self.required = dict(required)
        # Parameters judged within a tolerance instead of equal (name → how far off is still right).
        self.tolerance: dict[str, float] = {}
        # Why a required value is what it is, for a parameter that follows the link (name → words).
        self.notes: dict[str, str] = {}
        self.before: Callable[[], None] | None = None  # called first by every check: update ``required``
        # Judged, reported and written by setup, but never a reason to refuse arming (``advice``).
        self.advisory: set[str] = set()
        self.reboot_required = reboot_required
        self.ok: bool | None = None
        self.report: dict[str, Any] = {}
        self.reboot_pending: tuple[str, ...] = ()
        self._lock = threading.Lock()

    def rebooted(self) -> None:
        """The autopilot rebooted: what was written is now in effect, and must be checked again."""
        self.ok = None
        self.reboot_pending = ()

    def _right(self, name: str, have: px4.ParamValue, want: px4.ParamValue, ptype: int) -> bool:
        """Equal (as the autopilot stores it), or within the parameter's :attr:`tolerance` when it has one."""
        if name in self.tolerance:
            return abs(float(have) - float(want)) <= self.tolerance[name]
        return param_equal(have, want, ptype)

    def _rows(self, got: Mapping[str, tuple[px4.ParamValue, int]]) -> dict[str, dict[str, Any]]:
        rows: dict[str, dict[str, Any]] = {}
        for name, (want, want_type) in self.required.items():
            have = got.get(name)
            ptype = have[1] if have else want_type
            rows[name] = {
                "want": want,
                "have": have[0] if have else None,
                "type": _PARAM_TYPE_NAMES.get(ptype, str(ptype)),
                "ok": have is not None and self._right(name, have[0], want, ptype),
            }
        return rows

    def check(self, deadline: float, *, announce: bool = True) -> dict[str, Any]:
        """Read every required parameter; the report ``{ok, params: {name: {want, have, type, ok}}, …}``."""
        if self.before is not None:
            self.before()
        with self._lock:
            got = self.params.read(self.required, deadline)
            rows = self._rows(got)
            missing = [n for n, r in rows.items() if r["have"] is None]
            off = [n for n, r in rows.items() if not r["ok"] and r["have"] is not None]
            wrong = [n for n in off if n not in self.advisory]
            advice = [n for n in off if n in self.advisory]
            ok = not missing and not wrong
            if missing and len(missing) == len(rows):
                # Nothing answered: the check did not happen (link down), keep the previous verdict.
                report = {"ok": False, "params": rows, "missing": missing, "wrong": wrong, "complete": False}
                self.report = report
                return report
            self.ok = ok
            report = {
                "ok": ok,
                "params": rows,
                "missing": missing,
                "wrong": wrong,
                "advice": advice,
                "complete": True,
                "notes": dict(self.notes),
            }
            self.report = report
        if announce:
            if ok:
                self.events.emit("setup", "arena parameters set", 6)
            else:
                diff = ", ".join(f"{n}={rows[n]['have']} (want {rows[n]['want']})" for n in wrong)
                parts = [p for p in (diff, f"no answer for {', '.join(missing)}" if missing else "") if p]
                self.events.emit(
                    "setup", "arena parameters not set: " + "; ".join(parts), 4, wrong=wrong, missing=missing
                )
        return report

    def setup(self, deadline: float) -> dict[str, Any]:
        """Write every required parameter that differs, read all back; the check report plus ``written``."""
        first = self.check(deadline, announce=False)
        written: list[str] = []
        failed: list[str] = []
        for name, row in first["params"].items():
            if row["ok"]:
                continue
            want, want_type = self.required[name]
            ptype = next((t for t, n in _PARAM_TYPE_NAMES.items() if n == row["type"]), want_type)
            try:
                back = self.params.write(name, want, ptype, deadline)
            except px4.Px4Error as exc:
                failed.append(f"{name}: {exc}")
                continue
            if back is None:
                failed.append(f"{name}: no answer")
            else:
                written.append(name)
        report = self.check(deadline)
        report["written"] = written
        report["failed"] = failed
        known = self.reboot_required(deadline) if self.reboot_required is not None and written else None
        need = sorted(known.intersection(written) if known is not None else written)
        report["reboot_required"] = need
        report["reboot_metadata"] = known is not None
        if need:
            self.reboot_pending = tuple(sorted({*self.reboot_pending, *need}))
        if written:
            self.events.emit("setup", f"wrote {', '.join(written)}", 5, written=written, reboot_required=need)
        return report
