"""What a PX4 SITL instance number fixes: its ports and system id, and the config rules of a ``"px4-sitl"``
vehicle, as every arena process loads a config (:func:`arena_common.runtime.options.read_config`)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
import typer

from arena_common.core import config as config_mod
from arena_common.core.errors import ConfigError
from arena_common.runtime import px4_sitl_rules
from arena_common.runtime.options import load_config, parse_config, read_config
from arena_common.runtime.px4_sitl_rules import Px4SitlError
from tests.helpers import REPO
from tests.unit.core.test_config import BASE, SITL, write


def test_ports_of_an_instance() -> None:
    p = px4_sitl_rules.ports(3)
    assert (p.offboard, p.px4_offboard, p.gcs, p.px4_gcs, p.truth, p.px4_truth) == (
        14543, 14583, 14550, 18573, 19413, 19453,
    )  # fmt: skip
    assert p.system_id == 4 and p.gateway_mavlink() == "udpin:127.0.0.1:14543"
    for bad in (-1, 10, True, 2.0):
        with pytest.raises(Px4SitlError, match=r"0\.\.9"):
            px4_sitl_rules.ports(bad)  # type: ignore[arg-type]


def test_px4_sitl_link_and_system_id_follow_from_the_instance(tmp_path: Path) -> None:
    v = read_config(write(tmp_path, SITL)).vehicle("d1")
    assert (v.autopilot, v.px4_instance) == ("px4-sitl", 3)
    assert v.mavlink == "udpin:127.0.0.1:14543" and v.system_id == 4
    assert v.px4_sitl and not v.simulated
    shape = config_mod.load(write(tmp_path, SITL))  # the shape alone leaves them to the rules
    assert px4_sitl_rules.apply(shape).vehicle("d1") == v
    assert px4_sitl_rules.apply(px4_sitl_rules.apply(shape)) == px4_sitl_rules.apply(shape)


def test_px4_sitl_accepts_the_matching_link_and_id_and_boot_params(tmp_path: Path) -> None:
    text = (
        SITL.replace(
            "px4_instance = 3",
            'px4_instance = 3\nmavlink = "udpin:0.0.0.0:14543"\nsystem_id = 4\n'
            "px4_params = { EKF2_EVP_NOISE = 0.05, EKF2_EV_CTRL = 15 }",
        )
        + "[security]\ninsecure = true\n"
    )  # 0.0.0.0: PX4 SITL's port on every interface, unsigned
    v = read_config(write(tmp_path, text)).vehicle("d1")
    assert v.mavlink == "udpin:0.0.0.0:14543" and v.system_id == 4
    assert v.px4_params == {"EKF2_EVP_NOISE": 0.05, "EKF2_EV_CTRL": 15}


def test_shipped_px4_sitl_config_mixes_nothing_it_cannot_start() -> None:
    cfg = read_config(REPO / "deploy" / "px4-sitl.toml")
    assert {v.autopilot for v in cfg.vehicles.values()} == {"px4-sitl"}
    assert [(v.px4_instance, v.system_id, v.mavlink) for v in cfg.vehicles.values()] == [
        (0, 1, "udpin:127.0.0.1:14540"),
        (1, 2, "udpin:127.0.0.1:14541"),
    ]
    assert "sim" in cfg.host("sitl").services  # the Motive emulator


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            SITL.replace("px4_instance = 3\n", ""),
            'vehicles.d1.px4_instance: expected the PX4 SITL instance number (0..9) of a "px4-sitl" vehicle',
        ),
        (
            SITL.replace("px4_instance = 3", "px4_instance = 10"),
            "vehicles.d1.px4_instance: expected an integer in 0..9, got 10",
        ),
        (
            SITL.replace("px4_instance = 3", "px4_instance = -1"),
            "vehicles.d1.px4_instance: expected an integer in 0..9, got -1",
        ),
        (
            SITL.replace("px4_instance = 3", "px4_instance = 3\nsystem_id = 3"),
            "vehicles.d1.system_id: expected 4, the MAV_SYS_ID of PX4 SITL instance 3 (or leave it out), got 3",
        ),
        (
            SITL.replace("px4_instance = 3", 'px4_instance = 3\nmavlink = "udpin:127.0.0.1:14540"'),
            "vehicles.d1.mavlink: expected udpin:127.0.0.1:14543 for PX4 SITL instance 3 (px4_instance; or "
            "leave mavlink out), got 'udpin:127.0.0.1:14540'",
        ),
        (
            SITL.replace("px4_instance = 3", 'px4_instance = 3\nmavlink = "tcp:127.0.0.1:14543"'),
            "vehicles.d1.mavlink: expected udpin:127.0.0.1:14543 for PX4 SITL instance 3 (px4_instance; or "
            "leave mavlink out), got 'tcp:127.0.0.1:14543'",
        ),
        (
            SITL.replace("px4_instance = 3", 'px4_instance = 3\nmavlink = "udpin:192.168.1.5:14543"'),
            "vehicles.d1.mavlink: expected udpin:127.0.0.1:14543 for PX4 SITL instance 3 (px4_instance; or "
            "leave mavlink out), got 'udpin:192.168.1.5:14543'",
        ),
        (
            BASE.replace("system_id = 1", "system_id = 1\npx4_instance = 1"),
            "vehicles.d1.px4_instance: expected no px4_instance unless autopilot = \"px4-sitl\" (got 'sim')",
        ),
        (
            BASE.replace(
                "system_id = 1", 'system_id = 1\nautopilot = "px4"\npx4_params = { EKF2_EV_CTRL = 15 }'
            ),
            "vehicles.d1.px4_params: expected no px4_params unless autopilot = \"px4-sitl\" (got 'px4')",
        ),
        (
            SITL + '[vehicles.d2]\nautopilot = "px4-sitl"\npx4_instance = 3\n',
            "vehicles.d2.px4_instance: expected a PX4 SITL instance not used by d1, got 3",
        ),
        (
            # The id instance 3 implies, given to a vehicle before it.
            '[vehicles.d0]\nmavlink = "udpin:127.0.0.1:14600"\nsystem_id = 4\n' + SITL,
            "vehicles.d1.system_id: expected a system id not used by d0, got 4",
        ),
        (
            # ... and after it.
            SITL + '[vehicles.d2]\nmavlink = "udpin:127.0.0.1:14600"\nsystem_id = 4\n',
            "vehicles.d2.system_id: expected a system id not used by d1, got 4",
        ),
        (
            # A simulated vehicle's gateway on the port PX4 SITL instance 3 sends to, on the same host.
            SITL.replace('vehicles = ["d1"]', 'vehicles = ["d1", "d2"]')
            + '[vehicles.d2]\nmavlink = "udpin:127.0.0.1:14543"\nsystem_id = 9\n',
            "hosts.h.vehicles: expected vehicles whose gateways listen on distinct UDP ports (d1 and d2 both use "
            "14543 on this host), got ['d1', 'd2']",
        ),
    ],
)
def test_px4_sitl_errors_name_the_file_vehicle_and_field(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        read_config(path)
    assert str(err.value) == f"{path}: {message}"
    config_mod.load(path)  # the shape alone accepts them: the rules are this module's
    with pytest.raises(ConfigError, match="^doc.toml: " + message.split(":")[0]):
        parse_config(tomllib.loads(text), "doc.toml")  # the same rules on a parsed document


def test_every_program_loader_applies_the_rules(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, SITL.replace("px4_instance = 3", "px4_instance = 3\nsystem_id = 3"))
    with pytest.raises(typer.Exit) as exit_:
        load_config(path)
    assert exit_.value.exit_code == 2
    assert f"error: {path}: vehicles.d1.system_id: expected 4, the MAV_SYS_ID" in capsys.readouterr().err
