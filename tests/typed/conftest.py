"""The typed tier (``make test-typed``): every command a user reads, typed as a user types it."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.typed.harness import ARENA, Command, commands


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.typed)
            if not ARENA.exists():
                item.add_marker(pytest.mark.skip(reason=f"no arena console script at {ARENA} (make setup)"))


@pytest.fixture
def typed(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    """Start ``arena`` command lines in ``tmp_path`` (no ``deploy/`` there: a default config cannot be
    read); each one, and every process naming ``tmp_path``, is killed at the end."""
    with commands(tmp_path) as start:
        yield start
