"""`arena px4 check|setup <drone>` through a running gateway, and the gateway's command line."""

from __future__ import annotations

from collections.abc import Callable

from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.core.vehiclespec import VehicleSpec
from arena_common.mavlink import px4
from services.mavlink_gateway import FLAGS, overridden
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)

runner = CliRunner()


def test_px4_check_then_setup_print_tables(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(params=None)
    cfg_path = rig.cfg.path
    res = runner.invoke(app, ["px4", "check", "d1", "-c", cfg_path])
    assert res.exit_code == 1, res.output
    lines = res.output.splitlines()
    assert lines[0].split() == ["parameter", "type", "want", "have", "status"]
    row = next(line for line in lines if line.startswith("EKF2_EV_CTRL"))
    assert row.split() == ["EKF2_EV_CTRL", "INT32", "15", "0", "DIFFERS"]
    assert next(line for line in lines if line.startswith("COM_OF_LOSS_T")).split()[-1] == "ok"
    assert "d1: check FAILED" in res.output

    res = runner.invoke(app, ["px4", "setup", "d1", "-c", cfg_path])
    assert res.exit_code == 0, res.output
    row = next(line for line in res.output.splitlines() if line.startswith("EKF2_EV_CTRL"))
    assert row.split() == ["EKF2_EV_CTRL", "INT32", "15", "15", "ok", "(written)"]
    assert "rebooted the autopilot for" in res.output and "EKF2_HGT_REF" in res.output
    assert "d1: setup ACCEPTED" in res.output
    for name, (value, _) in px4.ARENA_REQUIRED_PARAMS.items():
        assert rig.aps["d1"].param(name) == value or abs(float(rig.aps["d1"].param(name)) - value) < 1e-6

    res = runner.invoke(app, ["px4", "check", "d1", "-c", cfg_path])
    assert res.exit_code == 0 and "DIFFERS" not in res.output and "d1: check ACCEPTED" in res.output


def test_px4_check_without_a_gateway_and_bad_names(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(start=False)
    res = runner.invoke(app, ["px4", "check", "d1", "-c", rig.cfg.path, "--timeout", "1"])
    assert res.exit_code == 1 and "TIMEOUT" in res.output and "no answer" in res.output
    res = runner.invoke(app, ["px4", "check", "bad/name", "-c", rig.cfg.path])
    assert res.exit_code == 2 and "invalid vehicle name" in res.output


def test_gateway_command_line_help_and_unknown_vehicle(make_rig: Callable[..., Rig]) -> None:
    res = runner.invoke(app, ["run", "gateway", "--help"])
    assert res.exit_code == 0 and "--vehicle" in res.output and "--sysid" in res.output
    rig = make_rig(start=False)
    res = runner.invoke(app, ["run", "gateway", "--vehicle", "nope", "-c", rig.cfg.path])
    assert res.exit_code == 2 and "no vehicle 'nope'" in res.output


def test_every_gateway_flag_overrides_a_config_field_within_its_bounds(make_rig: Callable[..., Rig]) -> None:
    """The config is the one home of a gateway's settings: each flag names one field of the vehicle's
    section, and a value out of that field's bounds is refused with the config's own words."""
    rig = make_rig(start=False)
    res = runner.invoke(app, ["run", "gateway", "--help"], env={"COLUMNS": "200"})
    for flag, field in FLAGS.items():
        assert field in VehicleSpec.__struct_fields__, field
        assert flag in res.output, flag
    for argv, words in (
        (["--state-rate", "0.5"], "--state-rate: vehicles.d1.state_rate: expected a number in 1.0..200.0"),
        (["--telemetry-rate", "-1"], "vehicles.d1.telemetry_rate: expected a number in 0.0..200.0"),
        (["--sysid", "255"], "--sysid: vehicles.d1.gateway_system_id: expected an integer in 1..254"),
        (["--origin", "91,0,0"], "vehicles.d1.origin: expected a list of 3 numbers (within -90.0..90.0"),
        (["--origin", "north"], "or the word off, got 'north'"),
        # A flag opens to the network no more than the config may (docs/safety.md: ground-station links).
        (
            ["--gcs", "udpin:0.0.0.0:14550"],
            "vehicles.d1.gcs: expected a ground-station link on loopback only",
        ),
    ):
        res = runner.invoke(
            app, ["run", "gateway", "-v", "d1", "-c", rig.cfg.path, *argv], env={"COLUMNS": "300"}
        )
        assert res.exit_code == 2, res.output
        assert words in " ".join(res.output.split()), res.output
    # Valid flags land in the vehicle's section, and nowhere else.
    cfg = overridden(
        rig.cfg,
        "d1",
        {"--origin": "-33.86, 151.21, 5", "--sysid": 200, "--allow-gcs-manual": True, "--gcs": None},
    )
    d1 = cfg.vehicle("d1")
    assert (d1.origin, d1.gateway_system_id, d1.allow_gcs_manual) == ((-33.86, 151.21, 5.0), 200, True)
    assert d1.gcs == rig.cfg.vehicle("d1").gcs
    assert overridden(rig.cfg, "d1", {"--origin": "off"}).vehicle("d1").origin == "off"
