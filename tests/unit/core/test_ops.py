"""One table of operations (arena_common/core/ops.py), and both ends of every one implemented from it."""

from __future__ import annotations

import operator

import pytest

from arena_common.client.aio import AsyncVehicle
from arena_common.client.vehicle import Vehicle
from arena_common.core import ops, wire
from arena_common.gateway.commands import CommandExecutor


def test_every_vehicle_operation_has_a_gateway_method() -> None:
    """The gateway answers exactly the table's vehicle operations, each with its method ``_<op>``."""
    for op in ops.vehicle_ops():
        assert callable(getattr(CommandExecutor, f"_{op.name}", None)), op.name


@pytest.mark.parametrize("op", [o for o in ops.OPS.values() if o.client], ids=operator.attrgetter("name"))
def test_every_operation_a_program_sends_has_its_method_in_both_facades(op: ops.Op) -> None:
    owner: object = Vehicle
    *facets, method = op.client.split(".")
    if facets:  # a facet of the vehicle: vehicle.params.get
        from arena_common.client.params import Params

        owner = {"params": Params}[facets[0]]
    assert callable(getattr(owner, method)), f"Vehicle has no {op.client} for {op.name}"
    assert callable(getattr(AsyncVehicle, op.aio_method)), (
        f"AsyncVehicle has no {op.aio_method} for {op.name}"
    )


def test_the_wire_names_every_operation_of_the_table() -> None:
    assert tuple(ops.OPS) == wire.COMMAND_OPS


def test_arguments_are_checked_by_the_table() -> None:
    assert ops.check("takeoff", {}) == {"height": 1.0}
    assert ops.check("goto", {"p": [1, 2, -1]}) == {
        "p": (1.0, 2.0, -1.0),
        "yaw": None,
        "tol": None,
        "wait": False,
    }
    bad = [
        ("takeoff", "height", "1", "takeoff: argument 'height' must be a finite number, got '1'"),
        ("takeoff", "height", float("nan"), "must be a finite number"),
        ("takeoff", "speed", 1.0, "takeoff: unknown argument 'speed' (it takes: height)"),
        ("goto", "p", [1, 2], "goto: argument 'p' must be [north, east, down]"),
        ("goto", "wait", 1, "goto: argument 'wait' must be true or false"),
        ("mode", "mode", "", "mode: argument 'mode' must be a non-empty string"),
        ("param_set", "name", "X", "param_set: argument 'value' is missing"),
    ]
    for name, arg, value, message in bad:
        args: dict[str, object] = {"p": [0, 0, -1]} if name == "goto" else {}
        args[arg] = value
        with pytest.raises(ops.OpError) as err:
            ops.check(name, args)
        assert message in str(err.value), (name, arg, value)
    with pytest.raises(ops.OpError, match=r"'fly' is no operation \(known: arm, disarm"):
        ops.check("fly", {})


def test_the_client_refuses_what_the_table_refuses_before_sending() -> None:
    class NoArena:  # anything the vehicle would touch after the check fails loudly
        config = None

        def __getattr__(self, name: str) -> object:
            raise AssertionError(f"sent anyway ({name})")

    v = Vehicle.__new__(Vehicle)
    v.arena = NoArena()  # type: ignore[assignment]
    v.name = "d1"
    with pytest.raises(ops.OpError, match="takeoff: argument 'height' must be a finite number"):
        v.command("takeoff", 1.0, height="high")
