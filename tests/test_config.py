from pathlib import Path

import pytest

from arena_common import config
from arena_common.errors import ConfigError
from tests.conftest import REPO

BASE = """
[vehicles.d1]
rigid_body = "d1"
mavlink = "udpin:127.0.0.1:14541"
system_id = 1
[hosts.h]
vehicles = ["d1"]
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "arena.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("name", ["sim.toml", "lab.example.toml"])
def test_shipped_configs_are_valid(name: str) -> None:
    cfg = config.load(REPO / "deploy" / name)
    assert cfg.vehicles
    for host in cfg.hosts.values():
        assert set(host.vehicles) <= set(cfg.vehicles)


def test_sim_config_has_three_vehicles_with_distinct_ids() -> None:
    cfg = config.load(REPO / "deploy" / "sim.toml")
    assert list(cfg.vehicles) == ["d1", "d2", "d3"]
    assert len({v.system_id for v in cfg.vehicles.values()}) == 3
    assert cfg.vehicles["d1"].sim_mavlink() == "udpout:127.0.0.1:14541"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (BASE.replace("system_id = 1", 'system_id = "one"'), "vehicles.d1.system_id: expected an integer"),
        (
            BASE.replace("system_id = 1", "system_id = 0"),
            "vehicles.d1.system_id: expected an integer in 1..250",
        ),
        (
            BASE.replace('vehicles = ["d1"]', 'vehicles = ["d9"]'),
            "hosts.h.vehicles: expected names of configured",
        ),
        (
            BASE.replace("[vehicles.d1]", '[vehicles."d*1"]').replace('["d1"]', "[]"),
            "invalid vehicle name 'd*1'",
        ),
        (BASE + "[arena]\nsize = [7, 4]\n", "arena.size: expected a list of 3 numbers"),
        (BASE + "[mocap]\nup_axis = 'x'\n", "mocap.up_axis: expected one of y, z, enu"),
        (BASE + "[mocap]\nbogus = 1\n", "mocap.bogus: unknown field"),
        (
            BASE.replace('mavlink = "udpin:127.0.0.1:14541"\n', ""),
            "vehicles.d1.mavlink: expected a pymavlink",
        ),
        (BASE + '[vehicles.d2]\nmavlink = "udpin:127.0.0.1:1"\nsystem_id = 1\n', "vehicles.d2.system_id"),
        ("[arena\n", "not valid TOML"),
    ],
)
def test_errors_name_file_and_field(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert str(path) in str(err.value)
    assert message in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        config.load(tmp_path / "nope.toml")


def test_unknown_host_lists_known_ones(tmp_path: Path) -> None:
    cfg = config.load(write(tmp_path, BASE))
    with pytest.raises(ConfigError, match=r"host 'other' is not in the config \(known hosts: h\)"):
        cfg.host("other")


def test_safe_box() -> None:
    spec = config.ArenaSpec(size=(7.0, 4.0, 2.5), margin=0.5)
    assert spec.safe_box() == ((-3.0, 3.0), (-1.5, 1.5), (-2.0, 0.0))
