"""The layer check (tools/layers.py) on the real tree, and on a tree that breaks each of its rules once."""

from __future__ import annotations

from pathlib import Path

from tools import layers

FILES = {
    # A clean little arena: every import points down.
    "arena_common/__init__.py": "from arena_common.client.api import Arena\n",
    "arena_common/core/__init__.py": "",
    "arena_common/core/wire.py": "",
    "arena_common/bus/__init__.py": "",
    "arena_common/bus/security.py": "from arena_common.core import wire\n",
    "arena_common/mocap/__init__.py": "",
    "arena_common/mocap/natnet.py": "from arena_common.core import wire\n",
    "arena_common/runtime/__init__.py": "",
    "arena_common/runtime/service.py": "from arena_common.bus import security\n",
    "arena_common/pipeline/__init__.py": "",
    "arena_common/pipeline/ingest.py": "from arena_common.runtime import service\n",
    "arena_common/client/__init__.py": "",
    "arena_common/client/api.py": "from arena_common.core import wire\nArena = object\n",
    "arena_common/gateway/__init__.py": "",
    "arena_common/gateway/gateway.py": "from arena_common.runtime import service\n",
    "arena_common/sim/__init__.py": "",
    "arena_common/sim/world.py": "from arena_common.core import wire\n",
    "arena_common/cli/__init__.py": "",
    "arena_common/core/services.py": 'SERVICES = (S("x", "services.ingest"), S("s", "services.sim_world"))\n',
    "services/__init__.py": "",
    "services/ingest.py": "from arena_common.pipeline import ingest\ndef main(): ...\ndef cli(): ...\n",
    "services/sim_world.py": "from arena_common.sim import world\ndef main(): ...\ndef cli(): ...\n",
    "bench/__init__.py": "",
    "bench/run.py": "from arena_common.sim import world\nfrom tools import vectors\n",
    "tools/__init__.py": "",
    "tools/vectors.py": "from arena_common.core import wire\n",
    "examples/hover.py": "from arena_common import Arena\n",
}

BREAKS = {
    # rule 1: a layer above, a sibling
    "arena_common/core/bad_up.py": (
        "from arena_common.bus import security\n",
        "core imports arena_common.bus.security, a layer above it",
    ),
    "arena_common/gateway/bad_sibling.py": (
        "from arena_common.client import api\n",
        "gateway imports its sibling client",
    ),
    # rule 2: the client never loads the runtime
    "arena_common/client/bad_runtime.py": (
        "from arena_common.runtime import service\n",
        "client never loads runtime",
    ),
    # rule 3: the simulator only for the simulator, services.sim_* and bench
    "services/bad_sim.py": (
        "from arena_common.sim import world\ndef main(): ...\ndef cli(): ...\n",
        "only the simulator, services.sim_* and bench import arena_common.sim",
    ),
    # rule 4: the library imports no services, bench, tools or tests
    "arena_common/gateway/bad_foreign.py": (
        "import services.ingest\n",
        "the library imports services.ingest",
    ),
    # rule 5: services
    "services/bad_other.py": (
        "from services import ingest\ndef main(): ...\ndef cli(): ...\n",
        "a service imports another service",
    ),
    "services/orphan.py": (
        "def main(): ...\ndef cli(): ...\n",
        "services/orphan.py: not in the table of services",
    ),
    "services/nomain.py": ("def cli(): ...\n", "services/nomain.py: a service module without `main`"),
    # rule 6: bench, tools, examples
    "tools/bad_bench.py": ("from bench import run\n", "tools imports bench.run"),
    "examples/bad_example.py": (
        "from arena_common.runtime import service\n",
        "an example imports arena_common.runtime.service",
    ),
}
# rule 7: the user's API loads no service runtime
USER_API = ("arena_common/__init__.py", "from arena_common.runtime import service\nArena = object\n")


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_project_keeps_its_layers() -> None:
    assert layers.problems() == []


def test_a_clean_tree_passes(tmp_path: Path) -> None:
    _write(tmp_path, FILES)
    assert layers.problems(tmp_path) == []


def test_each_rule_is_enforced(tmp_path: Path) -> None:
    _write(tmp_path, FILES)
    _write(tmp_path, {rel: text for rel, (text, _) in BREAKS.items()})
    (tmp_path / layers.NAMERS[0]).write_text(
        'SERVICES = (S("x", "services.ingest"), S("s", "services.sim_world"), S("b", "services.bad_sim"),'
        ' S("o", "services.bad_other"), S("n", "services.nomain"), S("g", "services.gone"))\n'
    )
    _write(tmp_path, dict([USER_API]))
    found = "\n".join(layers.problems(tmp_path))
    for rel, (_, message) in BREAKS.items():
        assert message in found, f"{rel}: expected {message!r} in:\n{found}"
    assert f"{layers.NAMERS[0]}: names services.gone, which does not exist" in found
    assert "`import arena_common` loads arena_common.runtime.service" in found
    assert "services/ingest.py" not in found and "services/sim_world.py" not in found  # the good ones


def test_the_picture_in_the_docs_is_drawn_from_the_rules(tmp_path: Path) -> None:
    doc = tmp_path / layers.DOC
    doc.parent.mkdir(parents=True)
    doc.write_text(f"# x\n{layers.BEGIN}\nold picture\n{layers.END}\n")
    assert any("stale" in p for p in layers.problems(tmp_path, probe=False))
    layers.write_picture(tmp_path)
    assert not [p for p in layers.problems(tmp_path, probe=False) if "picture" in p]
    assert "client/ never imports runtime/" in doc.read_text()
