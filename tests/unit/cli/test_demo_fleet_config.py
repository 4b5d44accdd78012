"""``arena demo --vehicles N`` writes its fleet's config (``fleet_config``): the base's content, N vehicles.

What the typed test (``tests/typed/test_demo_vehicles.py``) flies; here the written file itself, read back
with :mod:`tomllib` and the arena's own loader.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

import pytest

from arena_common.cli._demo import FLEET_STREAMS, fleet_config
from arena_common.core.config import load
from arena_common.core.errors import ArenaError
from tests.helpers import REPO


@pytest.mark.parametrize("base", ["sim.toml", "lab.example.toml", "px4-sitl.toml"])
def test_the_fleet_config_is_the_base_with_n_vehicles(tmp_path: Path, base: str) -> None:
    src = REPO / "deploy" / base
    out, spots = fleet_config(src, 4, tmp_path / "arena-demo-4.toml")
    text = out.read_text(encoding="utf-8")
    assert text.startswith(f"# 4 simulated vehicles on a grid, from {src} ")
    raw, want = tomllib.loads(text), _expected(tomllib.loads(src.read_text(encoding="utf-8")))

    names = ["d1", "d2", "d3", "d4"]
    vehicles = raw.pop("vehicles")
    assert list(vehicles) == names and list(spots) == names
    ports = set()
    for i, (name, v) in enumerate(vehicles.items(), start=1):
        assert v["rigid_body"] == name and v["system_id"] == i
        assert v["stream_rates"] == FLEET_STREAMS and v["sim"] == {"start": list(spots[name])}
        assert v["mavlink"].startswith("udpin:127.0.0.1:")
        ports.add(v["mavlink"])
    assert len(ports) == 4
    assert raw == want  # everything else: the base's, but for what a fleet changes

    cfg = load(out)
    assert list(cfg.vehicles) == names and cfg.zenoh.vehicle_mode == "client"
    assert next(iter(cfg.hosts.values())).vehicles == tuple(names)
    assert [v.sim.start for v in cfg.vehicles.values()] == [spots[n] for n in names]


def test_a_fleet_too_big_for_the_room_gets_a_room_grown_for_it(tmp_path: Path) -> None:
    src = REPO / "deploy" / "sim.toml"
    out, spots = fleet_config(src, 50, tmp_path / "arena-demo-50.toml")
    size = tomllib.loads(src.read_text(encoding="utf-8"))["arena"]["size"]
    cfg = load(out)
    assert len(cfg.vehicles) == 50 and cfg.arena.size[2] == size[2]
    assert cfg.arena.size[0] > size[0] and cfg.arena.size[1] > size[1]
    assert all(abs(n) < cfg.arena.size[0] / 2 and abs(e) < cfg.arena.size[1] / 2 for n, e in spots.values())


def _expected(base: dict[str, Any]) -> dict[str, Any]:
    """The base as a fleet of d1..d4 changes it (the vehicles aside): by hand, as fleet_config's doc says."""
    want = copy.deepcopy(base)
    want.pop("vehicles", None)
    want.setdefault("pipeline", {})["decimate"] = "transform"
    want.setdefault("zenoh", {})["vehicle_mode"] = "client"
    for i, host in enumerate(want["hosts"].values()):
        host["vehicles"] = ["d1", "d2", "d3", "d4"] if i == 0 else []
        if "vehicle_services" in host:
            host["vehicle_services"] = [s for s in host["vehicle_services"] if s != "downsampler"] or [
                "gateway"
            ]
    return want


def test_odd_names_and_strings_are_written_as_toml(tmp_path: Path) -> None:
    """Keys and strings TOML must quote or escape come back as they were."""
    base = tmp_path / "base.toml"
    base.write_text(
        '[arena]\nname = "salle \\"B\\" — ∅\\\\ \\t"\n\n[zenoh]\nconnect = ["tcp/127.0.0.1:7447"]\n\n'
        '[hosts."ground.pc"]\nservices = ["router"]\n',
        encoding="utf-8",
    )
    out, _ = fleet_config(base, 2, tmp_path / "arena-demo-2.toml")
    raw = tomllib.loads(out.read_text(encoding="utf-8"))
    assert raw["arena"]["name"] == 'salle "B" — ∅\\ \t'
    assert raw["hosts"] == {"ground.pc": {"services": ["router"], "vehicles": ["d1", "d2"]}}
    assert load(out).arena.name == 'salle "B" — ∅\\ \t'


def test_fleet_sizes_out_of_range_are_refused(tmp_path: Path) -> None:
    for n in (0, 251):
        with pytest.raises(ArenaError, match=r"--vehicles: 1\.\.250"):
            fleet_config(REPO / "deploy" / "sim.toml", n, tmp_path / "x.toml")
