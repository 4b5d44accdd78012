"""The PX4 SITL launcher, the truth bridge's conversion and the mixed sim/real planning, without a PX4 build.

A stand-in ``px4`` (a shell script printing what PX4 prints) exercises start, readiness, boot parameters,
stop and clean-up; the real-PX4 tier (``tests/px4``, ``make test-px4``) flies the real one.
"""

from __future__ import annotations

import math
import os
import stat
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from arena_common.bus import security
from arena_common.cli._deploy import DeployError, render_systemd
from arena_common.core import config as config_mod
from arena_common.geometry.frames import quat_from_yaw, quat_yaw
from arena_common.mavlink import px4
from arena_common.runtime import px4_sitl
from arena_common.runtime.options import read_config
from arena_common.runtime.px4_sitl import Px4Sitl, Px4SitlError
from arena_common.runtime.supervisor import plan, sim_world_plan
from services import sim_vehicle
from services.px4_truth import EARTH_RADIUS, Smoothed, TruthFrame, geodetic_to_ned

LISTENER_OUTPUT = """
TOPIC: estimator_status_flags
 estimator_status_flags
    timestamp: 4048000 (0.680000 seconds ago)
    timestamp_sample: 3896000 (152000 us before timestamp)
    control_status_changes: 10
    cs_tilt_align: True
    cs_ev_pos: False
    x: -0.03764
    ref_lat: nan
    vxy_max: inf
    delta_xy: [0.00000, -1.50000]
"""

FAKE_PX4 = """#!/bin/sh
echo "INFO  [px4] instance: $3 args: $*"
echo "INFO  [param] EKF2_EV_CTRL=$PX4_PARAM_EKF2_EV_CTRL EKF2_EVP_NOISE=$PX4_PARAM_EKF2_EVP_NOISE"
echo "INFO  [param] SDLOG_MODE=$PX4_PARAM_SDLOG_MODE model=$PX4_SIM_MODEL cwd=$(pwd)"
echo "INFO  [px4] Startup script returned successfully"
exec sleep 60
"""


@pytest.fixture
def fake_build(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A PX4 build whose helpers are flattened (3-byte text files), with a stand-in ``px4``."""
    build = tmp_path / "px4-sitl"
    (build / "bin").mkdir(parents=True)
    (build / "etc").mkdir()
    exe = build / "bin" / "px4"
    exe.write_text(FAKE_PX4)
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    (build / "bin" / "px4-listener").write_text("px4")  # flattened: not executable
    (build / "bin" / "px4-alias.sh").write_text("#!/bin/sh\n")
    (build / "bin" / "px4-param").symlink_to("px4")
    monkeypatch.setenv(px4_sitl.ENV_DIR, str(build))
    monkeypatch.setattr(px4_sitl, "LOCK_FILE", str(tmp_path / "px4_lock-{n}"))
    return build


def test_no_build_names_both_places(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(px4_sitl.ENV_DIR, str(tmp_path / "a"))
    monkeypatch.setattr(px4_sitl, "DEFAULT_DIR", tmp_path / "b")
    with pytest.raises(Px4SitlError) as err:
        px4_sitl.find_build()
    assert f"$PX4_SITL_DIR={tmp_path / 'a'}" in str(err.value) and str(tmp_path / "b") in str(err.value)
    assert px4_sitl.build_missing_reason() == str(err.value)
    monkeypatch.delenv(px4_sitl.ENV_DIR)
    with pytest.raises(Px4SitlError, match=r"\$PX4_SITL_DIR is not set"):
        px4_sitl.find_build()


def test_tool_links_point_flattened_helpers_at_px4(fake_build: Path, tmp_path: Path) -> None:
    d = px4_sitl.link_tools(fake_build, tmp_path / "links")
    px4_exe = fake_build / "bin" / "px4"
    assert os.readlink(d / "px4") == str(px4_exe)
    assert os.readlink(d / "px4-listener") == str(px4_exe)  # flattened → px4
    assert os.readlink(d / "px4-alias.sh") == str(fake_build / "bin" / "px4-alias.sh")  # kept
    assert os.readlink(d / "px4-param") == str(fake_build / "bin" / "px4-param")  # a real link, kept
    px4_sitl.link_tools(fake_build, tmp_path / "links")  # again: replaces, no error


def test_start_ready_boot_params_stop_and_clean_up(fake_build: Path) -> None:
    lines: list[str] = []
    sitl = Px4Sitl(2, params={"EKF2_EV_CTRL": 15.0, "EKF2_EVP_NOISE": 0.05}, output=lines.append)
    with sitl:
        root = sitl.workdir.parent
        assert sitl.alive and sitl.boot_s is not None and sitl.boot_s < 30 and sitl.boots == 1
        assert os.readlink(sitl.tools / "px4-listener") == str(fake_build / "bin" / "px4")
        text = "\n".join(sitl.lines)
        assert f"args: {fake_build / 'etc'} -i 2 -d -w {sitl.workdir}" in text
        assert "EKF2_EV_CTRL=15 EKF2_EVP_NOISE=0.05" in text  # integers without ".0" (INT32 parameters)
        assert f"SDLOG_MODE=-1 model=sihsim_quadx cwd={sitl.workdir}" in text
        assert lines == list(sitl.lines)
        sitl.restart()  # same working directory, a second boot
        assert sitl.workdir.parent == root and sitl.boots == 2 and sitl.alive
    assert not sitl.alive and sitl.returncode is not None and not root.exists()
    assert sitl.stop() == sitl.returncode  # idempotent


def test_an_exit_while_starting_is_an_error_with_its_lines(fake_build: Path) -> None:
    (fake_build / "bin" / "px4").write_text("#!/bin/sh\necho 'ERROR [px4] no way'\nexit 3\n")
    sitl = Px4Sitl(1)
    sitl.start()
    with pytest.raises(
        Px4SitlError, match=r"exited with status 3 while starting; last lines:\nERROR \[px4\] no way"
    ):
        sitl.wait_ready(10)
    sitl.stop()


def test_a_busy_instance_is_refused(fake_build: Path, tmp_path: Path) -> None:
    import fcntl

    lock = tmp_path / "px4_lock-4"
    with open(lock, "w") as f:
        assert not px4_sitl.instance_busy(4)
        fcntl.lockf(f, fcntl.LOCK_EX)  # as a running px4 holds it (another process sees it held)
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child reports through its exit status
            os._exit(0 if px4_sitl.instance_busy(4) else 1)
        assert os.waitpid(pid, 0)[1] == 0
    with pytest.raises(Px4SitlError, match="not a PX4 parameter name"):
        Px4Sitl(4, params={"ekf2_ev_ctrl": 1})


def test_parse_listener() -> None:
    [m] = px4_sitl.parse_listener(LISTENER_OUTPUT)
    assert m["timestamp"] == 4048000 and m["control_status_changes"] == 10
    assert m["cs_tilt_align"] is True and m["cs_ev_pos"] is False
    assert m["x"] == pytest.approx(-0.03764) and math.isnan(m["ref_lat"])  # type: ignore[arg-type]
    assert m["vxy_max"] == math.inf and m["delta_xy"] == [0.0, -1.5]
    assert px4_sitl.parse_listener("never published\n") == []
    assert px4_sitl.is_true(m, "cs_tilt_align") and not px4_sitl.is_true(m, "missing")
    assert px4_sitl.finite(m["x"]) and not px4_sitl.finite(m["ref_lat"]) and not px4_sitl.finite(True)


def test_sih_home_as_px4_holds_it() -> None:
    lat, lon, alt = px4_sitl.sih_home()
    assert lat == float(np.float32(47.397742)) and lon == float(np.float32(8.545594))
    assert alt == float(np.float32(489.4))
    assert px4_sitl.sih_home({"SIH_LOC_H0": 10.0}, {"PX4_HOME_LAT": "40.0"})[::2] == (40.0, 10.0)


def test_boot_parameter_presets() -> None:
    arena = px4_sitl.arena_boot_params("arena", {"EKF2_EVP_NOISE": 0.05})
    assert arena["EKF2_EV_CTRL"] == 15 and arena["EKF2_EVP_NOISE"] == 0.05
    assert set(px4.ARENA_REQUIRED_PARAMS) <= set(arena)
    assert px4_sitl.arena_boot_params("px4", {"EKF2_EV_CTRL": 15}) == {"EKF2_EV_CTRL": 15.0}
    with pytest.raises(Px4SitlError):
        px4_sitl.arena_boot_params("lab")
    assert px4_sitl.param_text(15.0) == "15" and px4_sitl.param_text(0.05) == "0.05"


# -- the truth bridge's conversion ---------------------------------------------------------------------


def test_geodetic_to_ned_small_offsets() -> None:
    home = (47.397742, 8.545594, 489.4)
    assert geodetic_to_ned(*home, home) == (0.0, 0.0, 0.0)
    n, e, d = geodetic_to_ned(home[0] + 1e-5, home[1], home[2] + 1.5, home)
    assert n == pytest.approx(math.radians(1e-5) * EARTH_RADIUS, abs=1e-6) and abs(e) < 1e-9 and d == -1.5
    n, e, _ = geodetic_to_ned(home[0], home[1] + 1e-5, home[2], home)
    assert e == pytest.approx(math.radians(1e-5) * EARTH_RADIUS * math.cos(math.radians(home[0])), rel=1e-6)
    assert abs(n) < 1e-6  # the curvature term: micrometres at this range
    one_cm = geodetic_to_ned(home[0] + 1e-7, home[1], home[2], home)[0]  # no cancellation at 1e-7°
    assert one_cm == pytest.approx(0.0111195, rel=1e-4)


def _msg(
    lat: float, lon: float, alt: float, q: tuple[float, ...], v: tuple[int, int, int]
) -> SimpleNamespace:
    return SimpleNamespace(
        lat=round(lat * 1e7), lon=round(lon * 1e7), alt=round(alt * 1e3), attitude_quaternion=list(q),
        vx=v[0], vy=v[1], vz=v[2], rollspeed=0.1, pitchspeed=0.0, yawspeed=-0.2,
    )  # fmt: skip


def test_truth_frame_places_and_turns_the_vehicle() -> None:
    home = (47.0, 8.0, 400.0)
    north_1m = 1.0 / EARTH_RADIUS * 180.0 / math.pi
    msg = _msg(home[0] + north_1m, home[1], home[2] + 2.0, (-1.0, 0.0, 0.0, 0.0), (100, 0, -50))
    plain = TruthFrame(home, (-1.0, 0.5)).pose(msg, 123)
    assert plain.t == 123 and plain.ok and plain.vok
    assert plain.p == pytest.approx((0.0, 0.5, -2.0), abs=0.01)  # 1 m north of its start, 2 m up
    assert plain.q == (1.0, 0.0, 0.0, 0.0)  # the sign PX4 sent (-1, 0, 0, 0) made canonical
    assert plain.v == pytest.approx((1.0, 0.0, -0.5)) and plain.w == pytest.approx((0.1, 0.0, -0.2))
    # SIH's north is the arena's east when the vehicle starts heading east (sim.yaw_deg = 90).
    turned = TruthFrame(home, (0.0, 0.0), math.pi / 2).pose(msg, 0)
    assert turned.p == pytest.approx((0.0, 1.0, -2.0), abs=0.01)
    assert turned.v == pytest.approx((0.0, 1.0, -0.5), abs=1e-9)
    assert quat_yaw(turned.q) == pytest.approx(math.pi / 2)
    yawed = TruthFrame(home, yaw=math.pi / 2).pose(_msg(*home, quat_from_yaw(0.3), (0, 0, 0)), 0)
    assert quat_yaw(yawed.q) == pytest.approx(0.3 + math.pi / 2)


# -- mixed sim / real planning ---------------------------------------------------------------------------

MIXED = """
[zenoh]
router_listen = ["tcp/127.0.0.1:7999"]
[hosts.ground]
services = ["router", "sim", "mocap", "transform"]
vehicles = ["s1", "p1", "x1"]
[hosts.companion]
vehicles = ["p2"]
vehicle_services = ["downsampler"]
[vehicles.s1]
mavlink = "udpin:127.0.0.1:14601"
system_id = 9
[vehicles.p1]
autopilot = "px4-sitl"
px4_instance = 0
[vehicles.p2]
autopilot = "px4-sitl"
px4_instance = 1
[vehicles.x1]
autopilot = "px4"
mavlink = "udpin:127.0.0.1:14602"
system_id = 20
"""


def _load(tmp_path: Path, text: str) -> config_mod.ArenaConfig:
    path = tmp_path / "arena.toml"
    path.write_text(textwrap.dedent(text))
    return read_config(path)


def test_plan_starts_px4_sitl_with_its_gateway_and_sim_only_for_sim_vehicles(tmp_path: Path) -> None:
    cfg = _load(tmp_path, MIXED)
    names = [s.name for s in plan(cfg, "ground", python="/py")]
    assert names == [
        "router", "sim-vehicle", "sim-motive", "mocap", "transform",
        "downsampler.s1", "gateway.s1",
        "px4-sitl.p1", "px4-truth.p1", "downsampler.p1", "gateway.p1",
        "downsampler.x1", "gateway.x1",
    ]  # fmt: skip
    spec = next(s for s in plan(cfg, "ground", python="/py") if s.name == "px4-truth.p1")
    assert spec.argv[:3] == ("/py", "-m", "services.px4_truth") and spec.argv[-2:] == ("--vehicle", "p1")
    # p2's gateway runs nowhere here: no PX4 SITL is started for it on the companion.
    assert [s.name for s in plan(cfg, "companion", python="/py")] == ["downsampler.p2"]
    assert sim_vehicle.select_vehicles(cfg) == ["s1"]
    with pytest.raises(config_mod.ConfigError, match=r"vehicles\.p1\.autopilot is 'px4-sitl': not simulated"):
        sim_vehicle.select_vehicles(cfg, ["p1"])
    # The truth of a PX4 SITL vehicle is published by the host of its gateway (and by the sim host).
    assert security.owners(cfg)["arena/p1/truth"] == {"ground"}


def test_the_motive_emulator_runs_alone_without_simulated_vehicles(tmp_path: Path) -> None:
    no_sim = MIXED.replace('["s1", "p1", "x1"]', '["p1", "x1"]')
    no_sim = no_sim.replace('[vehicles.s1]\nmavlink = "udpin:127.0.0.1:14601"\nsystem_id = 9\n', "")
    cfg = _load(tmp_path, no_sim)
    assert not any(v.simulated for v in cfg.vehicles.values())
    names = [s.name for s in plan(cfg, "ground", python="/py")]
    assert "sim-motive" in names and "sim-vehicle" not in names
    assert [s.name for s in sim_world_plan(cfg, "ground", python="/py")] == ["sim-motive"]
    with pytest.raises(config_mod.ConfigError, match='no vehicle has autopilot = "sim"'):
        sim_vehicle.select_vehicles(cfg)


def test_systemd_units_follow_the_autopilots(tmp_path: Path) -> None:
    no_sim = MIXED.replace('["s1", "p1", "x1"]', '["x1"]').replace(
        '[vehicles.s1]\nmavlink = "udpin:127.0.0.1:14601"\nsystem_id = 9\n', ""
    )
    units = render_systemd(_load(tmp_path, no_sim), "ground", workdir=tmp_path).files
    assert any(f.endswith("arena-sim-motive.service") for f in units)
    assert not any(f.endswith("arena-sim-vehicle.service") for f in units)  # it would find nothing to fly
    with pytest.raises(DeployError, match=r"serves autopilot = \"px4-sitl\" vehicles \(p1\)"):
        render_systemd(_load(tmp_path, MIXED), "ground", workdir=tmp_path)


def test_the_truths_quantised_position_is_smoothed_without_lag() -> None:
    """SIH's truth steps 1.1 cm north (1e-7°): a hover wandering across a step, and a flight at 0.8 m/s,
    through the bridge's smoothing at 100 Hz.  The steps shrink tenfold (what one frame of the transform's
    velocity estimate sees), and the smoothed position stays on the true one (no lag added)."""
    quantum, dt_ns = 0.0111195, 10_000_000
    for speed in (0.0, 0.8):
        smooth, before, worst_step, worst_error = Smoothed(), None, 0.0, 0.0
        for k in range(300):
            t = k * dt_ns * 1e-9
            true_n = 0.3 + speed * t + 0.05 * math.sin(2 * math.pi * 0.3 * t)
            true_v = speed + 0.05 * 2 * math.pi * 0.3 * math.cos(2 * math.pi * 0.3 * t)
            sample = (round(true_n / quantum) * quantum, 0.0, -1.0)
            p = smooth.update(k * dt_ns, sample, (round(true_v * 100) / 100, 0.0, 0.0))
            if before is not None and k > 50:
                worst_step = max(worst_step, abs(p[0] - before[0] - true_v * 0.01))
                worst_error = max(worst_error, abs(p[0] - true_n))
            before = p
        assert worst_step < 0.002, (speed, worst_step)  # a raw step: 0.0111 m
        assert worst_error < 0.008, (speed, worst_error)  # within the quantum itself
    # A jump (PX4 booted again) or a pause is not smoothed across.
    smooth = Smoothed()
    smooth.update(0, (0.0, 0.0, -1.0), (0.0, 0.0, 0.0))
    assert smooth.update(10_000_000, (1.0, 0.0, -1.0), (0.0, 0.0, 0.0)) == (1.0, 0.0, -1.0)
    assert smooth.update(500_000_000, (2.0, 0.0, -1.0), (0.0, 0.0, 0.0)) == (2.0, 0.0, -1.0)
