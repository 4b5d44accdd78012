import re
from pathlib import Path

import msgspec
import pytest

from arena_common.core import config, convert, vehiclespec
from arena_common.core.errors import ConfigError
from tests.helpers import REPO

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
        (
            BASE.replace("system_id = 1", "system_id = 1\nstate_rate = 0"),
            "vehicles.d1.state_rate: expected a number",
        ),
        (BASE.replace("system_id = 1", "system_id = 1\ntelemetry_rate = -1"), "vehicles.d1.telemetry_rate"),
        (BASE + "[vehicles.d1.sim]\nbogus = 1\n", "vehicles.d1.sim.bogus: unknown field"),
        ("arena = 5\n" + BASE, "arena: expected a table, got 5"),
        (BASE + "[hosts.g]\nservices = ['mocap', 'bogus']\n", "hosts.g.services: expected names among "),
        (
            # The key that is wrong, not the first that PX4's parameter names would refuse.
            BASE.replace(
                "system_id = 1", "system_id = 1\nstream_rates = { ATTITUDE_QUATERNION = 5, bogus = 1 }"
            ),
            "vehicles.d1.stream_rates: expected a string matching ^[A-Z][A-Z0-9_]{0,49}$, got 'bogus'",
        ),
    ],
)
def test_errors_name_file_and_field(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert str(path) in str(err.value)
    assert message in str(err.value)


def test_every_field_says_what_it_expects_in_words() -> None:
    words = re.compile(
        r"(an integer|a number|a string|true or false|one of |names among |a list of |a table)"
    )
    structs: list[type[convert.Spec]] = [config.ArenaConfig, config.HostSpec, vehiclespec.VehicleSpec]
    structs += [*config._SECTIONS.values(), vehiclespec.SimVehicleSpec]
    for cls in structs:
        for field in msgspec.structs.fields(cls):
            assert words.match(convert.expected(field.type)), (cls.__name__, field.name)


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


# -- what flies each vehicle: autopilot = "sim" | "px4" | "px4-sitl" ---------------------------------------

SITL = """
[vehicles.d1]
autopilot = "px4-sitl"
px4_instance = 3
[hosts.h]
vehicles = ["d1"]
"""


def test_autopilot_defaults_to_the_simulated_one(tmp_path: Path) -> None:
    v = config.load(write(tmp_path, BASE)).vehicle("d1")
    assert v.autopilot == "sim" and v.simulated and not v.px4_sitl
    assert v.px4_instance is None and v.px4_params == {}


def test_a_px4_sitl_vehicle_may_leave_its_link_and_id_to_its_instance(tmp_path: Path) -> None:
    # The shape alone: runtime.px4_sitl_rules fills them in (tests/unit/runtime/test_px4_sitl_rules.py).
    v = config.load(write(tmp_path, SITL)).vehicle("d1")
    assert (v.autopilot, v.px4_instance) == ("px4-sitl", 3)
    assert v.mavlink == "" and v.system_id == 0
    assert v.px4_sitl and not v.simulated


def test_system_ids_left_to_px4_sitl_instances_do_not_clash_yet(tmp_path: Path) -> None:
    text = SITL + '[vehicles.d2]\nautopilot = "px4-sitl"\npx4_instance = 4\n'
    assert [v.system_id for v in config.load(write(tmp_path, text)).vehicles.values()] == [0, 0]


def test_external_px4_needs_its_link_and_id_like_today(tmp_path: Path) -> None:
    v = config.load(
        write(tmp_path, BASE.replace("system_id = 1", 'system_id = 1\nautopilot = "px4"'))
    ).vehicle("d1")
    assert v.autopilot == "px4" and not v.simulated and not v.px4_sitl
    assert v.mavlink == "udpin:127.0.0.1:14541" and v.system_id == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            SITL.replace('"px4-sitl"', '"ardupilot"'),
            "vehicles.d1.autopilot: expected one of sim, px4, px4-sitl",
        ),
        (
            SITL.replace("px4_instance = 3", 'px4_instance = "3"'),
            "vehicles.d1.px4_instance: expected an integer, got '3'",
        ),
        (
            SITL.replace("px4_instance = 3", "px4_instance = 3\npx4_params = { ekf2_ev_ctrl = 15 }"),
            "vehicles.d1.px4_params: expected PX4 parameter names",
        ),
        (
            SITL.replace("px4_instance = 3", 'px4_instance = 3\npx4_params = { EKF2_EV_CTRL = "15" }'),
            "vehicles.d1.px4_params.EKF2_EV_CTRL: expected a number",
        ),
        (
            SITL.replace(
                "px4_instance = 3", 'px4_instance = 3\nsim = { mavlink = "udpout:127.0.0.1:14543" }'
            ),
            'vehicles.d1.sim.mavlink: expected no simulated side unless autopilot = "sim"',
        ),
    ],
)
def test_autopilot_errors_name_the_vehicle_and_field(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert str(path) in str(err.value)
    assert message in str(err.value)


def test_same_port_on_different_hosts_is_fine(tmp_path: Path) -> None:
    # Companion computers each listen on 14540 for their own autopilot: no clash across hosts.
    text = """
[vehicles.c1]
autopilot = "px4"
mavlink = "udpin:0.0.0.0:14540"
mavlink_peer = "192.168.1.41:14550"
system_id = 11
[vehicles.c2]
autopilot = "px4"
mavlink = "udpin:0.0.0.0:14540"
mavlink_peer = "192.168.1.42:14550"
system_id = 12
[hosts.cc1]
vehicles = ["c1"]
[hosts.cc2]
vehicles = ["c2"]
"""
    cfg = config.load(write(tmp_path, text))
    assert [v.mavlink for v in cfg.vehicles.values()] == ["udpin:0.0.0.0:14540"] * 2
