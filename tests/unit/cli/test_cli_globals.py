"""The options every command shares are declared once and may stand before or after the sub-command."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.cli._globals import hoist
from tests.helpers import REPO

runner = CliRunner()


def test_hoist_moves_shared_options_and_their_values_only() -> None:
    argv = [
        "goto",
        "d1",
        "0",
        "0",
        "-1.0",
        "--config",
        "a.toml",
        "-e",
        "tcp/x:1",
        "--mode=client",
        "--yaw",
        "9",
    ]
    assert hoist(argv) == [
        "--config",
        "a.toml",
        "-e",
        "tcp/x:1",
        "--mode=client",
        "goto",
        "d1",
        "0",
        "0",
        "-1.0",
        "--yaw",
        "9",
    ]
    assert hoist(["echo", "--", "-c", "x"]) == ["echo", "--", "-c", "x"]  # after --, nothing moves


@pytest.mark.parametrize("before", [True, False])
def test_config_option_before_or_after_the_command(tmp_path: Path, before: bool) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[mocap]\nup_axis = 'x'\n")
    opts = ["--config", str(bad)]
    res = runner.invoke(app, [*opts, "px4", "check", "d1"] if before else ["px4", "check", "d1", *opts])
    assert res.exit_code == 2
    assert f"{bad}: mocap.up_axis: expected one of y, z, enu, got 'x'" in res.output


def test_a_bad_mode_is_refused_before_the_command_runs() -> None:
    res = runner.invoke(app, ["status", "--mode", "bogus"])
    assert res.exit_code == 2 and "--mode must be one of peer, client, router" in res.output


def test_the_shared_options_are_declared_once() -> None:
    cli = REPO / "arena_common" / "cli"
    declared = [
        p.name for p in cli.glob("*.py") for line in p.read_text().splitlines() if ": ConfigOpt" in line
    ]
    assert declared == ["_globals.py"]
