"""Runs in a virtual environment of ROS 2's own wheels (rclpy and the message packages), never in the
arena's: tests/system/test_ros2_rclpy.py feeds it a JSON list of requests on stdin and reads a JSON list
of answers on stdout, one for each.

- ``{"op": "decode", "type": "pkg/msg/Name", "hex": CDR}`` → ``{"fields": {...}}``: the message as real
  ``rclpy.serialization.deserialize_message`` reads it, every field by name (sequences as lists, a
  ``byte`` as its number, NaN as JSON's NaN);
- ``{"op": "encode", "type": ..., "fields": {...}}`` → ``{"hex": CDR}``: the message built with the
  package's own class and serialized by ``rclpy.serialization.serialize_message``;
- ``{"op": "hash", "type": ...}`` → ``{"hash": "RIHS01_…"}``: the type hash in the package's
  ``share/<pkg>/msg/<Name>.json``, as rosidl generated it;

or ``{"missing": reason}`` when the message's package is not installed here.
"""

from __future__ import annotations

import importlib
import json
import os
import sys
from typing import Any


def _cls(type_name: str) -> Any:
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def _to_json(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {f: _to_json(getattr(value, f)) for f in value.get_fields_and_field_types()}
    if isinstance(value, bytes):  # a ``byte`` field (one byte), or bytes of a ``byte[]``
        return value[0] if len(value) == 1 else list(value)
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return [_to_json(v) for v in value]  # list, array.array, numpy array


def _fill(msg: Any, fields: dict[str, Any]) -> Any:
    for name, value in fields.items():
        current = getattr(msg, name)
        if isinstance(value, dict) and hasattr(current, "get_fields_and_field_types"):
            _fill(current, value)
        else:
            setattr(msg, name, value)
    return msg


def answer(req: dict[str, Any]) -> dict[str, Any]:
    from rclpy.serialization import deserialize_message, serialize_message

    type_name = req["type"]
    try:
        cls = _cls(type_name)
    except ImportError as exc:
        return {"missing": f"{type(exc).__name__}: {exc}"}
    if req["op"] == "decode":
        return {"fields": _to_json(deserialize_message(bytes.fromhex(req["hex"]), cls))}
    if req["op"] == "encode":
        return {"hex": serialize_message(_fill(cls(), req["fields"])).hex()}
    pkg, kind, name = type_name.split("/")
    with open(os.path.join(sys.prefix, "share", pkg, kind, f"{name}.json")) as f:
        hashes = json.load(f)["type_hashes"]
    return {"hash": next(h["hash_string"] for h in hashes if h["type_name"] == type_name)}


if __name__ == "__main__":
    json.dump([answer(r) for r in json.load(sys.stdin)], sys.stdout)
