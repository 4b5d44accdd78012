"""The documented wire contract: generated files match the code, golden vectors decode the same everywhere."""

from __future__ import annotations

import json
import math
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import msgspec
import pytest

from arena_common.core import keys, wire
from tests.helpers import REPO, TESTS
from tools import wiredoc

GOLDEN = TESTS / "golden"
JS_DIR = TESTS / "js"
VECTOR_FILES = sorted(GOLDEN.glob("*.json"))


def _load(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


def _same_float(a: float, b: float) -> bool:
    return struct.pack(">d", a) == struct.pack(">d", b) or (math.isnan(a) and math.isnan(b))


def strict_equal(a: Any, b: Any) -> bool:
    """Equal values of equal JSON types: 1 is not 1.0, True is not 1, -0.0 is not 0.0."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return _same_float(a, b)
    if isinstance(a, list):
        return len(a) == len(b) and all(strict_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(strict_equal(a[k], b[k]) for k in a)
    return bool(a == b)


_SPECIAL = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "-0": -0.0}


def js_equal(py: Any, js: Any) -> bool:
    """Does ``js`` (decode.mjs's tagged JSON) hold exactly the value Python's msgpack decoded?"""
    if py is None or isinstance(py, (bool, str)):
        return type(js) is type(py) and js == py
    if isinstance(py, int):
        if isinstance(js, dict):
            return js.keys() == {"$int"} and js["$int"] == str(py)
        return type(js) is int and js == py and abs(py) <= 2**53
    if isinstance(py, float):
        if isinstance(js, dict):
            return (
                js.keys() == {"$float"}
                and js["$float"] in _SPECIAL
                and _same_float(py, _SPECIAL[js["$float"]])
            )
        if type(js) not in (int, float) or not math.isfinite(py) or (py == 0 and math.copysign(1, py) < 0):
            return False
        return _same_float(py, float(js))
    if isinstance(py, bytes):
        return js == {"$bin": py.hex()}
    if isinstance(py, list):
        return isinstance(js, list) and len(js) == len(py) and all(map(js_equal, py, js))
    if isinstance(py, dict):
        return isinstance(js, dict) and py.keys() == js.keys() and all(js_equal(py[k], js[k]) for k in py)
    raise AssertionError(f"unexpected decoded type {type(py).__name__}")


def _without_nan(v: Any) -> Any:
    if isinstance(v, float) and math.isnan(v):
        return None
    if isinstance(v, list):
        return [_without_nan(x) for x in v]
    if isinstance(v, dict):
        return {k: _without_nan(x) for k, x in v.items()}
    return v


# -- generated files ---------------------------------------------------------------------------------


def test_checked_in_files_equal_what_the_code_generates() -> None:
    drift = wiredoc.drift(REPO)
    assert drift == [], "wire docs drift from the code; run `python -m tools.wiredoc`:\n" + "\n".join(drift)


def test_check_reports_changed_missing_and_stale_files_and_write_repairs_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    written = wiredoc.write(tmp_path)
    assert len(written) == len(wiredoc.generated())
    assert wiredoc.drift(tmp_path) == []
    assert wiredoc.main(["--check", "--root", str(tmp_path)]) == 0

    schema = tmp_path / "docs/schemas/arena.Pose.json"
    schema.write_text(schema.read_text().replace('"minimum": 0', '"minimum": 1', 1))
    (tmp_path / "tests/golden/estop_kill.json").unlink()
    (tmp_path / "tests/golden/pose_old.json").write_text("{}\n")
    (tmp_path / "docs/notes.md").write_text("not generated\n")  # other files are left alone
    assert wiredoc.drift(tmp_path) == [
        "docs/schemas/arena.Pose.json (changed)",
        "tests/golden/estop_kill.json (missing)",
        "tests/golden/pose_old.json (stale)",
    ]
    capsys.readouterr()
    assert wiredoc.main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "arena.Pose.json (changed)" in err and "3 file(s) drift" in err
    assert schema.read_text() != wiredoc.generated()["docs/schemas/arena.Pose.json"]  # --check wrote nothing

    assert wiredoc.main(["--root", str(tmp_path)]) == 0
    assert wiredoc.drift(tmp_path) == []
    assert not (tmp_path / "tests/golden/pose_old.json").exists()
    assert (tmp_path / "docs/notes.md").exists()


def test_check_runs_as_a_module() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "tools.wiredoc", "--check"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert "up to date" in proc.stdout


def test_every_type_has_a_schema_file_and_vectors() -> None:
    vectors = [_load(p) for p in VECTOR_FILES]
    assert {v["type"] for v in vectors} == set(wire.REGISTRY)
    for name, cls in wire.REGISTRY.items():
        assert _load(REPO / f"docs/schemas/arena.{name}.json") == wire.json_schema(cls)


def test_schemas_agree_with_msgspecs_own_schema_of_the_structs() -> None:
    """Ours describes the JSON rendering (NaN as null, no float64 limits); the fields, their JSON types and
    which are required are msgspec's."""
    for cls in wire.REGISTRY.values():
        (_,), defs = msgspec.json.schema_components([cls])
        theirs, ours = defs[cls.__name__], wire.json_schema(cls)
        assert list(ours["properties"]) == list(theirs["properties"]), cls
        assert ours["required"] == theirs.get("required", []), cls
        _same_properties(cls, ours, theirs, defs)


def _same_properties(cls: type, ours: dict[str, Any], theirs: dict[str, Any], defs: dict[str, Any]) -> None:
    for name, prop in ours["properties"].items():
        if "type" in prop:
            assert prop["type"] == theirs["properties"][name]["type"], (cls, name)
        else:  # optional (anyOf the type and null) or NaN allowed (a number or null)
            assert {"type": "null"} in prop["anyOf"], (cls, name)
        if prop.get("type") == "array" and prop["items"].get("type") == "object":  # an ``items`` field
            theirs_items = theirs["properties"][name]
            item = defs[theirs_items["items"]["$ref"].rsplit("/", 1)[1]]
            assert prop.get("maxItems") == theirs_items.get("maxItems"), (cls, name)
            assert list(prop["items"]["properties"]) == list(item["properties"]), (cls, name)
            assert prop["items"]["required"] == item.get("required", []), (cls, name)
            _same_properties(cls, prop["items"], item, defs)


def test_wire_md_documents_every_key_type_field_and_encoding() -> None:
    text = (REPO / "docs/wire.md").read_text(encoding="utf-8")
    for k in keys.KEYS:
        assert f"| `{k.pattern}` | {k.payload} | {k.qos} |" in text
    for cls in wire.REGISTRY.values():
        assert f"### `arena.{cls.SCHEMA}/{cls.VERSION}`" in text
        assert f"`{cls.encoding()}`" in text
        for _, spec in cls._specs:
            assert f"| `{spec.wire}` |" in text
            if spec.item is not None:  # the element type's own table follows the type's
                section = text.split(f"### `arena.{cls.SCHEMA}/", 1)[1].split("\n### ", 1)[0]
                assert f"| `{spec.wire}` | {spec.item.SCHEMA}[] |" in section
                table = section.split(f"Each element of `{spec.wire}` is a map, `{spec.item.SCHEMA}`", 1)[1]
                for _, element in spec.item._specs:
                    assert f"| `{element.wire}` |" in table, (cls, element.wire)
    for op in wire.COMMAND_OPS:
        assert f"`{op}`" in text


def test_vectors_cover_the_encodings_other_decoders_get_wrong() -> None:
    seen: set[str] = set()
    for path in VECTOR_FILES:
        for _, _, _, meaning in wiredoc.annotate(bytes.fromhex(_load(path)["hex"])):
            seen.add(meaning.split(" ")[0].rstrip(","))
            if meaning.startswith("float64"):
                seen.add(meaning)
    wanted = {"uint64", "uint32", "uint8", "negative", "positive", "map", "array", "fixstr", "true", "false"}
    assert wanted <= seen
    assert {"float64 NaN", "float64 -0.0"} <= seen
    assert any(_load(p)["hex"].startswith("de") for p in VECTOR_FILES), "no map16 (more than 15 fields)"


def test_annotate_walks_every_byte_and_refuses_truncated_input() -> None:
    raw = msgpack.packb({"a": [1, -1, -200, 70000, 2**40, -(2**40), 1.5, None, True, "x" * 40, b"\x00\x01"]})
    rows = wiredoc.annotate(raw)
    assert b"".join(chunk for _, chunk, _, _ in rows) == raw
    meanings = [m for *_, m in rows]
    assert "int16 -200" in meanings and "int64 -1099511627776" in meanings and "bin8, 2 bytes" in meanings
    with pytest.raises(wiredoc.WireDocError, match="truncated"):
        wiredoc.annotate(raw[:-1])
    with pytest.raises(wiredoc.WireDocError, match="trailing"):
        wiredoc.annotate(raw + b"\x00")
    with pytest.raises(wiredoc.WireDocError, match="not UTF-8"):
        wiredoc.annotate(b"\xa2\xff\xfe")
    with pytest.raises(wiredoc.WireDocError, match="0xc1"):
        wiredoc.annotate(b"\xc1")
    state = bytes.fromhex(_load(GOLDEN / "state_flying.json")["hex"])
    for cut in range(len(state)):  # every truncation is reported as such, never as another exception
        with pytest.raises(wiredoc.WireDocError, match="truncated"):
            wiredoc.annotate(state[:cut])


# -- golden vectors in Python ------------------------------------------------------------------------


@pytest.mark.parametrize("path", VECTOR_FILES, ids=lambda p: p.stem)
def test_vector_decodes_in_python_to_its_json_and_re_encodes_to_its_bytes(path: Path) -> None:
    vec = _load(path)
    cls = wire.REGISTRY[vec["type"]]
    raw = bytes.fromhex(vec["hex"])
    assert vec["name"] == path.stem
    assert vec["encoding"] == cls.encoding() and vec["schema"] == f"arena.{cls.SCHEMA}/{cls.VERSION}"

    payload = wire.decode_any(vec["key"], raw, vec["encoding"])
    assert type(payload) is cls
    assert strict_equal(wire.to_jsonable(payload), vec["json"])
    assert payload.encode() == raw
    assert strict_equal(_without_nan(msgpack.unpackb(raw)), vec["json"])
    if cls is not wire.CommandResult:  # replies travel on the command's key
        assert type(wire.decode_any(vec["key"], raw)) is cls


@pytest.mark.parametrize("path", VECTOR_FILES, ids=lambda p: p.stem)
def test_vector_json_validates_against_its_schema(path: Path) -> None:
    vec = _load(path)
    schema = _load(REPO / f"docs/schemas/arena.{vec['type']}.json")
    validator = jsonschema.Draft202012Validator(schema)
    jsonschema.Draft202012Validator.check_schema(schema)
    validator.validate(vec["json"])

    # The schema is not vacuous: each required field missing, or of the wrong type, is refused.
    for name in schema["required"]:
        broken = {k: v for k, v in vec["json"].items() if k != name}
        assert not validator.is_valid(broken), f"missing {name} accepted"
        assert not validator.is_valid(vec["json"] | {name: {"wrong": "type"}}), f"bad {name} accepted"
    # Nor inside the elements of an array of maps.
    for name, prop in schema["properties"].items():
        item = prop.get("items", {})
        for i, element in enumerate(vec["json"].get(name, []) if item.get("type") == "object" else []):
            for field in item["required"]:
                others = [e for j, e in enumerate(vec["json"][name]) if j != i]
                broken = {k: v for k, v in element.items() if k != field}
                assert not validator.is_valid(vec["json"] | {name: [*others, broken]}), f"{name}[].{field}"
                wrong = element | {field: {"wrong": "type"}}
                assert not validator.is_valid(vec["json"] | {name: [*others, wrong]}), f"{name}[].{field}"


def test_mocap_frame_schema_validates_frames_and_refuses_bad_elements() -> None:
    validator = jsonschema.Draft202012Validator(wire.json_schema(wire.MocapFrame))
    body = wire.MocapBody(v="d1", id=1, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)
    frame = wire.MocapFrame(t=1, fn=1, b=(body, body.replace(v="d2", ok=False, err=0.001)))
    jsonable = wire.to_jsonable(frame)
    assert jsonable["b"][0]["err"] is None  # NaN, as JSON has it
    validator.validate(jsonable)
    validator.validate(wire.to_jsonable(frame.replace(b=())))
    validator.validate(wire.to_jsonable(frame.replace(b=(body,) * 256)))
    bad = [
        jsonable | {"b": [wire.to_jsonable(body)] * 257},
        jsonable | {"b": "x"},
        jsonable | {"b": [5]},
        jsonable | {"b": [jsonable["b"][0] | {"p": [0.0, "x", 0.0]}]},
        jsonable | {"b": [jsonable["b"][0] | {"q": [1.0, 0.0, 0.0]}]},
        jsonable | {"b": [jsonable["b"][0] | {"ok": 1}]},
        jsonable | {"b": [jsonable["b"][0] | {"v": 7}]},
    ]
    for data in bad:
        assert not validator.is_valid(data), data


# -- golden vectors in JavaScript ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def node_decoded() -> dict[str, Any]:
    node = shutil.which("node")
    if node is None:
        pytest.skip(
            "node is not on PATH: the JavaScript cross-check of the golden vectors needs Node.js >= 18"
        )
    lock = _load(JS_DIR / "package-lock.json")
    want = lock["packages"]["node_modules/@msgpack/msgpack"]["version"]
    installed = JS_DIR / "node_modules/@msgpack/msgpack/package.json"
    if not installed.is_file() or _load(installed)["version"] != want:
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip("npm is not on PATH: cannot install @msgpack/msgpack for the JavaScript cross-check")
        proc = subprocess.run(
            [npm, "ci", "--prefix", str(JS_DIR), "--no-audit", "--no-fund"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, f"npm ci in {JS_DIR} failed:\n{proc.stdout}\n{proc.stderr}"
    proc = subprocess.run(
        [node, str(JS_DIR / "decode.mjs"), str(GOLDEN)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, f"decode.mjs failed:\n{proc.stderr}"
    decoded: dict[str, Any] = json.loads(proc.stdout)
    return decoded


def test_node_decodes_every_golden_vector_exactly_as_python(node_decoded: dict[str, Any]) -> None:
    vectors = {p.stem: _load(p) for p in VECTOR_FILES}
    assert node_decoded.keys() == vectors.keys()
    for name, vec in vectors.items():
        py = msgpack.unpackb(bytes.fromhex(vec["hex"]), raw=False)
        assert js_equal(py, node_decoded[name]), f"{name}: node decoded {node_decoded[name]!r}, python {py!r}"
    # Times above 2^53 reached JavaScript as exact BigInts.
    assert node_decoded["pose_tracked"]["t"] == {"$int": "1700000000123456789"}
    # Maps inside an array (MocapFrame's bodies) keep their fields, NaN included.
    assert node_decoded["mocapframe_two_bodies"]["b"][1]["err"] == {"$float": "nan"}
    assert node_decoded["mocapframe_empty"]["b"] == []


def test_the_js_comparison_catches_the_mistakes_it_exists_for() -> None:
    t = 1_700_000_000_123_456_789
    assert js_equal({"t": t, "v": [0.1, -0.0]}, {"t": {"$int": str(t)}, "v": [0.1, {"$float": "-0"}]})
    assert not js_equal(t, float(t))  # a rounded JavaScript number
    assert not js_equal(t, {"$int": str(t + 1)})
    assert not js_equal(0.1, 0.1000000000000001)
    assert not js_equal(-0.0, 0)
    assert not js_equal(0.0, {"$float": "-0"})
    assert not js_equal(math.nan, None)
    assert js_equal(math.nan, {"$float": "nan"})
    assert not js_equal(True, 1)
    assert not js_equal({"a": 1}, {"a": 1, "b": 2})
    assert not js_equal([1, 2], [1])
