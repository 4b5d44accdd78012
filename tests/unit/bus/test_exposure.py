"""What a config may expose to the network (:mod:`arena_common.bus.exposure`): a pinned MAVLink peer is one
real host on a listening UDP link; without ``security.insecure`` nothing listens beyond loopback
unauthenticated (the Zenoh side: ``test_security_config.py``).  And what each loader checks."""

from __future__ import annotations

from pathlib import Path

import pytest

import arena_common
from arena_common.bus import exposure
from arena_common.core import config as config_mod
from arena_common.core.errors import ConfigError
from arena_common.runtime.options import read_config
from tests.unit.core.test_config import BASE, write

PX4 = BASE.replace("system_id = 1", 'system_id = 1\nautopilot = "px4"')
SITL_PINNED = '[vehicles.d1]\nautopilot = "px4-sitl"\npx4_instance = 0\nmavlink_peer = "127.0.0.1:14580"\n'
OPEN_LINK = BASE.replace("udpin:127.0.0.1:14541", "udpin:0.0.0.0:14541")


@pytest.mark.parametrize(
    ("peer", "extra", "message"),
    [
        ('"192.168.1.31"', "", "expected the autopilot's IPv4 address and UDP port, IP:PORT"),
        ('"drone.local:14550"', "", "expected the autopilot's IPv4 address and UDP port"),
        ('"192.168.1.300:14550"', "", "expected the autopilot's IPv4 address and UDP port"),
        ('"0.0.0.0:14550"', "", "expected the autopilot's IPv4 address and UDP port"),
        ('"192.168.1.31:0"', "", "expected the autopilot's IPv4 address and UDP port"),
        ("14550", "", "vehicles.d1.mavlink_peer: expected a string"),
        ('"192.168.1.31:14550"', "tcp", "expected no mavlink_peer unless mavlink is udpin:HOST:PORT"),
        ('"192.168.1.31:14550"', "sim", 'expected no mavlink_peer with autopilot = "sim"'),
    ],
)
def test_a_bad_mavlink_peer_is_a_config_error_naming_the_field(
    tmp_path: Path, peer: str, extra: str, message: str
) -> None:
    text = (BASE if extra == "sim" else PX4).replace("system_id = 1", f"system_id = 1\nmavlink_peer = {peer}")
    if extra == "tcp":
        text = text.replace("udpin:127.0.0.1:14541", "tcp:127.0.0.1:5760")
    path = write(tmp_path, text)
    for load in (read_config, exposure.load):  # every process's loader and the client's
        with pytest.raises(ConfigError) as err:
            load(path)
        assert str(path) in str(err.value) and "vehicles.d1.mavlink_peer" in str(err.value)
        assert message in str(err.value)


def test_a_pin_is_checked_even_when_the_arena_is_knowingly_insecure(tmp_path: Path) -> None:
    text = PX4.replace("system_id = 1", 'system_id = 1\nmavlink_peer = "drone.local:14550"')
    with pytest.raises(ConfigError, match=r"vehicles\.d1\.mavlink_peer: expected the autopilot's IPv4"):
        read_config(write(tmp_path, text + "[security]\ninsecure = true\n"))


def test_check_exposure_judges_a_loaded_config(tmp_path: Path) -> None:
    cfg = config_mod.load(write(tmp_path, OPEN_LINK))  # the shape alone lets it listen
    with pytest.raises(ConfigError) as err:
        exposure.check_exposure(cfg)
    assert str(err.value) == (
        f"{cfg.path}: vehicles.d1.mavlink: expected an unsigned MAVLink link listening on loopback only: sign "
        "it (vehicles.d1.signing_key_file), pin the autopilot's address (vehicles.d1.mavlink_peer) or, "
        "knowingly, set security.insecure = true, got 'udpin:0.0.0.0:14541'"
    )
    exposure.check_exposure(cfg.replace(security=cfg.security.replace(insecure=True)))


def test_the_clients_loader_checks_exposure_but_not_the_px4_sitl_rules(tmp_path: Path) -> None:
    assert arena_common.load_config is exposure.load
    with pytest.raises(ConfigError, match=r"vehicles\.d1\.mavlink: expected an unsigned MAVLink link"):
        arena_common.load_config(write(tmp_path, OPEN_LINK))
    # A PX4 SITL vehicle's link, left to its instance, stays unknown here: its pin is not judged against
    # it; every process's loader derives the link (udpin on loopback) and accepts the pin.
    v = exposure.load(write(tmp_path, SITL_PINNED)).vehicle("d1")
    assert (v.mavlink, v.system_id, v.mavlink_peer) == ("", 0, "127.0.0.1:14580")
    assert read_config(write(tmp_path, SITL_PINNED)).vehicle("d1").mavlink == "udpin:127.0.0.1:14540"
    wrong = SITL_PINNED.replace("px4_instance = 0", "px4_instance = 0\nsystem_id = 5")
    exposure.load(write(tmp_path, wrong))
    with pytest.raises(ConfigError, match=r"vehicles\.d1\.system_id: expected 1, the MAV_SYS_ID"):
        read_config(write(tmp_path, wrong))
