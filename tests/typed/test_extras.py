"""An optional extra that is missing, as a user meets it: the project installed by ``pip install`` without
extras, in a venv of its own, and a command that needs one typed there.  It says which extra and the line
that installs it, exits 2, and prints no traceback."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from arena_common.core.services import EXTRAS
from tests.helpers import REPO

pytestmark = pytest.mark.timeout(420)
INSTALL_S = 300.0  # a venv and the project's required dependencies from pip's cache: ~40 s on 2 cores


@pytest.fixture(scope="module")
def bare(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The ``arena`` console script of a venv holding the project and its required dependencies only."""
    venv = tmp_path_factory.mktemp("no-extras") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=INSTALL_S)
    # From a copy of the checkout: pip builds in the source tree, and the checkout keeps no build/ of its own.
    source = tmp_path_factory.mktemp("source") / "flying-arena"
    junk = (
        ".git",
        ".venv",
        "build",
        "*.egg-info",
        "__pycache__",
        "node_modules",
        "recordings",
        "bench-results",
    )
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(*junk))
    pip = [str(venv / "bin/python"), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(source)]
    done = subprocess.run(pip, capture_output=True, text=True, timeout=INSTALL_S)
    if done.returncode != 0:
        pytest.skip(f"pip install of the project into a fresh venv failed: {done.stderr[-2000:]}")
    python = str(venv / "bin/python")
    for extra, modules in EXTRAS.items():
        probe = f"import importlib.util as u; raise SystemExit(any(u.find_spec(m) for m in {modules!r}))"
        assert subprocess.run([python, "-c", probe], timeout=60).returncode == 0, f"{extra} installed anyway"
    yield venv / "bin/arena"


def _typed(arena: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(arena), *args], capture_output=True, text=True, timeout=120, cwd=cwd)


def test_a_service_without_its_extra_names_it(bare: Path, tmp_path: Path) -> None:
    done = _typed(bare, "run", "ros2", "-c", str(REPO / "deploy/sim.toml"), cwd=tmp_path)
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    assert "arena run ros2: this needs the optional extra 'ros2'" in done.stderr, done.stderr
    assert "pip install 'flying-arena[ros2]'" in done.stderr, done.stderr


def test_the_service_as_arena_up_and_systemd_start_it_names_it(bare: Path, tmp_path: Path) -> None:
    python = bare.parent / "python"
    argv = [str(python), "-m", "services.ros2", "-c", str(REPO / "deploy/sim.toml")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    assert "the ROS 2 service: this needs the optional extra 'ros2'" in done.stderr, done.stderr


def test_an_export_without_its_extra_names_it(bare: Path, tmp_path: Path) -> None:
    recording = tmp_path / "flight.mcap"
    recording.write_bytes(b"")  # the extra is checked before the file is read
    done = _typed(bare, "export", "--ros2", str(recording), cwd=tmp_path)
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    assert "--ros2: this needs the optional extra 'ros2'" in done.stderr, done.stderr


def test_the_same_install_runs_what_needs_no_extra(bare: Path, tmp_path: Path) -> None:
    """The venv is the project as installed (not a broken one): a service without extras starts its help."""
    done = _typed(bare, "run", "gateway", "--help", cwd=tmp_path)
    assert done.returncode == 0, done
    assert "--vehicle" in done.stdout
