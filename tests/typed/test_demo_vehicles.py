"""``arena demo --vehicles N``: N simulated vehicles on a grid fly the formation, typed as a user types it.

The README's line flies 20; the test types the same command with 4 (a busy 2-core machine) on a config
of free ports (:class:`tests.typed.harness.Typed`), which ``--vehicles`` takes as its base: its room,
mocap and Zenoh ports, its host.  The fleet's own config is written next to the log.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from arena_common.cli._demo import fleet_room, fleet_spacing, grid
from arena_common.core.config import load
from arena_common.core.errors import ArenaError
from tests.helpers import free_port, wait_for
from tests.typed.harness import ARENA, Command, Typed, commands, leftovers

pytestmark = [
    pytest.mark.system,
    pytest.mark.timeout(400),
    pytest.mark.skipif(not ARENA.exists(), reason=f"no arena console script at {ARENA}"),
]

FLOWN_S = 300.0  # the arena up, 4 vehicles ready, the whole formation flown and landed, on a busy machine
# `arena demo` says it waits for the vehicles once its router listens (3.6 s on an idle 2-core machine, 13.4 s
# loaded: load average 5) and its session is open; it gives up by itself, saying why, after its own
# --ready-timeout (90 s and 2 s a vehicle): the test's bound is the demo's, plus its error.
READY_S = 90.0 + 2.0 * 4 + 15.0


@pytest.fixture
def typed(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    """``arena`` command lines in ``tmp_path``, killed (with all they started) at the end."""
    with commands(tmp_path) as start:
        yield start


@pytest.mark.covers("arena demo --vehicles 20")
def test_a_fleet_on_a_grid_flies_the_formation_and_lands(
    tmp_path: Path, typed: Callable[..., Command]
) -> None:
    base = Typed(tmp_path, f"tcp/127.0.0.1:{free_port()}", router=True, px4=False)
    log = tmp_path / "demo.log"
    cmd = typed("demo", str(base.path), "--vehicles", "4", "--once", "--log", str(log))
    cmd.wait_line(r"waiting for d1, d2, d3, d4: gateways alive and vision fused", timeout=READY_S)

    fleet = tmp_path / "arena-demo-4.toml"  # next to the log
    cfg = load(fleet)
    assert list(cfg.vehicles) == ["d1", "d2", "d3", "d4"]
    assert cfg.pipeline.decimate == "transform"
    assert sorted(v.system_id for v in cfg.vehicles.values()) == [1, 2, 3, 4]
    ports = {v.mavlink for v in cfg.vehicles.values()}
    assert len(ports) == 4 and all(p.startswith("udpin:127.0.0.1:") for p in ports), ports
    starts = [v.sim.start for v in cfg.vehicles.values()]
    assert len(set(starts)) == 4 and all(abs(n) < 3.5 and abs(e) < 2.0 for n, e in starts), starts
    raw = tomllib.loads(fleet.read_text())
    assert raw["mocap"]["command_port"] == base.command_port  # the base's ports, kept
    # The base's Zenoh, with each gateway a client of the router (no peer mesh of N processes).
    assert raw["zenoh"] == {**tomllib.loads(base.path.read_text())["zenoh"], "vehicle_mode": "client"}
    assert cfg.zenoh.vehicle_mode == "client"
    assert {v.stream_rates["ATTITUDE"] for v in cfg.vehicles.values()} == {10.0}  # PX4's 100 Hz: unread

    assert cmd.exits_within(FLOWN_S) == 0, cmd.output() + "\n" + log.read_text(errors="replace")[-3000:]
    out = cmd.output()
    assert f"4 vehicles on a grid: config {fleet} " in re.sub(r"\s+", " ", out), out
    assert "formation step 6/6" in out and "landed: demo complete" in out, out
    wait_for(lambda: not leftovers([str(tmp_path)], cmd.pid), timeout=15, interval=0.2, what="nothing left")


def test_fifty_vehicles_stand_apart_in_a_room_grown_for_them() -> None:
    """Vehicles stand min_separation plus two hovers' largest swing apart (1.4 m): the default room holds
    ten; fifty get a room grown for them; a grid that does not fit is an error naming the spacing."""
    least = fleet_spacing(0.6)
    assert least == pytest.approx(1.4)
    assert fleet_room(10, (7.0, 4.0), 0.7, least) == (7.0, 4.0)
    room = fleet_room(50, (7.0, 4.0), 0.7, least)
    assert room[0] > 7.0 and room[0] / room[1] == pytest.approx(7.0 / 4.0, rel=0.01)
    spots = grid(50, room, 0.7, least)
    assert len(set(spots)) == 50
    assert all(abs(n) <= room[0] / 2 - 0.7 and abs(e) <= room[1] / 2 - 0.7 for n, e in spots)
    closest = min(
        ((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2) ** 0.5 for i, a in enumerate(spots) for b in spots[i + 1 :]
    )
    assert closest >= least - 1e-9, closest
    with pytest.raises(ArenaError, match=r"at least 1\.4 m apart"):
        grid(50, (7.0, 4.0), 0.7, least)
