"""The MAVLink gateway of one vehicle: the arena bus on one side, its PX4 on the other.

:class:`Gateway` wires the parts (:mod:`arena_common.gateway`, :mod:`arena_common.gateway.setpoints`,
:mod:`arena_common.gateway.commands`, :mod:`arena_common.mavlink.protocols`, :mod:`arena_common.mavlink.link`)
and runs them in threads:

- **link reader** — frames of the vehicle's system id only; answers TIMESYNC requests at once, feeds
  acknowledgements, parameter values and the vehicle state, publishes raw telemetry (rate-limited per
  message type, decoding only what is used) and forwards every frame to the ground station if any;
- **vision** — each pose on ``arena/<drone>/vision`` goes out once, as soon as it arrives, as ODOMETRY
  (or VISION_POSITION_ESTIMATE), sent from the Zenoh thread that received it (no hand-off: a short,
  bounded, non-blocking piece of work); it needs neither the reader nor the bus router, so a gateway
  next to its downsampler keeps the vision flowing (peer to peer on loopback) when the router dies;
- **setpoints** — the offboard stream with its leases and safety rules;
- **commands** — the ``arena/<drone>/cmd`` queryable (two workers), and ``arena/estop``;
- **events** — published in order from their own thread, so a congested bus never stalls the rest;
- **supervisor** (the caller's thread, :meth:`Gateway.run`) — State at ``state_rate`` (published while
  anyone subscribes, else built only for its events at ``unwatched_rate``, or ``idle_rate`` while
  disarmed; :class:`~arena_common.gateway.state.StateReport`), the link's supervision
  (:class:`~arena_common.gateway.linkwatch.LinkWatch`: our HEARTBEAT and TIMESYNC probe at 1 Hz, link
  loss after no HEARTBEAT for 3 s, re-opening, what is asked of the autopilot when the link comes up)
  and its health (:class:`~arena_common.gateway.health.Health`: rejects, signing, the clock's events).

We speak as ``source_system`` (245 by default: not QGroundControl's 255) and component
MAV_COMP_ID_ONBOARD_COMPUTER (191), and always address the configured ``system_id``, never 0.

Given the process's :class:`~arena_common.runtime.clock.ClockSync` (``clock``), pose times — on the mocap
host's clock — are corrected by this host's measured offset before their age is judged and ODOMETRY is
stamped; arming is refused while that offset is unknown or too uncertain (the reason names the clock),
an offset beyond ``clock.max_offset`` raises a ``clock`` event naming the fix (chrony), and the state's
``fs`` says ``clock_unknown``, ``clock_uncertain``, ``clock_offset`` or ``clock_unchecked`` (no
reference on the bus, ``clock.require`` false).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from arena_common.bus.session import Bus, Handler, Lane, Received, Subscription, typed
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.gateway.clockwatch import ClockWatch
from arena_common.gateway.commands import CommandExecutor
from arena_common.gateway.evdelay import EvDelay
from arena_common.gateway.events import EventSink
from arena_common.gateway.health import Health
from arena_common.gateway.linkwatch import LinkWatch
from arena_common.gateway.options import GatewayOptions, stream_ids
from arena_common.gateway.origin import GlobalOrigin
from arena_common.gateway.separation import Separation
from arena_common.gateway.setpoints import SetpointForwarder
from arena_common.gateway.state import StateReport, VehicleState
from arena_common.gateway.telemetry import TelemetryPublisher
from arena_common.gateway.timesync import TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink import px4
from arena_common.mavlink.link import MSG, GcsForwarder, MavlinkLink, MavlinkLinkError
from arena_common.mavlink.metadata import HANDLED_MESSAGES, MetadataClient
from arena_common.mavlink.protocols import MavCommander, ParamClient
from arena_common.mavlink.signing import GATEWAY_UNSIGNED, LinkSigning, vehicle_key
from arena_common.runtime.clock import ClockSync
from arena_common.runtime.service import Stats

__all__ = ["Gateway", "GatewayOptions"]


class Gateway:
    """One vehicle's gateway.  ``with Gateway(cfg, "d1", bus) as gw: gw.run(stop)``.

    ``bus`` may be None to drive the MAVLink side alone (then nothing is published or served).
    """

    def __init__(
        self,
        cfg: ArenaConfig,
        vehicle: str,
        bus: Bus | None,
        *,
        options: GatewayOptions | None = None,
        stats: Stats | None = None,
        log: logging.Logger | None = None,
        clock: ClockSync | None = None,
        own_vision: bool = True,
    ) -> None:
        self.cfg = cfg
        self.own_vision = own_vision  # False: a host process hands it its vision (:meth:`offer_vision`)
        self.clock = clock
        self.spec = v = cfg.vehicle(vehicle)
        self.name = v.name
        self.bus = bus
        self.options = o = options or GatewayOptions()
        self.state_rate, self.telemetry_rate = v.state_rate, v.telemetry_rate
        self.stats = stats or Stats()
        self.log = log or logging.getLogger(f"arena.gateway.{v.name}")
        stream_rates = stream_ids(cfg, v.name)  # before opening anything: a bad name is a config error
        key = vehicle_key(cfg, v.name)  # SigningError (a ConfigError) for a bad key file
        self.signing = LinkSigning(key, allow_unsigned=GATEWAY_UNSIGNED) if key is not None else None
        self.link = MavlinkLink(
            v.mavlink,
            v.system_id,
            source_system=v.gateway_system_id,
            source_component=o.source_component,
            signing=self.signing,
            peer=v.mavlink_peer or None,
            budget=o.link_budget,
        )
        self._event_pub = bus.command_publisher(keys.events(v.name), wire.Event) if bus is not None else None
        self.events = EventSink(self._event_pub.put if self._event_pub is not None else None, self.log)
        self.clock_watch = ClockWatch(clock, cfg.clock, self.events)
        self.state = VehicleState(v.system_id, self.events, o.link_timeout)
        self.origin = (
            GlobalOrigin(self.link, v.system_id, v.origin, self.events) if v.origin != "off" else None
        )
        self.timesync = TimeSync(self.link)
        self.vision = VisionSender(
            self.link,
            max_pose_age=v.max_pose_age,
            message=v.vision_message,
            send_velocity=o.send_velocity,
            stats=self.stats,
            offset_ns=clock.offset_ns if clock is not None else None,
            stamp_us=self.timesync.autopilot_us,
            source=keys.vision(v.name),
            published_on_mocap_clock=cfg.pipeline.decimate == "transform",
        )
        self.health = Health(self.link, self.vision, self.clock_watch, self.stats, self.events, self.log)
        self.link.on_reject = self.health.rejected  # frames of the vehicle refused for their signature
        self.commander, self.params, self.metadata = self._protocols()
        self.linkwatch = LinkWatch(
            self.link, self.state, self.commander, self.params, self.metadata, self.timesync, self.events,
            name=v.name, origin=self.origin, options=o, stream_rates=stream_rates,
        )  # fmt: skip
        self.setup = self.linkwatch.setup
        self.ev_delay = EvDelay(v.name, self.timesync, self.vision, self.setup, self.events)
        self.separation = Separation(self.name, self.cfg.arena.min_separation)
        self.forwarder = self._setpoint_forwarder()
        self.executor = self._command_executor()
        self.report = StateReport(
            self.state, self.vision, self.forwarder, self.setup, self.timesync, self.clock_watch,
            fused_tolerance=o.fused_tolerance,
        )  # fmt: skip
        self.telemetry = TelemetryPublisher(bus, v.name, self.telemetry_rate, exclude=(MSG["TIMESYNC"],))
        self.gcs = GcsForwarder(v.gcs, self.link, allow_manual=v.allow_gcs_manual) if v.gcs else None
        self.state.on_mode_change.append(self._mode_changed)
        self.state.on_reboot.append(self.linkwatch.rebooted)
        self.state.on_link_change.append(self.linkwatch.link_changed)
        self._handlers = self._message_handlers()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._state_pub = (
            bus.stream_publisher(keys.state(v.name), wire.State, Lane.REPORT) if bus is not None else None
        )
        self._started = False

    def _protocols(self) -> tuple[MavCommander, ParamClient, MetadataClient]:
        """The MAVLink exchanges with the autopilot: commands, parameters, its metadata."""
        v, o = self.spec, self.options
        commander = MavCommander(self.link, v.system_id, ack_timeout=o.ack_timeout, attempts=o.attempts)
        params = ParamClient(self.link, v.system_id, timeout=o.ack_timeout, attempts=o.attempts)
        # The autopilot's own parameter metadata (COMPONENT_METADATA + MAVLink FTP): which parameters need
        # a reboot.  Never reset an FTP session: a ground station may be using it through the forwarder.
        metadata = MetadataClient(self.link, v.system_id, reset_busy=False)
        return commander, params, metadata

    def _setpoint_forwarder(self) -> SetpointForwarder:
        o = self.options
        return SetpointForwarder(
            self.link,
            self.spec.system_id,
            self.cfg.arena,
            self.events,
            rate=o.stream_rate,
            prestream=o.prestream,
            goto_speed=o.goto_speed,
            goto_climb=o.goto_climb,
            position=lambda: self.state.position(time.monotonic()),
            velocity=lambda: self.state.v if self.state.position(time.monotonic()) is not None else None,
            grounded=self.state.flight_problem,
            separation=self.separation,
            stats=self.stats,
        )

    def _command_executor(self) -> CommandExecutor:
        return CommandExecutor(
            vehicle=self.spec,
            arena=self.cfg.arena,
            state=self.state,
            vision=self.vision,
            commander=self.commander,
            params=self.params,
            setup=self.setup,
            forwarder=self.forwarder,
            timesync=self.timesync,
            events=self.events,
            origin=self.origin,
            vision_stale=self.options.vision_stale,
            clock_problem=self.clock_problem,
        )

    def _message_handlers(self) -> dict[int, Callable[[Any, float], None]]:
        """Which object reads each message the autopilot sends (the rest goes to telemetry only)."""
        handlers: dict[int, Callable[[Any, float], None]] = {
            MSG["HEARTBEAT"]: self.state.on_heartbeat,
            MSG["SYS_STATUS"]: self.state.on_sys_status,
            MSG["EXTENDED_SYS_STATE"]: self.state.on_ext_sys_state,
            MSG["LOCAL_POSITION_NED"]: self.state.on_local_position,
            MSG["ATTITUDE_QUATERNION"]: self.state.on_attitude,
            MSG["BATTERY_STATUS"]: self.state.on_battery,
            MSG["STATUSTEXT"]: self.state.on_statustext,
            MSG["ESTIMATOR_STATUS"]: self.state.on_estimator_status,
            MSG["TIMESYNC"]: self.timesync.on_timesync,
            MSG["COMMAND_ACK"]: self.commander.on_ack,
            MSG["PARAM_VALUE"]: self.params.on_param_value,
        }
        for msgid in HANDLED_MESSAGES:
            handlers[msgid] = self.metadata.on_message
        if self.origin is not None:
            handlers[MSG["GPS_GLOBAL_ORIGIN"]] = self.origin.on_gps_global_origin
        return handlers

    # -- lifetime ------------------------------------------------------------------------------------
    def start(self) -> Gateway:
        """Open the link (retried by :meth:`run` if it fails) and start the threads and bus endpoints."""
        if self._started:
            return self
        self._started = True
        self._thread(self.events.run, "events", self._stop)
        try:
            self.link.open()
        except MavlinkLinkError as exc:
            self.events.emit("link", f"cannot open the link yet: {exc}", 3)
        self._thread(self._read_loop, "mavlink")
        bus = self.bus
        if bus is not None:
            # Each pose is sent from the Zenoh thread that received it: no hand-off, no thread to wake.
            if self.own_vision:
                bus.subscribe(
                    keys.vision(self.name),
                    channel=Handler(self._on_vision, lambda e: self.health.failed("vision", e)),
                )
            sp_sub = bus.subscribe(keys.setpoint(self.name), capacity=4, ring=True)
            self._thread(self.forwarder.run, "setpoints", sp_sub, self._stop, self.health.failed)
            bus.subscribe(
                keys.FLEET, channel=Handler(self._on_fleet, lambda e: self.health.failed("fleet", e))
            )
            estop_sub = bus.subscribe(keys.ESTOP, capacity=16, ring=False)
            self._thread(self._estop_loop, "estop", estop_sub)
            bus.serve(keys.cmd(self.name), self.executor.handle, workers=2)
        if self.gcs is not None:
            self._thread(self._gcs_loop, "gcs")
        self.log.info(
            "gateway for %s: %s, system %d, we are %d/%d, %s",
            self.name,
            self.spec.mavlink,
            self.spec.system_id,
            self.spec.gateway_system_id,
            self.options.source_component,
            f"MAVLink 2 signing with key {self.signing.key.fingerprint}" if self.signing else "unsigned",
        )
        return self

    def _thread(self, target: Any, name: str, *args: Any) -> None:
        t = threading.Thread(target=target, args=args, name=f"gw-{self.name}-{name}", daemon=True)
        t.start()
        self._threads.append(t)

    def close(self) -> None:
        """Stop every thread and close the link (bus endpoints close with the bus)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self.events.close()
        self.link.close()
        if self.gcs is not None:
            self.gcs.close()

    def __enter__(self) -> Gateway:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- supervisor ----------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """The supervisor loop, in the caller's thread, until ``stop`` is set."""
        period = 1.0 / self.state_rate
        unwatched = max(period, 1.0 / self.options.unwatched_rate)
        idle = max(unwatched, 1.0 / self.options.idle_rate)
        now = time.monotonic()
        next_state, next_second = now, now
        while not stop.is_set() and not self._stop.is_set():
            now = time.monotonic()
            if now >= next_state:
                # A program reading the state gets it at its rate; nobody reading, the checks go on at
                # 10 Hz while armed and at 2 Hz while disarmed (a fleet on the ground costs next to nothing).
                step = period if self._state_watched() else unwatched if self.state.armed else idle
                next_state = max(next_state + step, now)
                self.publish_state(now)
            if now >= next_second:
                next_second = max(next_second + 1.0, now)
                self._every_second(now)
            self.state.supervise(now)
            self.linkwatch.supervise(now)
            if self.state.link:
                self.ev_delay.watch(now)
            stop.wait(max(0.0, min(next_state, next_second) - time.monotonic()))

    def _every_second(self, now: float) -> None:
        self.health.every_second()
        self.linkwatch.every_second()
        if self.timesync.rtt_s is not None:
            self._safe(self.telemetry.put, "timesync", self.timesync.fields(), wire.now_ns())

    def clock_problem(self) -> str | None:
        """Why pose times cannot be trusted on this host (arming is refused), or None."""
        return self.clock_watch.problem()

    def _mode_changed(self, old: str, new: str) -> None:
        if old == "OFFBOARD" and new != "OFFBOARD":
            self.forwarder.latch(f"the vehicle switched to {new}")

    def publish_state(self, now: float | None = None) -> wire.State:
        """Build (and publish, with a bus) the vehicle's :class:`~arena_common.core.wire.State` now."""
        msg = self.report.build(time.monotonic() if now is None else now)
        if self._state_pub is not None and self._state_pub.matching:  # nobody listening: nothing to send
            self._safe(self._state_pub.put, msg)
        return msg

    def _state_watched(self) -> bool:
        """Whether the state is read (always, without a bus: it is built for its caller)."""
        return self._state_pub is None or self._state_pub.matching

    def _safe(self, fn: Any, *args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:  # the bus is closing; never take the gateway down for it
            self.log.debug("not published: %s", exc)

    # -- threads -------------------------------------------------------------------------------------
    def _read_loop(self) -> None:
        link, handlers, tele, stats = self.link, self._handlers, self.telemetry, self.stats
        while not self._stop.is_set():
            try:
                frames = link.read(0.5)  # a frame wakes it at once; the timeout only sees _stop
            except Exception as exc:
                self.health.failed("mavlink", exc)
                self._stop.wait(0.05)
                continue
            if not frames:
                continue
            if self.gcs is not None:
                self.gcs.forward_to_gcs(frames)
            now, t_ns = time.monotonic(), wire.now_ns()
            stats.count("mav_in", len(frames))
            for frame in frames:
                handler = handlers.get(frame.msgid)
                due = tele.due(frame.msgid, now)
                if handler is None and not due:
                    continue
                msg = link.decode(frame)
                if msg is None:
                    continue
                if handler is not None:
                    try:
                        handler(msg, now)
                    except Exception as exc:  # a malformed message must not stop the link
                        self.health.failed(f"mavlink: handling {msg.get_type()}", exc)
                if due:
                    try:
                        tele.publish(msg, now, t_ns)
                    except Exception as exc:  # the bus is closing, or a field msgpack cannot carry
                        self.health.failed("telemetry", exc)

    def _on_vision(self, item: Received[Any]) -> None:
        if self._stop.is_set():
            return
        self.stats.count("in")
        pose = typed(item, wire.Pose, self.health.vision_reject)
        if pose is not None:
            self._send_vision(pose)

    def offer_vision(self, pose: wire.Pose) -> None:
        """Send ``pose`` to the autopilot as the vehicle's vision (what a host process serving several
        vehicles calls with each one's pose of a mocap frame, instead of the vehicle's own key)."""
        if self._stop.is_set():
            return
        self.stats.count("in")
        self._send_vision(pose)

    def _send_vision(self, pose: wire.Pose) -> None:
        reason = self.vision.offer(pose)
        if reason is None:
            self.stats.latency((wire.now_ns() - pose.t + self.vision.correction()) * 1e-9)
        else:
            self.stats.reject(f"vision: {reason}")

    def _on_fleet(self, item: Received[Any]) -> None:
        """Every vehicle's position (10 Hz): keep this one apart from the others while it flies (on the
        ground nothing is decoded: an idle fleet costs next to nothing)."""
        if self._stop.is_set() or self.state.flight_problem() is not None:
            return
        fleet = typed(item, wire.Fleet, self.health.fleet_reject)
        if fleet is not None:
            self.separation.update(fleet)
            commanded, travel_left = self.forwarder.course()
            closing = self.separation.closing(commanded=commanded, travel_left=travel_left)
            if closing is not None:
                self.forwarder.guard(closing, self.state.mode == "OFFBOARD")

    def _estop_loop(self, sub: Subscription) -> None:
        while not self._stop.is_set():
            item = sub.get(0.5)  # an estop wakes it at once; the timeout only sees _stop
            if item is None:
                continue
            e = typed(item, wire.Estop, self.health.estop_reject)
            if e is None:
                continue
            try:
                self.estop(e)
            except Exception as exc:  # the next estop must still work
                self.health.failed("estop", exc)

    def estop(self, e: wire.Estop) -> str:
        """Land (or kill the motors when ``e.kill``) at once; the autopilot's result."""
        self.forwarder.supersede(f"estop from {e.src or '?'}", src=e.src)
        self.forwarder.latch("estop")
        params: tuple[float, ...]
        if e.kill:
            cmd, params = px4.MAV_CMD_COMPONENT_ARM_DISARM, (0.0, float(px4.ARM_DISARM_FORCE_MAGIC))
        else:
            cmd, params = px4.MAV_CMD_NAV_LAND, (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, math.nan)
        self.commander.send(cmd, params)  # at once, even while another exchange of this command runs
        result = self.commander.command(cmd, params)
        what = "kill" if e.kill else "land"
        self.events.emit(
            "safety",
            f"estop ({e.reason or 'no reason'}) from {e.src or '?'}: {what} → {result}",
            1,
            result=result,
        )
        return result

    def _gcs_loop(self) -> None:
        gcs = self.gcs
        assert gcs is not None
        while not self._stop.is_set():
            try:
                gcs.open()
                break
            except MavlinkLinkError as exc:
                self.events.emit("link", f"ground station link: {exc}", 4, every=30.0)
                self._stop.wait(2.0)
        while not self._stop.is_set():
            gcs.pump(0.1)
