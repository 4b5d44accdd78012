"""The Motive emulator's scene images each body where it truly is at mid-exposure, whenever its true
poses arrive: a simulation that stalls and catches up delivers a burst of poses at once, and a camera
system would have seen the vehicle move on smoothly meanwhile."""

from __future__ import annotations

from arena_common.geometry.filters import JumpGate, VelocityEstimator
from arena_common.sim.natnet_motive import TickClock
from arena_common.sim.natnet_scene import OFFSET_WINDOW, SampleClock, SimScene

SPEED = 0.7  # m/s north
TRUTH_HZ = 250
FRAME_HZ = 180
EPOCH = 500 * 10**9  # the truth's clock reads this much less than the scene's: another clock, same rate
TRANSIT_NS = 300_000
STALL_AT_NS, STALL_NS = 10**9, 200_000_000


def _arrival(t: int) -> int:
    """The truth of instant ``t`` (scene clock) arrives in transit, or at the stall's end if made during it."""
    if STALL_AT_NS <= t < STALL_AT_NS + STALL_NS:
        return STALL_AT_NS + STALL_NS + TRANSIT_NS
    return t + TRANSIT_NS


def _fly(stamped: bool) -> tuple[list[float], JumpGate, float]:
    """Frames of a vehicle flying north at SPEED for 1.9 s through a 0.2 s stall of its simulation: the
    error of each frame's position from the truth at mid-exposure, the jump gate after them, and the
    velocity estimate's worst error."""
    scene = SimScene(camera_latency=0.004, software_latency=0.001)
    scene.add_body("d1", 1)
    clock = TickClock()
    truths = sorted((round(i * 1e9 / TRUTH_HZ) for i in range(2 * TRUTH_HZ)), key=_arrival)
    gate, estimator = JumpGate(), VelocityEstimator()
    errors: list[float] = []
    worst_v, j = 0.0, 0
    for k in range(1, int(1.9 * FRAME_HZ)):
        now = round(k * 1e9 / FRAME_HZ) + 20_000_000
        while j < len(truths) and _arrival(truths[j]) <= now:
            t = truths[j]
            north = SPEED * t * 1e-9
            scene.update(
                "d1",
                (north, 0.0, -1.0),
                (1.0, 0.0, 0.0, 0.0),
                True,
                _arrival(t),
                stamp_ns=t - EPOCH if stamped else None,
                v_ned=(SPEED, 0.0, 0.0) if stamped else None,
            )
            j += 1
        frame = scene.frame(k, k / FRAME_HZ, now, clock)
        assert frame is not None
        rb = frame.rigid_bodies[0]
        assert rb.tracking_valid
        mid = now - 5_000_000
        errors.append(abs(rb.pos[0] - SPEED * mid * 1e-9))  # Motive x is arena north with no calibration
        if gate.check(mid, rb.pos, rb.quat_xyzw).accepted:
            v = estimator.update(mid, rb.pos, (1.0, 0.0, 0.0, 0.0))
            if v.valid:
                worst_v = max(worst_v, abs(v.linear_ned[0] - SPEED))
    return errors, gate, worst_v


def test_a_stalled_simulations_burst_of_true_poses_is_imaged_as_the_vehicle_flew() -> None:
    errors, gate, worst_v = _fly(stamped=True)
    # Behind by what the least-delayed pose spent in transit (0.3 ms at 0.7 m/s: 0.21 mm), never more.
    assert max(errors) < SPEED * TRANSIT_NS * 1e-9 + 1e-6, max(errors)
    assert sum(gate.rejected.values()) == 0 and gate.resets == 0
    assert worst_v < 1e-6, worst_v


def test_true_poses_placed_at_their_arrival_freeze_then_jump_as_the_stall_ends() -> None:
    """What the scene did before the poses carried their own time (kept to show what the rule is for)."""
    errors, _, worst_v = _fly(stamped=False)
    assert max(errors) > 0.1, max(errors)  # frozen for the stall: 0.14 m behind at its end
    assert worst_v > 2.0, worst_v  # a velocity estimate of several m/s out of a steady 0.7 m/s


def test_the_sample_clock_takes_the_least_delay_and_never_places_a_pose_after_its_arrival() -> None:
    clock = SampleClock()
    assert clock.place(1_000, 501_000) == 501_000  # the first: its delay is all the offset known
    assert clock.place(2_000, 502_400) == 502_000  # delayed 400 ns more than the first: placed earlier
    assert clock.place(3_000, 502_900) == 502_900  # less delayed than any before: the new offset
    assert clock.place(4_000, 504_400) == 503_900  # delayed 500 ns more than that one: placed earlier
    # A clock running fast (another host's skew): its stamps would land after the arrival; they do not.
    fast = SampleClock()
    fast.place(0, 0)
    assert fast.place(2_000_000, 1_000_000) == 1_000_000
    # The least delay is forgotten after OFFSET_WINDOW: a clock that stepped back 10 ms is followed again.
    window = round(OFFSET_WINDOW * 1e9)
    late = SampleClock()
    assert late.place(0, 10) == 10
    assert late.place(1_000, 1_001_010) == 1_010  # delayed 1 ms more than the first, within the window
    step = window + 10_000_000
    assert late.place(window + 100, step + 100) == step + 100  # the window has forgotten both
    assert late.place(window + 200, step + 600) == step + 200  # and this offset is the one kept
