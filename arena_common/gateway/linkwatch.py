"""The supervision of one gateway's link to its autopilot (:class:`LinkWatch`).

Our HEARTBEAT (1 Hz) says MAV_TYPE_GCS: PX4 sends STATUSTEXT (its failsafe texts and the reasons it
refuses a command) only on links where it hears a ground station, and those texts become events.  To PX4
we are then a ground station: losing our heartbeat for COM_DL_LOSS_T triggers NAV_DLL_ACT (disabled by
default; the arena relies on the offboard-loss and position-loss failsafes, see ``docs/px4.md``).

The link is re-opened when it would not open (every second) or once the autopilot fell silent (every
``link_timeout`` s, while no HEARTBEAT comes back).  Whenever the link comes up and after an autopilot
reboot, the gateway asks the autopilot for its EKF origin and, only if it has none, gives it
the vehicle's ``origin`` ((0, 0, 0) by default) with SET_GPS_GLOBAL_ORIGIN, so that PX4 without GPS has
the global reference its AUTO modes need; an origin the EKF already has (GNSS) is never replaced, which
would re-base its local frame.  It also asks for ESTIMATOR_STATUS at ``estimator_rate`` (the published
state carries no position the autopilot marks invalid, nor one dead-reckoned without vision) and for the
vehicle's ``stream_rates``, and checks the arena's parameters (``check_at_start``) in a thread of its own.
"""

from __future__ import annotations

import threading
import time

from arena_common.gateway.events import EventSink
from arena_common.gateway.options import GatewayOptions
from arena_common.gateway.origin import GlobalOrigin
from arena_common.gateway.state import VehicleState
from arena_common.gateway.timesync import TimeSync
from arena_common.mavlink import px4
from arena_common.mavlink.link import MSG, MavlinkLink
from arena_common.mavlink.metadata import MetadataClient, MetadataError, reboot_required
from arena_common.mavlink.protocols import MavCommander, ParamClient, SetupChecker

__all__ = ["LinkWatch"]


class LinkWatch:
    """What the gateway does for its link as it comes and goes, from the supervisor's loop.

    It owns our HEARTBEAT and TIMESYNC probe (:meth:`every_second`), the re-opening of the link, what is
    asked of the autopilot whenever the link comes up or the autopilot reboots (the EKF origin, the message
    intervals, the parameter check: :attr:`setup`), and the names of the parameters that need a reboot
    (from the autopilot's own metadata, read once per boot).
    """

    def __init__(
        self,
        link: MavlinkLink,
        state: VehicleState,
        commander: MavCommander,
        params: ParamClient,
        metadata: MetadataClient,
        timesync: TimeSync,
        events: EventSink,
        *,
        name: str,
        origin: GlobalOrigin | None,
        options: GatewayOptions,
        stream_rates: dict[int, float],
    ) -> None:
        self.link = link
        self.state = state
        self.name = name  # the vehicle's
        self.options = options
        self.stream_rates = stream_rates  # the vehicle's stream_rates by message id (0 stops a stream)
        self.commander = commander
        self.metadata = metadata
        self.timesync = timesync
        self.origin = origin
        self.events = events
        self.setup = SetupChecker(params, events, reboot_required=self.reboot_required)
        self._reboot_names: frozenset[str] | None = None
        self._origin_wanted = False
        self._intervals_wanted = False
        self._check_wanted = False  # set when the link comes up (or the autopilot reboots)
        self._checking = threading.Lock()
        self._lost_since: float | None = None
        self._next_reopen = 0.0

    def every_second(self) -> None:
        """Our HEARTBEAT (as a ground station) and our TIMESYNC probe."""
        self.link.send(
            self.link.mav.heartbeat_encode(
                px4.MAV_TYPE_GCS, px4.MAV_AUTOPILOT_INVALID, 0, 0, px4.MAV_STATE_ACTIVE
            )
        )
        self.timesync.request()

    def supervise(self, now: float) -> None:
        """Re-open a lost link; once it is up, ask the autopilot what is wanted (the supervisor calls it)."""
        link, state = self.link, self.state
        if not link.is_open:
            if now >= self._next_reopen:
                self._next_reopen = now + 1.0
                if link.reopen():
                    self.events.emit("link", f"link {link.url} open", 6)
            return
        if state.link:
            self._lost_since = None
        elif state.hb_count and self._lost_since is None:
            self._lost_since = now
            self._next_reopen = now
        if self._lost_since is not None and now >= self._next_reopen:
            self._next_reopen = now + self.options.link_timeout
            ok = link.reopen()
            self.events.emit("link", f"re-opening {link.url}: {'ok' if ok else 'failed'}", 5, every=10.0)
        if not state.link:
            return
        if self.origin is not None:
            if self._origin_wanted:
                self._origin_wanted = False
                self.origin.request(now)
            else:
                self.origin.supervise(now)
        if self._intervals_wanted:
            self._intervals_wanted = False
            self._ask_intervals()
        if self._check_wanted and not self._checking.locked():
            self._check_wanted = False
            threading.Thread(target=self._background_check, name=f"gw-{self.name}-check", daemon=True).start()

    def _ask_intervals(self) -> None:
        """ESTIMATOR_STATUS at ``estimator_rate``, and the vehicle's ``stream_rates``."""
        interval = px4.MAV_CMD_SET_MESSAGE_INTERVAL
        if self.options.estimator_rate > 0:
            self.commander.send(interval, (MSG["ESTIMATOR_STATUS"], 1e6 / self.options.estimator_rate))
        for msgid, hz in self.stream_rates.items():
            self.commander.send(interval, (msgid, 1e6 / hz if hz > 0 else -1.0))

    def _background_check(self) -> None:
        with self._checking:
            report = self.setup.check(time.monotonic() + 5.0)
            if not report.get("complete"):
                self._check_wanted = True  # nothing answered: try again later

    def link_changed(self, up: bool) -> None:
        """The autopilot's HEARTBEAT came (``up``) or stopped (:attr:`VehicleState.on_link_change`)."""
        if up:
            self._origin_wanted = True
            self._intervals_wanted = True
            if self.options.check_at_start:
                self._check_wanted = True

    def rebooted(self) -> None:
        """The autopilot rebooted (:attr:`VehicleState.on_reboot`): it forgot what it was given."""
        self._origin_wanted = True
        self._intervals_wanted = True
        self.timesync.reset()
        self._reboot_names = None  # it may be another firmware now
        self.setup.rebooted()
        if self.options.check_at_start:
            self._check_wanted = True

    def reboot_required(self, deadline: float) -> frozenset[str] | None:
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
