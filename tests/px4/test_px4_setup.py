"""``arena px4 check`` / ``arena px4 setup`` on a real PX4 v1.16 (SITL, SIH) booted with PX4's defaults.

With its defaults PX4 flies on (SIH's simulated) GNSS and magnetometer and ignores vision.  ``check``
lists what differs; ``setup`` writes it, learns from PX4's own metadata that some of it (EKF2_HGT_REF…)
needs a reboot, and asks for one — PX4 SITL answers the MAVLink reboot command DENIED, so setup answers
FAILED naming the reboot, and the gateway refuses to arm until the autopilot rebooted.  Then the
"power-cycle" (PX4 booted again with its saved parameters): the gateway notices, checks again, vision is
fused with the yaw aligned, the local position is where the vehicle truly is (no jump), and it flies.
The gateway never replaces the EKF origin PX4 had from GNSS; after the reboot (no GNSS) it gives one.
"""

from __future__ import annotations

import math
import time

import pytest
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.core import wire
from arena_common.core.errors import SafetyRefused
from arena_common.mavlink import px4 as px4_params
from arena_common.mavlink.metadata import load_parameters_json, reboot_required
from arena_common.runtime.px4_sitl import find_build, is_true
from tests.conftest import wait_for
from tests.px4.conftest import PX4ArenaFactory
from tests.px4.harness import FlightRecord

SIH_HOME_LAT = 47.397742  # PX4 SITL's default home (PX4_HOME_LAT), where SIH's GNSS puts the EKF origin


def test_setup_on_px4_defaults_reboot_then_fly(px4_arena: PX4ArenaFactory) -> None:
    stack, arena = px4_arena(("d1",), preset="px4")
    px4 = stack.px4["d1"]
    d1 = arena.vehicle("d1")
    record = FlightRecord(arena, "d1")
    cfg = str(stack.cfg.path)
    runner = CliRunner()
    t0 = wire.now_ns()

    # PX4's defaults: GNSS-referenced EKF, vision ignored.
    assert px4.param("EKF2_EV_CTRL") == 0 and px4.param("EKF2_GPS_CTRL") == 7, "not PX4's defaults"
    origin = wait_for(
        lambda: [e.text for e in d1.events() if e.kind == "setup" and "EKF origin" in e.text],
        timeout=20,
        interval=0.2,
        what="the gateway asking PX4 for its EKF origin",
    )
    local = {k: v for k, v in px4.listener("vehicle_local_position").items() if isinstance(v, (int, float))}
    assert abs(local["ref_lat"] - SIH_HOME_LAT) < 1e-3, local  # GNSS origin, not replaced by ours
    assert "left as it is" in origin[0], origin

    check = runner.invoke(app, ["px4", "check", "d1", "-c", cfg])
    differs = [line.split()[0] for line in check.output.splitlines() if line.rstrip().endswith("DIFFERS")]
    assert check.exit_code == 1, check.output
    assert {"EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_GPS_CTRL", "EKF2_NOAID_TOUT"} <= set(differs), check.output

    setup = runner.invoke(app, ["px4", "setup", "d1", "-c", cfg])
    print(f"\n$ arena px4 setup d1\n{setup.output}")
    assert setup.exit_code == 1, setup.output  # SITL refuses the MAVLink reboot: FAILED, naming it
    assert "setup FAILED" in setup.output and "reboot" in setup.output, setup.output
    # Named for the reboot: exactly the written ones the build's own metadata marks rebootRequired.
    reboot_line = setup.output.split(" take effect only after a reboot")[0].splitlines()[-1]
    metadata = load_parameters_json(find_build() / "parameters.json")
    expected = reboot_required(metadata).intersection(differs)
    assert {"EKF2_HGT_REF", "EKF2_MAG_TYPE"} <= expected, expected
    assert set(reboot_line.split(", ")) == expected, (reboot_line, expected)
    for name, (want, _) in px4_params.ARENA_REQUIRED_PARAMS.items():  # every value written, as PX4 says
        have = px4.param(name)
        assert have is not None and math.isclose(have, float(want), rel_tol=1e-6), (name, have, want)

    with pytest.raises(SafetyRefused) as refused:
        d1.arm()
    assert "reboot" in str(refused.value), refused.value
    assert px4.listener("vehicle_status")["arming_state"] == 1
    state = d1.state
    assert state is not None
    setup_ok_before_reboot = state.setup_ok

    # The power-cycle: PX4 boots again from its saved parameters.
    before = record.latest_truth()
    boot = px4.restart()
    rebooted = wait_for(
        lambda: [e for e in d1.events() if e.t >= t0 and "rebooted" in e.text],
        timeout=30,
        interval=0.2,
        what="the gateway noticing the reboot",
    )
    wait_for(
        lambda: d1.link and (s := d1.state) is not None and s.setup_ok and s.vis_fused,
        timeout=60,
        interval=0.2,
        what="setup verified and vision fused after the reboot",
    )
    flags = wait_for(
        lambda: (
            (f := px4.listener("estimator_status_flags"))
            and all(is_true(f, k) for k in ("cs_ev_pos", "cs_ev_hgt", "cs_ev_yaw", "cs_yaw_align"))
            and f
        ),
        timeout=30,
        interval=0.5,
        what="PX4 fusing vision with its yaw aligned",
    )
    assert not is_true(flags, "cs_gnss_pos") and not is_true(flags, "cs_mag_hdg"), flags
    wait_for(
        lambda: is_true(px4.listener("vehicle_status"), "pre_flight_checks_pass"),
        timeout=30,
        interval=0.5,
        what="PX4's pre-flight checks to pass",
    )
    time.sleep(1.0)
    truth, state = record.latest_truth(), d1.state
    assert truth is not None and state is not None and state.p is not None, state
    jump = math.dist(state.p, truth.p)
    given = [e.text for e in d1.events() if e.t >= rebooted[0].t and "EKF origin" in e.text]
    print(
        f"PX4 booted again in {boot:.2f} s; {rebooted[0].text}; then {given}; its estimate "
        f"{tuple(round(x, 3) for x in state.p)} vs truth {tuple(round(x, 3) for x in truth.p)}: "
        f"{jump * 100:.1f} cm apart (before setup, PX4's GNSS frame put it at "
        f"{tuple(round(local[k], 2) for k in ('x', 'y', 'z'))}, truly at "
        f"{tuple(round(x, 2) for x in before.p) if before else '?'}); state.setup_ok while the reboot was "
        f"pending: {setup_ok_before_reboot}"
    )
    assert jump < 0.1, (state.p, truth.p)  # the local position is the arena's, where the vehicle is
    assert any("EKF origin set" in g for g in given), given  # no GNSS any more: the gateway gives one

    d1.arm()
    assert px4.listener("vehicle_status")["arming_state"] == 2
    d1.takeoff(0.5, timeout=60)
    flown = record.latest_truth()
    d1.land(timeout=60)
    assert flown is not None
    assert -0.75 < flown.p[2] < -0.3, flown.p
    assert px4.listener("vehicle_status")["arming_state"] == 1
    assert not stack.dead(), stack.dead()
    assert not setup_ok_before_reboot  # not "set up" while what it wrote waits for a reboot
