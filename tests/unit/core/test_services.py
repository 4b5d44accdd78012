"""The table of services: one name per process, and every place that names a service reads it."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.core import services
from arena_common.core.config import load
from arena_common.core.services import EXTRAS, SERVICES, by_module, by_name, missing_extra, started_by
from arena_common.runtime.supervisor import plan
from tests.helpers import REPO, write_config


def test_one_name_one_module_one_word() -> None:
    names = [s.name for s in SERVICES]
    assert len(set(names)) == len(names)
    assert len({s.module for s in SERVICES}) == len(SERVICES)
    # A word typed after `arena run` never means another program after `arena sim`.
    words = [s.command for s in SERVICES]
    assert len(set(words)) == len(words), words
    assert all(s.name.startswith(services.SIM_PREFIX) == (s.group == "sim") for s in SERVICES)
    assert by_name("sim-motive").command == "motive" and by_name("px4-sitl").command == "px4-sitl"
    with pytest.raises(KeyError, match=r"no service .nope. \(known: mocap, transform"):
        by_name("nope")


@pytest.mark.parametrize("service", SERVICES, ids=[s.name for s in SERVICES])
def test_each_module_is_the_service_of_its_name(service: services.ServiceInfo) -> None:
    if service.extra and missing_extra(service.extra):
        pytest.skip(f"{service.name}: {missing_extra(service.extra)}")
    module = importlib.import_module(service.module)
    assert callable(module.main) and callable(module.cli)
    if hasattr(module, "SERVICE"):  # the presence name it announces (sim-world runs the two parts' own)
        assert service.name == module.SERVICE
    assert by_module(service.module) is service


def test_the_config_accepts_exactly_the_tables_words() -> None:
    host_words = {s.config for s in SERVICES if s.config and s.scope == "host"} | {"router"}
    assert set(services.HOST_SERVICES) == host_words
    assert set(services.VEHICLE_SERVICES) == {s.config for s in SERVICES if s.scope == "vehicle"}
    assert [s.name for s in started_by("sim")] == ["sim-vehicle", "sim-motive"]


def test_the_supervisor_names_processes_as_the_table(tmp_path: Path) -> None:
    cfg = load(write_config(tmp_path, "tcp/127.0.0.1:7447", n_vehicles=1))
    specs = plan(cfg, next(iter(cfg.hosts)))
    assert {s.name for s in specs} >= {"sim-vehicle", "sim-motive", "mocap", "gateway.d1"}
    for spec in specs:
        if spec.name == "router":
            continue
        row = by_name(spec.name.split(".")[0])
        assert spec.argv[1:3] == ("-m", row.module), spec


@pytest.mark.parametrize("group", ["run", "sim"])
def test_the_cli_has_one_command_per_service(group: str) -> None:
    out = CliRunner().invoke(app, [group, "--help"], terminal_width=200).output
    for s in SERVICES:
        listed = any(line.split()[:1] == [s.command] for line in out.splitlines() if line.startswith("│ "))
        listed = listed or f"│ {s.command} " in out
        assert listed == (s.group == group), f"arena {group} --help and {s.name}:\n{out}"


def test_extras_are_the_projects_own() -> None:
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra, modules in EXTRAS.items():
        packages = " ".join(extras[extra]).lower()
        assert all(m.lower() in packages for m in modules), (extra, modules, extras[extra])
    assert {s.extra for s in SERVICES if s.extra} <= set(EXTRAS)


def test_a_missing_extra_names_the_line_that_installs_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(EXTRAS, "ros2", ("rosbags", "no_such_module_here"))
    why = missing_extra("ros2")
    assert why is not None
    assert "'no_such_module_here'" in why and "'rosbags'" not in why
    assert why.endswith("pip install 'flying-arena[ros2]'")
    monkeypatch.setitem(EXTRAS, "ros2", ("json",))
    assert missing_extra("ros2") is None
