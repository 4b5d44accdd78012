"""The simulated vehicle's land detector: when a vehicle on the floor counts as landed (``QuadSim.landed``).

PX4 disarms ``COM_DISARM_LAND`` after its land detector says landed, and ``land()`` returns then, so how
long the detector takes after touchdown is what a program waits for at the end of every flight.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from arena_common.sim.physics import ControlGains, RigidBody

__all__ = ["LandDetector"]

NAN = math.nan


class LandDetector:
    """PX4-like land detector: ground contact, low thrust and no vertical motion for a while → landed.

    ``staged`` (the simulation as PX4 flies, ``fidelity = "px4"``) goes through PX4 v1.16's three stages
    (``MulticopterLandDetector``), each held for ``LNDMC_TRIG_TIME`` / 3 (1 s in all): **ground contact** — a
    descent commanded (or no climb-rate control), no vertical motion beyond ``LNDMC_Z_VEL_MAX`` (0.25 m/s), no
    horizontal one beyond ``LNDMC_XY_VEL_MAX`` (1.5 m/s), and the thrust at most 60 % of the way from
    ``MPC_THR_MIN`` to the hover thrust (its estimate valid); **maybe landed** — the thrust within 10 % of that
    range above ``MPC_THR_MIN`` and no roll or pitch rate beyond ``LNDMC_ROT_MAX``; **landed**.  Once it sees
    ground contact in flight, PX4's position controller cuts the thrust and clears its integrators ("flying
    but ground contact"; :class:`QuadSim` does so too), which brings the two later stages at once.  So the
    time from touchdown to landed is mostly the vertical velocity loop's integrator winding the thrust down
    to the ground-contact threshold: PX4 SITL took 4.6–5.1 s from touchdown to landed in four flights
    (6.6–7.1 s to disarmed, ``COM_DISARM_LAND`` 2 s after), where a fixed 0.5 s had made the simulation's
    ``land()`` return 3–4 s early (docs/px4.md, the parity table).

    Unstaged (``fidelity = "ideal"``): on the ground, with low thrust and no vertical motion for
    :attr:`LAND_TIME`.
    """

    LAND_TIME = 0.5  # s of landed conditions before declaring landed (unstaged)
    TAKEOFF_TIME = 0.1  # s off the ground before declaring airborne
    TRIG_TIME = 1.0  # LNDMC_TRIG_TIME: the three stages' time in all (staged)
    Z_VEL_MAX = 0.25  # LNDMC_Z_VEL_MAX, m/s (x 2.5 once maybe landed)
    XY_VEL_MAX = 1.5  # LNDMC_XY_VEL_MAX, m/s
    ROT_MAX = math.radians(20.0)  # LNDMC_ROT_MAX (x 2.5 once maybe landed)
    LOW_THRUST = 0.6  # of the range MPC_THR_MIN → hover thrust: ground contact (hover estimate valid)
    MIN_THRUST = 0.1  # of that range: maybe landed
    MANUAL_MIN_THRUST = 0.09  # MPC_MANTHR_MIN + 0.01: maybe landed without climb-rate control

    def __init__(self, staged: bool = False) -> None:
        self.staged = staged
        self.landed = True
        # Staged: PX4's first two stages (at ground contact its position controller cuts the thrust).
        self.ground_contact = False
        self.maybe_landed = False
        self._timer = 0.0
        self._stage_timers = [0.0, 0.0, 0.0]

    def reset(self, landed: bool = True) -> None:
        """Force a state (boot, reboot)."""
        self.landed = landed
        self.ground_contact = self.maybe_landed = False
        self._timer = 0.0
        self._stage_timers = [0.0, 0.0, 0.0]

    def update(
        self,
        dt: float,
        body: RigidBody,
        throttle_sp: float,
        hover: float,
        motors_on: bool,
        gains: ControlGains,
        climb_rate_sp: float = NAN,
    ) -> bool:
        """Update with one tick; returns the landed state.  ``climb_rate_sp``: the vertical velocity
        commanded (down positive), NaN where the climb rate is not controlled (attitude and thrust given)."""
        if self.landed:
            if self._held(not body.on_ground, dt, self.TAKEOFF_TIME):
                self.reset(landed=False)
            return self.landed
        if self.staged and motors_on:
            self._stages(dt, body, throttle_sp, hover, gains, climb_rate_sp)
            return self.landed
        if not motors_on:
            cond_landed = body.on_ground
        else:
            cond_landed = body.on_ground and throttle_sp < 0.9 * hover and abs(body.velocity[2]) < 0.1
        if self._held(cond_landed, dt, self.LAND_TIME):
            self.reset(landed=True)
        return self.landed

    def _held(self, holds: bool, dt: float, needed: float) -> bool:
        """Advance the unstaged timer while ``holds`` (else restart it); whether it has held ``needed`` s."""
        self._timer = self._timer + dt if holds else 0.0
        return self._timer >= needed

    def _stages(
        self, dt: float, body: RigidBody, throttle: float, hover: float, gains: ControlGains, climb_sp: float
    ) -> None:
        widen = 2.5 if self.maybe_landed else 1.0
        span = hover - gains.thr_min
        controlled = climb_sp == climb_sp
        # Without climb-rate control PX4 asks for no descent, and its minimal thrust is MPC_MANTHR_MIN + 0.01.
        minimal = gains.thr_min + span * self.MIN_THRUST if controlled else self.MANUAL_MIN_THRUST
        contact = (
            (not controlled or climb_sp > 0.0)
            and abs(body.velocity[2]) <= self.Z_VEL_MAX * widen
            and math.hypot(body.velocity[0], body.velocity[1]) <= self.XY_VEL_MAX
            and throttle <= gains.thr_min + span * self.LOW_THRUST
        )
        still = math.hypot(body.rates[0], body.rates[1]) <= self.ROT_MAX * widen
        maybe = self.ground_contact and still and throttle <= minimal + 1e-9
        stage_time = self.TRIG_TIME / 3.0
        timers = self._stage_timers
        for i, holds in enumerate((contact, maybe, self.maybe_landed)):
            timers[i] = timers[i] + dt if holds else 0.0
        # PX4's hysteresis: a stage is entered once its condition has held for its time, left at once.
        self.ground_contact = timers[0] >= stage_time
        self.maybe_landed = timers[1] >= stage_time
        if timers[2] >= stage_time:
            self.reset(landed=True)
