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
  disarmed; raw telemetry is published
  while anyone subscribes, per message type), our HEARTBEAT
  at 1 Hz, our TIMESYNC probe at 1 Hz, link-loss detection (no HEARTBEAT for 3 s) and re-opening the
  link, the arena parameter check when the link comes up.

We speak as ``source_system`` (245 by default: not QGroundControl's 255) and component
MAV_COMP_ID_ONBOARD_COMPUTER (191), and always address the configured ``system_id``, never 0.

When the vehicle's config names a ``signing_key_file``, the link uses MAVLink 2 signing
(:mod:`arena_common.mavlink.signing`): everything we send is signed (link id 0), and every frame of the vehicle
must be signed with the same key and carry a fresh timestamp, except RADIO_STATUS; refused frames are
counted as rejects (``mavlink: unsigned``, ``mavlink: bad signature``, ``mavlink: replayed``…) and
reported in a ``link`` event (``data.signing``: the reasons) at most every 10 s.  Frames forwarded from a
ground station go out as they are.

Our HEARTBEAT says MAV_TYPE_GCS: PX4 sends STATUSTEXT (its failsafe texts and the reasons it refuses a
command) only on links where it hears a ground station, and those texts become events.  To PX4 we are
then a ground station: losing our heartbeat for COM_DL_LOSS_T triggers NAV_DLL_ACT (disabled by default;
the arena relies on the offboard-loss and position-loss failsafes, see ``docs/px4.md``).

Whenever the link comes up and after an autopilot reboot, the gateway asks the autopilot for its EKF
origin and, only if it has none, gives it ``GatewayOptions.origin`` ((0, 0, 0) by default) with
SET_GPS_GLOBAL_ORIGIN, so that PX4 without GPS has the global reference its AUTO modes need; an origin
the EKF already has (GNSS) is never replaced, which would re-base its local frame.  It also asks for
ESTIMATOR_STATUS at ``estimator_rate``: the published state carries no position the autopilot marks
invalid, nor one dead-reckoned without vision (``fs``: ``position_invalid``, ``dead_reckoning``).

Given the process's :class:`~arena_common.runtime.clock.ClockSync` (``clock``), pose times — on the mocap
host's clock — are corrected by this host's measured offset before their age is judged and ODOMETRY is
stamped; arming is refused while that offset is unknown or too uncertain (the reason names the clock),
an offset beyond ``clock.max_offset`` raises a ``clock`` event naming the fix (chrony), and the state's
``fs`` says ``clock_unknown``, ``clock_uncertain``, ``clock_offset`` or ``clock_unchecked`` (no
reference on the bus, ``clock.require`` false).
"""

from __future__ import annotations

import collections
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
from arena_common.gateway.events import EventSink
from arena_common.gateway.options import GatewayOptions, stream_ids
from arena_common.gateway.origin import GlobalOrigin
from arena_common.gateway.separation import Separation
from arena_common.gateway.setpoints import SetpointForwarder
from arena_common.gateway.state import VehicleState
from arena_common.gateway.telemetry import TelemetryPublisher
from arena_common.gateway.timesync import TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.mavlink import px4
from arena_common.mavlink.link import MSG, Frame, GcsForwarder, MavlinkLink, MavlinkLinkError, mavlink2
from arena_common.mavlink.metadata import HANDLED_MESSAGES, MetadataClient, MetadataError, reboot_required
from arena_common.mavlink.protocols import MavCommander, ParamClient, SetupChecker
from arena_common.mavlink.signing import GATEWAY_UNSIGNED, LinkSigning, vehicle_key
from arena_common.runtime.clock import ClockSync
from arena_common.runtime.service import Stats

__all__ = ["Gateway", "GatewayOptions"]

MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MSG_ESTIMATOR_STATUS = 230


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
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.spec = v = cfg.vehicle(vehicle)
        self.name = v.name
        self.bus = bus
        self.options = o = options or GatewayOptions()
        self.state_rate = v.state_rate if o.state_rate is None else o.state_rate
        self.telemetry_rate = v.telemetry_rate if o.telemetry_rate is None else o.telemetry_rate
        self.stats = stats or Stats()
        self.log = log or logging.getLogger(f"arena.gateway.{v.name}")
        self._stream_rates = stream_ids(cfg, v.name)  # before opening anything: a bad name is a config error
        key = vehicle_key(cfg, v.name)  # SigningError (a ConfigError) for a bad key file
        self.signing = LinkSigning(key, allow_unsigned=GATEWAY_UNSIGNED) if key is not None else None
        self.link = MavlinkLink(
            v.mavlink,
            v.system_id,
            source_system=o.source_system,
            source_component=o.source_component,
            signing=self.signing,
            on_reject=self._rejected,
            peer=v.mavlink_peer or None,
        )
        self._rejects: collections.Counter[tuple[str, str, int]] = collections.Counter()
        self._rejects_report = 0.0
        self._event_pub = bus.command_publisher(keys.events(v.name), wire.Event) if bus is not None else None
        self.events = EventSink(self._event_pub.put if self._event_pub is not None else None, self.log)
        self.clock_watch = ClockWatch(clock, cfg.clock, self.events)
        self.state = VehicleState(v.system_id, self.events, o.link_timeout)
        self.origin = (
            GlobalOrigin(self.link, v.system_id, o.origin, self.events) if o.origin is not None else None
        )
        self._origin_wanted = False
        self.timesync = TimeSync(self.link)
        self.vision = VisionSender(
            self.link,
            max_pose_age=v.max_pose_age,
            message=v.vision_message,
            send_velocity=o.send_velocity,
            stats=self.stats,
            offset_ns=clock.offset_ns if clock is not None else None,
            source=keys.vision(v.name),
        )
        self.commander, self.params, self.metadata, self.setup = self._protocols()
        self._reboot_names: frozenset[str] | None = None
        self.separation = Separation(self.name, self.cfg.arena.min_separation)
        self.forwarder = self._setpoint_forwarder()
        self.executor = self._command_executor()
        self.telemetry = TelemetryPublisher(bus, v.name, self.telemetry_rate, exclude=(MSG["TIMESYNC"],))
        gcs_url = o.gcs if o.gcs is not None else v.gcs
        self.gcs = GcsForwarder(gcs_url, self.link, allow_manual=o.allow_gcs_manual) if gcs_url else None
        self.state.on_mode_change.append(self._mode_changed)
        self.state.on_reboot.append(self._rebooted)
        self.state.on_link_change.append(self._link_changed)
        self._handlers = self._message_handlers()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._state_pub = (
            bus.stream_publisher(keys.state(v.name), wire.State, Lane.REPORT) if bus is not None else None
        )
        self._check_wanted = False  # set when the link comes up (or the autopilot reboots)
        self._checking = threading.Lock()
        self._lost_since: float | None = None
        self._next_reopen = 0.0
        self._started = False
        self._failures: set[tuple[str, str]] = set()
        self._link_counts: dict[str, int] = {}
        self._intervals_wanted = False
        self._position_problem: str | None = None

    def _protocols(self) -> tuple[MavCommander, ParamClient, MetadataClient, SetupChecker]:
        """The MAVLink exchanges with the autopilot: commands, parameters, its metadata, the setup check."""
        v, o = self.spec, self.options
        commander = MavCommander(self.link, v.system_id, ack_timeout=o.ack_timeout, attempts=o.attempts)
        params = ParamClient(self.link, v.system_id, timeout=o.ack_timeout, attempts=o.attempts)
        # The autopilot's own parameter metadata (COMPONENT_METADATA + MAVLink FTP): which parameters need
        # a reboot.  Never reset an FTP session: a ground station may be using it through the forwarder.
        metadata = MetadataClient(self.link, v.system_id, reset_busy=False)
        setup = SetupChecker(params, self.events, reboot_required=self._reboot_required)
        return commander, params, metadata, setup

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
            bus.subscribe(
                keys.vision(self.name), channel=Handler(self._on_vision, lambda e: self._failed("vision", e))
            )
            sp_sub = bus.subscribe(keys.setpoint(self.name), capacity=4, ring=True)
            self._thread(self.forwarder.run, "setpoints", sp_sub, self._stop, self._failed)
            bus.subscribe(keys.FLEET, channel=Handler(self._on_fleet, lambda e: self._failed("fleet", e)))
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
            self.options.source_system,
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
            self._supervise_link(now)
            stop.wait(max(0.0, min(next_state, next_second) - time.monotonic()))

    def _every_second(self, now: float) -> None:
        self._count_link_rejects()
        self.clock_watch.check()
        self.link.send(
            self.link.mav.heartbeat_encode(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, px4.MAV_STATE_ACTIVE)
        )
        self.timesync.request()
        if self.timesync.rtt_s is not None:
            self._safe(self.telemetry.put, "timesync", self.timesync.fields(), wire.now_ns())

    def clock_problem(self) -> str | None:
        """Why pose times cannot be trusted on this host (arming is refused), or None."""
        return self.clock_watch.problem()

    def _count_link_rejects(self) -> None:
        """Publish what the link dropped since the last call as rejects with a reason."""
        link = self.link
        totals = {
            "mavlink: foreign system": link.foreign,
            "mavlink: bad crc": link.bad_crc,
            "mavlink: unchecked frame": link.unchecked,
            "mavlink: undecodable": link.decode_errors,
            "mavlink: cannot pack": link.pack_errors,
            "mavlink: wrong source": link.wrong_source,
        }
        if link.wrong_source > self._link_counts.get("mavlink: wrong source", 0):
            self.events.emit(
                "link",
                f"frames from {link.last_wrong_source} dropped: the link is pinned to {self.spec.mavlink_peer}",
                4,
                every=10.0,
            )
        for reason, total in totals.items():
            self.stats.reject(reason, total - self._link_counts.get(reason, 0))
            self._link_counts[reason] = total
        garbage = link.garbage - self._link_counts.get("garbage", 0)
        self._link_counts["garbage"] = link.garbage
        if garbage > 0:
            self.stats.count("mavlink_garbage_bytes", garbage)
            self.stats.reject("mavlink: garbage")

    def _failed(self, what: str, exc: BaseException) -> None:
        """One sample made a loop fail: count it, log the first of each kind, and go on."""
        self.stats.reject(f"{what}: error")
        key = (what, type(exc).__name__)
        if key not in self._failures:
            self._failures.add(key)
            self.log.error(
                "%s: %s: %s (counted as '%s: error'; going on)", what, key[1], exc, what, exc_info=exc
            )

    def _supervise_link(self, now: float) -> None:
        if not self.link.is_open:
            if now >= self._next_reopen:
                self._next_reopen = now + 1.0
                if self.link.reopen():
                    self.events.emit("link", f"link {self.spec.mavlink} open", 6)
            return
        if self.state.link:
            self._lost_since = None
        elif self.state.hb_count and self._lost_since is None:
            self._lost_since = now
            self._next_reopen = now
        if self._lost_since is not None and now >= self._next_reopen:
            self._next_reopen = now + self.options.link_timeout
            ok = self.link.reopen()
            self.events.emit(
                "link", f"re-opening {self.spec.mavlink}: {'ok' if ok else 'failed'}", 5, every=10.0
            )
        if self.origin is not None and self.state.link:
            if self._origin_wanted:
                self._origin_wanted = False
                self.origin.request(now)
            else:
                self.origin.supervise(now)
        if self._intervals_wanted and self.state.link:
            self._intervals_wanted = False
            if self.options.estimator_rate > 0:
                interval_us = 1e6 / self.options.estimator_rate
                self.commander.send(px4.MAV_CMD_SET_MESSAGE_INTERVAL, (MSG_ESTIMATOR_STATUS, interval_us))
            for msgid, hz in self._stream_rates.items():  # the vehicle's stream_rates: 0 stops the stream
                self.commander.send(px4.MAV_CMD_SET_MESSAGE_INTERVAL, (msgid, 1e6 / hz if hz > 0 else -1.0))
        if self._check_wanted and self.state.link and not self._checking.locked():
            self._check_wanted = False
            threading.Thread(target=self._background_check, name=f"gw-{self.name}-check", daemon=True).start()

    def _background_check(self) -> None:
        with self._checking:
            report = self.setup.check(time.monotonic() + 5.0)
            if not report.get("complete"):
                self._check_wanted = True  # nothing answered: try again later

    def _link_changed(self, up: bool) -> None:
        if up:
            self._origin_wanted = True
            self._intervals_wanted = True
        if up and self.options.check_at_start:
            self._check_wanted = True

    def _rebooted(self) -> None:
        self._origin_wanted = True
        self._intervals_wanted = True
        self.timesync.reset()
        self._reboot_names = None  # it may be another firmware now
        self.setup.rebooted()
        if self.options.check_at_start:
            self._check_wanted = True

    def _reboot_required(self, deadline: float) -> frozenset[str] | None:
        """Names of the autopilot's parameters that need a reboot, from its own metadata (None: unknown)."""
        if self._reboot_names is None:
            try:
                self._reboot_names = reboot_required(
                    self.metadata.fetch(min(deadline, time.monotonic() + 10.0))
                )
            except MetadataError as exc:
                self.events.emit(
                    "setup",
                    f"no parameter metadata from the autopilot ({exc}): every parameter written is taken "
                    "to need a reboot",
                    5,
                )
                return None
        return self._reboot_names

    def _rejected(self, reason: str, frame: Frame) -> None:
        """A frame of the vehicle failed the signature check (reader thread)."""
        self.stats.reject(f"mavlink: {reason}")
        spec = mavlink2.mavlink_map.get(frame.msgid)
        self._rejects[(reason, spec.msgname if spec is not None else str(frame.msgid), frame.compid)] += 1
        now = time.monotonic()
        if now < self._rejects_report:
            return
        self._rejects_report = now + 10.0
        total = sum(self._rejects.values())
        reasons: dict[str, int] = {}
        for (r, _, _), n in self._rejects.items():
            reasons[r] = reasons.get(r, 0) + n
        detail = ", ".join(
            f"{r} {name} (component {c}) ×{n}" for (r, name, c), n in self._rejects.most_common(4)
        )
        self._rejects.clear()
        fingerprint = self.signing.key.fingerprint if self.signing is not None else "?"
        self.events.emit(
            "link",
            f"signing: dropped {total} frame(s) of system {self.spec.system_id}: {detail}; the vehicle must "
            f"sign with the key {fingerprint} (PX4: MAV_SIGN_CFG and its key)",
            4,
            dropped=total,
            signing=reasons,
        )

    def _mode_changed(self, old: str, new: str) -> None:
        if old == "OFFBOARD" and new != "OFFBOARD":
            self.forwarder.latch(f"the vehicle switched to {new}")

    def publish_state(self, now: float | None = None) -> wire.State:
        """Build (and publish, with a bus) the vehicle's :class:`~arena_common.core.wire.State` now."""
        now = time.monotonic() if now is None else now
        s, vis = self.state, self.vision
        t = wire.now_ns()
        p = s.position(now, max_age=1.0)
        vis_age = vis.age(now)
        mp = vis.last_p if vis.sent else None
        fused = (
            p is not None
            and mp is not None
            and vis_age is not None
            and vis_age < 0.3
            and now - s.p_time < 0.3
            and math.dist(p, mp) <= self.options.fused_tolerance
        )
        flags = s.flags(now)
        problem = s.estimate_problem(now)
        if vis_age is None or vis_age > px4.EV_TIMEOUT_S:
            flags.append("vision_stale")
            if p is not None and problem is None:
                problem = "no vision reaching the autopilot: its position is dead-reckoned"
                flags.append("dead_reckoning")
        if problem is not None and "dead_reckoning" not in flags:
            flags.append("position_invalid")
        if problem != self._position_problem:
            self._position_problem = problem
            if problem is not None:
                self.events.emit("estimator", f"position not valid: {problem}", 3, reason=problem)
            else:
                self.events.emit("estimator", "position valid again", 6)
        if self.forwarder.latched is not None and s.mode != "OFFBOARD":
            flags.append("offboard_latched")
        flags += self.clock_watch.flags()
        valid = p is not None and problem is None
        bat = s.bat
        msg = wire.State(
            t=t,
            sysid=self.spec.system_id,
            link=s.link,
            armed=s.armed,
            mode=s.mode,
            landed=s.landed,
            p=p if p is not None and valid and all(math.isfinite(c) for c in p) else None,
            v=s.v if valid and s.v is not None and all(math.isfinite(c) for c in s.v) else None,
            q=s.q,
            mp=mp,
            bat=None if bat is None else min(1.0, max(0.0, bat)),
            volt=s.volt,
            rtt=self.timesync.rtt_s,
            hb_age=s.hb_age(now),
            vis_rate=vis.rate(now),
            vis_age=vis_age,
            vis_fused=fused,
            ofb=self.forwarder.streaming(now),
            setup_ok=bool(self.setup.ok) and not self.setup.reboot_pending,
            fs=tuple(flags),
            tp=t,
            auth=self.forwarder.holder,
        )
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
                self._failed("mavlink", exc)
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
                        self._failed(f"mavlink: handling {msg.get_type()}", exc)
                if due:
                    try:
                        tele.publish(msg, now, t_ns)
                    except Exception as exc:  # the bus is closing, or a field msgpack cannot carry
                        self._failed("telemetry", exc)

    def _on_vision(self, item: Received[Any]) -> None:
        if self._stop.is_set():
            return
        self.stats.count("in")
        pose = typed(item, wire.Pose, self._vision_reject)
        if pose is None:
            return
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
        fleet = typed(item, wire.Fleet, lambda kind, detail: self.stats.reject(f"fleet: {kind}"))
        if fleet is not None:
            self.separation.update(fleet)
            commanded, travel_left = self.forwarder.course()
            closing = self.separation.closing(commanded=commanded, travel_left=travel_left)
            if closing is not None:
                self.forwarder.guard(closing, self.state.mode == "OFFBOARD")

    def _vision_reject(self, kind: str, detail: str) -> None:
        reason = "undecodable" if kind == "bad_payload" else "not a Pose"
        self.vision.refused(reason)
        self.stats.reject(f"vision: {reason}")

    def _estop_reject(self, kind: str, detail: str) -> None:
        self.stats.reject("estop: undecodable" if kind == "bad_payload" else "estop: not an Estop")

    def _estop_loop(self, sub: Subscription) -> None:
        while not self._stop.is_set():
            item = sub.get(0.5)  # an estop wakes it at once; the timeout only sees _stop
            if item is None:
                continue
            e = typed(item, wire.Estop, self._estop_reject)
            if e is None:
                continue
            try:
                self.estop(e)
            except Exception as exc:  # the next estop must still work
                self._failed("estop", exc)

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
