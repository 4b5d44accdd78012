"""`arena px4 check|setup <drone>` through a running gateway, and the gateway's command line."""

from __future__ import annotations

from collections.abc import Callable

from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.mavlink import px4
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
