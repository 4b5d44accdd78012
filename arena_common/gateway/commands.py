"""The gateway's command queryable: arena operations turned into MAVLink exchanges with the autopilot.

Every :class:`~arena_common.core.wire.Command` on ``arena/<drone>/cmd`` is answered with a
:class:`~arena_common.core.wire.CommandResult` whose ``result`` is the autopilot's COMMAND_ACK result
(``ACCEPTED``, ``TEMPORARILY_REJECTED``, ``DENIED``…), ``TIMEOUT`` after the retries, ``REFUSED`` with the
reason when the arena's rules forbid it, ``FAILED`` when the autopilot accepted but did not do it, or
``ERROR`` for a malformed request.  The operations and their arguments are the table of
:mod:`arena_common.core.ops` (checked by :func:`~arena_common.core.ops.check` before anything is done;
``docs/wire.md`` prints it); what each does to the autopilot is in its method below.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from arena_common.core import ops, wire
from arena_common.core.arrival import ARRIVAL_TOLERANCE, Arrival
from arena_common.core.config import ArenaSpec, VehicleSpec
from arena_common.gateway.events import EventSink
from arena_common.gateway.origin import GlobalOrigin
from arena_common.gateway.setpoints import SetpointForwarder, outside, yaw_problem
from arena_common.gateway.state import VehicleState
from arena_common.gateway.timesync import TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink import px4
from arena_common.mavlink.protocols import MavCommander, ParamClient, SetupChecker, param_equal

__all__ = ["CommandExecutor"]

NAN = math.nan
#: PX4 main modes flown with sticks: PX4 accepts them disarmed, and fails safe in the air without input.
_MANUAL_MAINS = frozenset(
    {px4.MAIN_MANUAL, px4.MAIN_ALTCTL, px4.MAIN_POSCTL, px4.MAIN_ACRO, px4.MAIN_STABILIZED}
)
#: s an arm waits for this host's clock (and the vision behind it) to settle: a program arming right after
#: the arena came up meets the first exchanges with the mocap host's clock still under way.
CLOCK_SETTLE_S = 3.0
#: Results the autopilot gave (COMMAND_ACK, or acknowledged but not done) whose reason it may still be
#: sending: the answer waits up to TEXT_GRACE_S for its STATUSTEXT.
_SAID_BY_AUTOPILOT = frozenset({"DENIED", "TEMPORARILY_REJECTED", "FAILED", "UNSUPPORTED"})
TEXT_GRACE_S = 0.2
CONFIRM_ASK_S = 0.1  # s between heartbeat requests while a mode or arming change is being confirmed


class _BadArgs(ValueError):
    pass


def _result(result: str, reason: str = "", **value: Any) -> wire.CommandResult:
    return wire.CommandResult(ok=result == "ACCEPTED", result=result, reason=reason, value=value)


def _refused(reason: str) -> wire.CommandResult:
    return wire.CommandResult(ok=False, result="REFUSED", reason=reason)


class CommandExecutor:
    """Answers the commands of one vehicle (see the module's table); :meth:`handle` serves the queryable."""

    #: Each vehicle operation of :data:`arena_common.core.ops.OPS` is answered by the method named
    #: ``_<op>`` (``_arm``, ``_goto``…).

    def __init__(
        self,
        *,
        vehicle: VehicleSpec,
        arena: ArenaSpec,
        state: VehicleState,
        vision: VisionSender,
        commander: MavCommander,
        params: ParamClient,
        setup: SetupChecker,
        forwarder: SetpointForwarder,
        timesync: TimeSync,
        events: EventSink,
        origin: GlobalOrigin | None = None,
        vision_stale: float = 0.2,
        goto_tolerance: float = ARRIVAL_TOLERANCE,
        clock_problem: Callable[[], str | None] | None = None,
    ) -> None:
        self.vehicle = vehicle
        self.arena = arena
        self.state = state
        self.vision = vision
        self.commander = commander
        self.params = params
        self.setup = setup
        self.forwarder = forwarder
        self.timesync = timesync
        self.events = events
        self.origin = origin
        self.vision_stale = vision_stale
        self.goto_tolerance = goto_tolerance
        self.clock_problem = clock_problem
        self._src = threading.local()  # the source of the command this thread runs
        self._ops: dict[str, Callable[[Mapping[str, Any], float], wire.CommandResult]] = {
            op.name: getattr(self, f"_{op.name}") for op in ops.vehicle_ops()
        }

    # -- entry ---------------------------------------------------------------------------------------
    def handle(self, key: str, cmd: wire.Command) -> wire.CommandResult:
        """Run one command within its ``timeout`` (less a margin for the answer to travel)."""
        started_ns = wire.now_ns()
        deadline = time.monotonic() + max(0.5, cmd.timeout - 0.3)
        op = self._ops.get(cmd.op)
        if op is None:
            known = ", ".join(o.name for o in ops.vehicle_ops())
            result = wire.CommandResult(
                False, "ERROR", f"{cmd.op!r} is not a vehicle operation (known: {known})"
            )
        elif cmd.op != "ping" and not self.commander.link.can_send():
            heard = (
                "link lost: no heartbeat from the autopilot" if self.state.hb_count else "nothing heard yet"
            )
            result = _refused(f"no link to the autopilot ({heard})")
        else:
            self._src.name = cmd.src
            try:
                result = op(ops.check(cmd.op, cmd.args), deadline)
            except ops.OpError as exc:
                result = wire.CommandResult(False, "ERROR", str(exc))
            except (_BadArgs, px4.Px4Error) as exc:
                result = wire.CommandResult(False, "ERROR", f"{cmd.op}: {exc}")
        if not result.ok and result.result not in ("REFUSED", "ERROR"):
            texts = self._texts_since(started_ns)
            if not texts and result.result in _SAID_BY_AUTOPILOT:
                # PX4 sends its reason (STATUSTEXT) next to the COMMAND_ACK, often a millisecond after it.
                until = min(time.monotonic() + TEXT_GRACE_S, deadline + TEXT_GRACE_S)
                while not texts and time.monotonic() < until:
                    time.sleep(0.01)
                    texts = self._texts_since(started_ns)
            if texts:
                reason = f"{result.reason}; " if result.reason else ""
                result = result.replace(reason=f"{reason}autopilot says: {' | '.join(texts)}")
        if cmd.op != "ping":
            text = f"{cmd.op} → {result.result}" + (f": {result.reason}" if result.reason else "")
            self.events.emit(
                "command", text, 6 if result.ok else 4, op=cmd.op, result=result.result, src=cmd.src
            )
        # Stamped with our clock: every State stamped from now on already shows the command's effect.
        return result.replace(t=wire.now_ns())

    def _texts_since(self, t_ns: int) -> list[str]:
        texts = [
            e.text
            for e in list(self.events.recent)
            if e.t >= t_ns and e.kind in ("statustext", "failsafe") and e.sev <= 4
        ]
        return list(dict.fromkeys(texts))[-4:]

    # -- helpers -------------------------------------------------------------------------------------
    def _take(self, what: str) -> None:
        """This command takes the vehicle: every setpoint stream seen so far ends (docs/safety.md)."""
        src = getattr(self._src, "name", "")
        self.forwarder.supersede(f"{what} from {src or '?'}", src=src)

    def _confirm(self, predicate: Callable[[], bool], deadline: float) -> bool:
        if predicate():
            return True
        # A heartbeat now, not in up to 1 s; asked again while it shows the old state (PX4 acknowledges a
        # mode change, and answers at once, a few ms before its commander has switched).
        while True:
            self.commander.send(px4.MAV_CMD_REQUEST_MESSAGE, (0,))
            if self.state.wait(predicate, min(deadline, time.monotonic() + CONFIRM_ASK_S)):
                return True
            if time.monotonic() >= deadline:
                return False

    def _set_mode(self, name: str, deadline: float) -> wire.CommandResult:
        main, sub = px4.mode_from_name(name)
        expected = px4.mode_name(main, sub)
        result = self.commander.command(
            px4.MAV_CMD_DO_SET_MODE, (px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub), deadline
        )
        if result != "ACCEPTED":
            return _result(result, f"{expected} not accepted")
        if not self._confirm(lambda: self.state.mode == expected, deadline):
            return _result("FAILED", f"{expected} acknowledged, but the heartbeat reports {self.state.mode}")
        return _result("ACCEPTED", mode=expected)

    def arm_refusal(self, deadline: float) -> str | None:
        """Why arming is refused under the arena's rules, or None."""
        if not self.state.link:
            return "no heartbeat from the autopilot"
        if self.setup.reboot_pending:
            return (
                f"{', '.join(self.setup.reboot_pending)} written but in effect only after a reboot: "
                f"`arena px4 reboot {self.vehicle.name}` (or power-cycle the vehicle)"
            )
        if self.vehicle.require_setup:
            if self.setup.ok is None:
                self.setup.check(deadline)
            if self.setup.ok is not True:
                report = self.setup.report
                wrong = ", ".join(report.get("wrong", []) + report.get("missing", [])) or "not checked"
                return f"arena parameters not set ({wrong}): run `arena px4 setup {self.vehicle.name}`"
        if self.origin is not None:
            # PX4 arms in Hold only with a global position: let the EKF origin exchange finish first.
            self.origin.wait_settled(deadline - 0.5)
        return self._settled(deadline)

    def _pose_problem(self) -> str | None:
        """Why pose times cannot be trusted (the clock: checked first, it is why no pose would reach the
        autopilot) or no fresh pose reached the autopilot (the vision sender says why), or None."""
        clock = self.clock_problem() if self.clock_problem is not None else None
        return clock or self.vision.problem(time.monotonic(), self.vision_stale)

    def _settled(self, deadline: float) -> str | None:
        """:meth:`_pose_problem`, given a moment (bounded) to clear: just after start-up the clock's first
        exchanges, or the first poses, may still be under way."""
        problem = self._pose_problem()
        until = min(deadline - 0.5, time.monotonic() + CLOCK_SETTLE_S)
        while problem is not None and time.monotonic() < until:
            time.sleep(0.1)
            problem = self._pose_problem()
        return problem

    # -- operations ----------------------------------------------------------------------------------
    def _arm(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        reason = self.arm_refusal(deadline)
        if reason:
            return _refused(reason)
        result = self.commander.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0), deadline)
        if result == "ACCEPTED" and not self._confirm(lambda: self.state.armed, deadline):
            return _result("FAILED", "arming acknowledged, but the heartbeat reports disarmed")
        return _result(result)

    def _disarm(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        result = self.commander.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, (0, 0), deadline)
        if result == "ACCEPTED" and not self._confirm(lambda: not self.state.armed, deadline):
            return _result("FAILED", "disarming acknowledged, but the heartbeat reports armed")
        return _result(result)

    def _kill(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        self._take("kill")
        self.forwarder.latch("kill")
        params = (0, px4.ARM_DISARM_FORCE_MAGIC)
        return _result(self.commander.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, params, deadline))

    def _takeoff(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        height = args["height"]
        ceiling = -self.arena.safe_box()[2][0]
        if not 0.2 <= height <= ceiling:
            return _refused(f"takeoff height {height:.2f} m outside [0.20, {ceiling:.2f}] (the safe volume)")
        back = self.params.write("MIS_TAKEOFF_ALT", height, px4.MAV_PARAM_TYPE_REAL32, deadline)
        if back is None:
            return _result("TIMEOUT", "could not set MIS_TAKEOFF_ALT")
        self._take("takeoff")
        result = self.commander.command(px4.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, NAN, NAN, NAN, NAN), deadline)
        return _result(result, height=height)

    def _land(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        self._take("land")
        return _result(self.commander.command(px4.MAV_CMD_NAV_LAND, (0, 0, 0, NAN, NAN, NAN, NAN), deadline))

    def _hold(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        self._take("hold")
        return self._set_mode("AUTO.LOITER", deadline)

    def _mode(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        main, sub = px4.mode_from_name(args["mode"])
        name = px4.mode_name(main, sub)
        if main in _MANUAL_MAINS:
            return _refused(f"{name} needs manual control input, which the arena never sends")
        if main != px4.MAIN_OFFBOARD:
            self._take(f"mode {name}")
            return self._set_mode(name, deadline)
        grounded = self.state.flight_problem()
        if grounded is not None:
            return _refused(f"{grounded}: take off first (OFFBOARD flies only a vehicle in the air)")
        snap = self.forwarder.snapshot()
        why = self.forwarder.engage(args["stream"], getattr(self._src, "name", ""))
        if why is not None:
            return _refused(why)
        if self.state.mode != "OFFBOARD":
            until = min(deadline, time.monotonic() + self.forwarder.prestream + 0.5)
            while not self.forwarder.live() and time.monotonic() < until:
                time.sleep(0.02)
            if not self.forwarder.live():
                self.forwarder.restore(snap)
                return _refused(
                    "no live setpoint stream: stream setpoints (within their lease) for "
                    f"{self.forwarder.prestream:.1f} s first, or use goto"
                )
        return self._set_mode(name, deadline)

    def _goto(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        goal = args["p"]
        yaw = args["yaw"] if args["yaw"] is not None else self.state.yaw()
        tol = args["tol"] if args["tol"] is not None else self.goto_tolerance
        wait = args["wait"]
        problem = yaw_problem(yaw)
        if problem:  # every argument is checked before the stream starts
            raise _BadArgs(problem)
        if tol <= 0.0:
            raise _BadArgs(f"argument 'tol' must be a positive distance in metres, got {tol!r}")
        where = outside(goal, self.arena.safe_box())
        if where:
            return _refused(f"goal outside the safe volume: {where}")
        grounded = self.state.flight_problem()
        if grounded is not None:
            return _refused(f"{grounded}: take off first")
        sep = self.forwarder.separation
        near = sep.path_problem(self.state.position(time.monotonic()), goal) if sep is not None else None
        if near is not None:
            return _refused(f"{near}: vehicles never meet")
        snap = self.forwarder.snapshot()
        self.forwarder.start_goto(goal, yaw, src=getattr(self._src, "name", ""))
        if self.state.mode != "OFFBOARD":
            while not self.forwarder.live() and time.monotonic() < deadline:
                time.sleep(0.02)
            res = self._set_mode("OFFBOARD", deadline)
            if not res.ok:
                self.forwarder.cancel_goto(f"OFFBOARD not engaged ({res.result})")
                self.forwarder.restore(snap)
                return res
        value: dict[str, Any] = {"goal": list(goal)}
        if wait:
            judge = Arrival(goal, tol)

            def arrived() -> bool:
                judge.add(time.monotonic(), self.state.position(time.monotonic()))
                return judge.arrived()

            reached = self.state.wait(arrived, deadline)
            value["dist"] = self._distance(goal)
            if not reached:
                return _result("IN_PROGRESS", f"not arrived: {judge.describe()}; holding the goal", **value)
        return _result("ACCEPTED", **value)

    def _distance(self, goal: tuple[float, float, float]) -> float:
        p = self.state.position(time.monotonic())
        return math.dist(p, goal) if p is not None else math.inf

    def _reboot(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        """Reboot the autopilot and wait until it is back (its boot clock restarted, heartbeats again)."""
        if self.state.armed:
            return _refused("armed: disarm first")
        s = self.state
        before = s.reboots
        s.expect_reboot(deadline)  # before asking: it may fall silent before this thread hears the answer
        result = self.commander.command(px4.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, (1,), deadline)
        if result != "ACCEPTED":
            s.expect_reboot(-math.inf)
            return _result(result, "the autopilot did not accept PREFLIGHT_REBOOT_SHUTDOWN: power-cycle it")
        if not s.wait(lambda: s.reboots > before and s.link, deadline):  # back: its boot clock restarted
            return _result("TIMEOUT", "reboot accepted, but the autopilot is not back yet")
        return _result("ACCEPTED", reboots=self.state.reboots)

    def _param_get(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        name = args["name"]
        px4.param_name_bytes(name)
        got = self.params.read([name], deadline)
        if name not in got:
            return _result("TIMEOUT", f"no PARAM_VALUE for {name} (unknown parameter?)")
        value, ptype = got[name]
        return _result("ACCEPTED", name=name, value=value, type=ptype)

    def _param_set(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        name, want = args["name"], args["value"]
        px4.param_name_bytes(name)
        got = self.params.read([name], deadline)
        if name not in got:
            return _result("TIMEOUT", f"no PARAM_VALUE for {name} (unknown parameter?)")
        ptype = got[name][1]
        back = self.params.write(name, want, ptype, deadline)
        if back is None:
            return _result("TIMEOUT", f"{name} not confirmed by the autopilot")
        if not param_equal(
            back[0], px4.decode_param_value(px4.encode_param_value(want, ptype), ptype), ptype
        ):
            return _result("FAILED", f"{name} reads back {back[0]}", name=name, value=back[0], type=ptype)
        if name in self.setup.required:
            self.setup.ok = None  # re-checked before the next arming
        return _result("ACCEPTED", name=name, value=back[0], type=ptype)

    def _check(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        report = self.setup.check(deadline)
        if not report["complete"]:
            return _result("TIMEOUT", "no parameter answered", **report)
        notes = "; ".join(report.get("notes", {}).values())
        if report["ok"] and not report.get("advice"):
            return _result("ACCEPTED", notes, **report)
        n = len(report["wrong"]) + len(report["missing"]) + len(report.get("advice", []))
        return _result(
            "FAILED", f"{n} parameters differ; {notes}" if notes else f"{n} parameters differ", **report
        )

    def _setup(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        if self.state.armed:
            return _refused("armed: parameters are written on the ground only")
        report = self.setup.setup(deadline)
        if not report["complete"]:
            return _result("TIMEOUT", "no parameter answered", **report)
        if report.get("written"):
            # PX4 saves changed parameters a moment later (measured: not yet after 0.2 s, done after 3 s):
            # a power-cycle right after setup would lose them.  Save now.
            saved = self.commander.command(px4.MAV_CMD_PREFLIGHT_STORAGE, (1,), deadline)
            report = {**report, "saved": saved}
            if saved != "ACCEPTED":
                self.events.emit(
                    "setup",
                    f"saving the parameters: {saved} (they are saved a moment later by themselves)",
                    4,
                )
        if report["ok"] and self.setup.reboot_pending:
            pending = ", ".join(self.setup.reboot_pending)
            rebooted = self._reboot({}, deadline)
            if not rebooted.ok:
                return _result(
                    "FAILED",
                    f"{pending} take effect only after a reboot: {rebooted.result} ({rebooted.reason}); "
                    "arming is refused until the autopilot reboots",
                    **report,
                )
            verified = self.setup.check(deadline)
            # What the check before the reboot measured still holds (the link did not change).
            notes = {**report.get("notes", {}), **verified.get("notes", {})}
            report = {**report, **verified, "rebooted": True, "notes": notes}
        if report["ok"]:
            rebooted_for = ", ".join(report["reboot_required"])
            note = f" (rebooted for {rebooted_for})" if report.get("rebooted") else ""
            why = "".join(f"; {text}" for text in report.get("notes", {}).values())
            return _result("ACCEPTED", f"arena parameters set and verified{note}{why}", **report)
        return _result("FAILED", "; ".join(report["failed"]) or "parameters still differ", **report)

    def _ping(self, args: Mapping[str, Any], deadline: float) -> wire.CommandResult:
        now = time.monotonic()
        s = self.state
        return _result(
            "ACCEPTED",
            sysid=self.vehicle.system_id,
            link=s.link,
            hb_age=s.hb_age(now),
            mode=s.mode,
            armed=s.armed,
            rtt=self.timesync.rtt_s,
            setup_ok=self.setup.ok,
        )
