"""The autopilot's parameters from a program: ``d1.params.get("MPC_XY_VEL_MAX")``, ``d1.params.set(…)``.

The gateway speaks the parameter protocol: PX4's INT32 parameters travel bytewise inside PARAM_SET /
PARAM_VALUE floats, which it packs and unpacks, so an integer parameter reads and writes as a Python
``int`` and a REAL32 one as a ``float``.  A write is read back and compared before it is confirmed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from arena_common.core import keys
from arena_common.mavlink import px4

if TYPE_CHECKING:
    from arena_common.client.vehicle import Vehicle

__all__ = ["Params"]

_FLOAT_TYPES = (px4.MAV_PARAM_TYPE_REAL32, px4.MAV_PARAM_TYPE_REAL64)  # read as floats, the rest as integers


def _typed(value: float, ptype: int) -> int | float:
    return float(value) if ptype in _FLOAT_TYPES else round(value)


class Params:
    """One vehicle's parameters (a facet of :class:`~arena_common.client.vehicle.Vehicle`)."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.vehicle = vehicle

    def get(self, name: str, timeout: float = 5.0) -> int | float:
        """The parameter's value (``int`` for integer types); :class:`CommandError` if unknown."""
        keys.validate_name(name, "parameter name")
        res = self.vehicle.command("param_get", timeout, name=name)
        return _typed(float(res.value["value"]), int(res.value.get("type", px4.MAV_PARAM_TYPE_REAL32)))

    def set(self, name: str, value: float, timeout: float = 5.0) -> int | float:
        """Write the parameter and return the value the autopilot confirmed (read back).

        An integer parameter given a float with a fraction is refused here (ValueError) rather than
        silently truncated.
        """
        keys.validate_name(name, "parameter name")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: a parameter value is a number, got {value!r}")
        if isinstance(value, float) and not value.is_integer():
            got = self.vehicle.command("param_get", timeout, name=name)
            if int(got.value.get("type", px4.MAV_PARAM_TYPE_REAL32)) not in _FLOAT_TYPES:
                raise ValueError(f"{name} is an integer parameter: {value!r} is not an integer")
        res = self.vehicle.command("param_set", timeout, name=name, value=value)
        return _typed(float(res.value["value"]), int(res.value.get("type", px4.MAV_PARAM_TYPE_REAL32)))

    def __getitem__(self, name: str) -> int | float:
        return self.get(name)

    def __setitem__(self, name: str, value: float) -> None:
        self.set(name, value)
