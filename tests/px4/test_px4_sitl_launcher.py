"""The launcher against the real build: boot parameters applied, PX4's own view readable, a reboot keeps
saved parameters, and nothing is left behind."""

from __future__ import annotations

from collections.abc import Callable

from arena_common.runtime.px4_sitl import Px4Sitl, instance_busy, is_true


def test_boot_listener_reboot_and_clean_stop(px4_sitl: Callable[..., Px4Sitl]) -> None:
    px4 = px4_sitl({"EKF2_EV_CTRL": 15, "EKF2_EVP_NOISE": 0.05})
    assert px4.boot_s is not None and px4.boot_s < 60 and instance_busy(px4.instance)
    assert px4.param("EKF2_EV_CTRL") == 15 and px4.param("EKF2_EVP_NOISE") == 0.05
    assert px4.param("EKF2_HGT_REF") == 1  # PX4's default where nothing was asked
    status = px4.listener("vehicle_status")
    assert status["system_id"] == px4.ports.system_id and status["arming_state"] == 1
    flags = px4.listener("estimator_status_flags")
    assert "cs_tilt_align" in flags and not is_true(flags, "cs_ev_pos")  # no vision reaches it
    # A value saved before a reboot survives it; boot parameters are applied again at each boot.
    assert px4.tool("param", "set", "MPC_XY_VEL_MAX", "3.5").returncode == 0
    assert px4.tool("param", "set", "EKF2_EVP_NOISE", "0.2").returncode == 0
    assert px4.tool("param", "save").returncode == 0
    px4.restart()
    assert px4.boots == 2 and px4.param("MPC_XY_VEL_MAX") == 3.5 and px4.param("EKF2_EVP_NOISE") == 0.05
    root = px4.workdir.parent
    px4.stop()
    assert not root.exists() and not instance_busy(px4.instance)
