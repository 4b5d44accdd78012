"""Parameters of the simulated PX4: the store, PX4's defaults, and which ones need a reboot.

:class:`ParamStore` keeps each parameter typed (sent bytewise like PX4), with PX4's sorted indices, and
separates the value *stored* (what PARAM_SET wrote and PARAM_VALUE reports) from the value *in effect*:
a parameter PX4 marks ``rebootRequired`` keeps the value it had at boot until the vehicle reboots
(:meth:`ParamStore.boot` snapshots them).

Which parameters need a reboot is PX4's fact, read from the build's own metadata, never hand-kept:
:func:`reboot_required_names` reads ``parameters.json`` of the PX4 SITL build (``$PX4_SITL_DIR``, else
``../shared/px4-sitl`` next to the repository); without a build it reads the copy of that list in
``arena_common/data/px4_reboot_required.json`` (the same JSON layout, stripped to the names and their
``rebootRequired`` flags), which is regenerated from a build with::

    python -m arena_common.sim.params ../shared/px4-sitl/parameters.json

The simulated vehicle knows :data:`~arena_common.mavlink.px4.PX4_DEFAULTS` plus :data:`SIM_EXTRA_DEFAULTS`
(PX4 v1.16 defaults of further parameters it implements).
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Final

from arena_common.mavlink import px4
from arena_common.mavlink.px4 import ParamValue
from arena_common.runtime.px4_sitl import DEFAULT_DIR, ENV_DIR

__all__ = [
    "DATA_FILE",
    "SIM_EXTRA_DEFAULTS",
    "ParamStore",
    "load_reboot_required",
    "px4_sitl_dir",
    "reboot_required_names",
    "write_reboot_data",
]

_I: Final = px4.MAV_PARAM_TYPE_INT32
_F: Final = px4.MAV_PARAM_TYPE_REAL32

#: PX4 v1.16 defaults (from the build's parameters.json) of parameters the simulated vehicle implements
#: beyond :data:`~arena_common.mavlink.px4.PX4_DEFAULTS`.
SIM_EXTRA_DEFAULTS: Final[Mapping[str, tuple[ParamValue, int]]] = {
    "NAV_DLL_ACT": (0, _I),  # data link loss: 0 disabled, 1 hold, 2 return, 3 land, 5 terminate, 6 disarm
    "COM_DL_LOSS_T": (10, _I),  # s without a ground station before the data link counts as lost
    "COM_FAIL_ACT_T": (5.0, _F),  # s of Hold before a (delayable) failsafe action
    "NAV_ACC_RAD": (10.0, _F),  # m, default acceptance radius of mission waypoints
    "MPC_LAND_CRWL": (0.3, _F),  # m/s, Land's descent below MPC_LAND_ALT3 (height above home)
    "MPC_LAND_ALT2": (5.0, _F),  # m: below it Land descends at MPC_LAND_SPEED
    "MPC_LAND_ALT3": (1.0, _F),  # m: below it at MPC_LAND_CRWL, graded in between
}

DATA_FILE: Final = Path(__file__).resolve().parents[1] / "data" / "px4_reboot_required.json"


def px4_sitl_dir() -> Path:
    """Where the PX4 SITL build is looked for (as :func:`~arena_common.runtime.px4_sitl.find_build` does):
    ``$PX4_SITL_DIR``, else ``../shared/px4-sitl``."""
    env = os.environ.get(ENV_DIR)
    return Path(env) if env else DEFAULT_DIR


def load_reboot_required(path: str | os.PathLike[str]) -> frozenset[str] | None:
    """Names PX4's ``parameters.json`` layout at ``path`` marks ``rebootRequired``; None if unreadable."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    entries = data.get("parameters") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        return None
    return frozenset(
        str(p["name"]) for p in entries if isinstance(p, dict) and "name" in p and p.get("rebootRequired")
    )


@functools.lru_cache(maxsize=4)
def _cached(build_file: str, data_file: str) -> tuple[frozenset[str], str]:
    names = load_reboot_required(build_file)
    if names is not None:
        return names, build_file
    names = load_reboot_required(data_file)
    if names is not None:
        return names, data_file
    return frozenset({"MAV_SYS_ID"}), "none (MAV_SYS_ID only)"


def reboot_required_names() -> tuple[frozenset[str], str]:
    """(names of the parameters that need a reboot, the file they came from)."""
    return _cached(str(px4_sitl_dir() / "parameters.json"), str(DATA_FILE))


def write_reboot_data(parameters_json: str | os.PathLike[str], dest: Path = DATA_FILE) -> int:
    """Write :data:`DATA_FILE` from a build's ``parameters.json``; returns how many names it holds."""
    data = json.loads(Path(parameters_json).read_text(encoding="utf-8"))
    kept = sorted(
        (p["name"] for p in data.get("parameters", ()) if isinstance(p, dict) and p.get("rebootRequired")),
    )
    out = {
        "comment": "PX4 parameters marked rebootRequired in the build's parameters.json "
        "(regenerate: python -m arena_common.sim.params PATH/TO/parameters.json)",
        "version": data.get("version"),
        "parameters": [{"name": name, "rebootRequired": True} for name in kept],
    }
    dest.parent.mkdir(parents=True, exist_ok=True)
    head = json.dumps({k: v for k, v in out.items() if k != "parameters"}, indent=1)[:-2]
    rows = ",\n".join("  " + json.dumps(p) for p in out["parameters"])
    dest.write_text(f'{head},\n "parameters": [\n{rows}\n ]\n}}\n', encoding="utf-8")
    return len(kept)


class ParamStore:
    """Parameters by name with PX4's sorted indices; values kept typed, sent bytewise.

    ``reboot_required``: names whose stored value takes effect only at the next :meth:`boot`.
    """

    def __init__(
        self, values: Mapping[str, tuple[ParamValue, int]], reboot_required: Iterable[str] = ()
    ) -> None:
        self._values: dict[str, list[Any]] = {name: [value, ptype] for name, (value, ptype) in values.items()}
        self.names = sorted(self._values)
        self._index = {name: i for i, name in enumerate(self.names)}
        self.reboot_required = frozenset(n for n in reboot_required if n in self._values)
        self._at_boot: dict[str, ParamValue] = {}
        self.boot()

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __len__(self) -> int:
        return len(self.names)

    def boot(self) -> None:
        """Take the stored values of the reboot-required parameters into effect (a (re)boot)."""
        self._at_boot = {name: self._values[name][0] for name in self.reboot_required}

    def get(self, name: str) -> ParamValue:
        """The stored value (what PARAM_VALUE reports)."""
        return self._values[name][0]  # type: ignore[no-any-return,unused-ignore]

    def applied(self, name: str) -> ParamValue:
        """The value in effect: the boot-time value of a reboot-required parameter, else the stored one."""
        if name in self._at_boot:
            return self._at_boot[name]
        return self._values[name][0]  # type: ignore[no-any-return,unused-ignore]

    def pending_reboot(self) -> list[str]:
        """Reboot-required parameters whose stored value is not in effect yet."""
        return sorted(n for n, v in self._at_boot.items() if self._values[n][0] != v)

    def type_of(self, name: str) -> int:
        """MAV_PARAM_TYPE of a parameter."""
        return int(self._values[name][1])

    def index_of(self, name: str) -> int:
        """PX4's index of a parameter (position in the sorted names)."""
        return self._index[name]

    def set_value(self, name: str, value: ParamValue) -> None:
        """Store a value given as a number (validated through the wire encoding for integers)."""
        entry = self._values[name]
        if entry[1] == px4.MAV_PARAM_TYPE_REAL32:
            entry[0] = float(value)
        else:
            entry[0] = px4.decode_param_value(px4.encode_param_value(value, entry[1]), entry[1])

    def set_wire(self, name: str, wire_value: float) -> None:
        """Store the float of a PARAM_SET bytewise in the parameter's own type (what PX4 does)."""
        entry = self._values[name]
        entry[0] = px4.decode_param_value(wire_value, entry[1])

    def wire(self, name: str) -> float:
        """The float a PARAM_VALUE carries for a parameter."""
        entry = self._values[name]
        return px4.encode_param_value(entry[0], entry[1])


def main(argv: list[str]) -> int:
    """``python -m arena_common.sim.params [PARAMETERS_JSON]``: regenerate :data:`DATA_FILE`."""
    source = Path(argv[1]) if len(argv) > 1 else px4_sitl_dir() / "parameters.json"
    try:
        n = write_reboot_data(source)
    except (OSError, ValueError) as exc:
        print(f"cannot read {source}: {exc}", file=sys.stderr)
        return 2
    print(f"{DATA_FILE}: {n} reboot-required parameters from {source}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
