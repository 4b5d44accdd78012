"""Every command a user is told to type has a test that types it: the typed tier's lint.

The commands come from three places a user reads: the fenced shell blocks of ``README.md`` and
``docs/*.md``, ``arena --help`` (every sub-command, walked from the typer app), and the systemd units of
``deploy/systemd/`` (their ``ExecStart``).  A test claims a command with the marker
``@pytest.mark.covers("...")`` (the command as the docs write it, ``.venv/bin/`` and comments left out;
``arena X Y`` for a sub-command; ``unit NAME`` for a unit).  ``python -m tools.typed --check`` (``make
lint``) fails naming every command no test claims, and every claim that names no command any more.

Commands that run on other machines or as the administrator (``sudo``, ``chronyc``, ``ssh``…) and the
test targets CI itself runs are listed in :data:`NOT_RUN_HERE` with the reason.
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^[ \t]*```(sh|bash|shell|console)[ \t]*\n(.*?)^[ \t]*```", re.S | re.M)

#: Commands no test of this machine types, with the reason (prefix → why).
NOT_RUN_HERE: dict[str, str] = {
    "sudo ": "administration of a lab computer (packages, chrony, systemd): not on a test machine",
    "echo ": "writes a lab computer's chrony configuration (piped to sudo tee)",
    "chronyc ": "chrony's own client, on a lab computer",
    "ssh ": "reaches another computer",
    "export ": "a ROS 2 user's shell settings, on a computer with ROS 2 (none can be installed here)",
    "ros2 ": "ROS 2's own tools (no ROS 2 here: tests/unit/ros2/ test the protocol they speak)",
    "rviz2": "ROS 2's 3D viewer (no ROS 2 here: tests/unit/ros2/ test the protocol it speaks)",
    "make test-radio": "PX4 SITL over a slow radio link, three flights (~4 min): by hand, outside CI's 45 minutes",
    "make test": "CI runs every test target itself (.ci/run); make test-typed is this tier",
    "make lint": "CI runs it (.ci/run)",
    "make docs": "CI runs it (.ci/run)",
}


@dataclass(frozen=True, slots=True)
class Command:
    """One command a user reads: where, and the text the tests claim it by."""

    where: str
    text: str


def _clean(line: str) -> str:
    line = re.sub(r"\s+#\s.*$", "", line.strip()) if not line.strip().startswith("#") else ""
    line = line.replace(".venv/bin/", "")
    return re.sub(r"\s+", " ", line).strip()


def doc_commands(repo: Path = REPO) -> list[Command]:
    """Every command line of the fenced shell blocks of README.md and docs/*.md (quoted lines joined)."""
    found: list[Command] = []
    for path in [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        for block in FENCE.finditer(text):
            first = text[: block.start(2)].count("\n") + 1
            pending, start = "", 0
            for i, raw in enumerate(block.group(2).splitlines()):
                if not pending:
                    start = first + i
                code = raw if pending else re.sub(r"\s+#\s.*$", "", raw)  # an apostrophe in a comment
                pending = f"{pending}\n{raw}" if pending else raw
                quoted = pending if "\n" in pending else code
                if quoted.count("'") % 2 or pending.rstrip().endswith("\\"):
                    continue  # a quoted string or a continued line goes on
                cmd = _clean(pending) if "\n" not in pending else pending.strip()
                pending = ""
                if cmd:
                    found.append(Command(f"{path.relative_to(repo)}:{start}", cmd))
    return found


def cli_commands() -> list[Command]:
    """``arena X [Y]`` for every command of ``arena --help`` and its groups."""
    import typer

    from arena_common.cli import app

    root = typer.main.get_command(app)
    found: list[Command] = []

    def walk(cmd: object, path: list[str]) -> None:
        sub = getattr(cmd, "commands", None)
        if sub:
            for name, child in sorted(sub.items()):
                walk(child, [*path, name])
        else:
            found.append(Command("arena --help", " ".join(["arena", *path])))

    walk(root, [])
    return found


def unit_commands(repo: Path = REPO) -> list[Command]:
    """``unit NAME`` for every systemd unit template that starts something."""
    return [
        Command(f"deploy/systemd/{p.name}", f"unit {p.name}")
        for p in sorted((repo / "deploy" / "systemd").glob("*.service"))
        if "ExecStart=" in p.read_text(encoding="utf-8")
    ]


def claims(repo: Path = REPO) -> dict[str, list[str]]:
    """Command text → the tests (``file::function``) that claim it with ``@pytest.mark.covers``."""
    out: dict[str, list[str]] = {}
    for path in sorted((repo / "tests").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for dec in node.decorator_list:
                if (
                    isinstance(dec, ast.Call)
                    and isinstance(dec.func, ast.Attribute)
                    and dec.func.attr == "covers"
                ):
                    for arg in dec.args:
                        if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                            out.setdefault(arg.value, []).append(f"{path.relative_to(repo)}::{node.name}")
    return out


def not_run_here(text: str) -> str:
    """Why ``text`` is typed by no test here ('' when a test must type it)."""
    return next((why for prefix, why in NOT_RUN_HERE.items() if text.startswith(prefix)), "")


def check(repo: Path = REPO) -> list[str]:
    """Problems: commands no test claims, claims that name no command."""
    commands = [*doc_commands(repo), *cli_commands(), *unit_commands(repo)]
    claimed = claims(repo)
    problems = [
        f"{c.where}: `{c.text}` is typed by no test (add @pytest.mark.covers({c.text!r}) to one that runs it)"
        for c in commands
        if c.text not in claimed and not not_run_here(c.text)
    ]
    known = {c.text for c in commands}
    for text, tests in sorted(claimed.items()):
        if text not in known:
            problems.append(f"{tests[0]}: claims `{text}`, which no doc, --help or unit has any more")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="fail on a command no test types")
    parser.add_argument("--list", action="store_true", help="list every command and its tests")
    args = parser.parse_args(argv)
    if args.list:
        claimed = claims()
        for c in [*doc_commands(), *cli_commands(), *unit_commands()]:
            who = ", ".join(claimed.get(c.text, [])) or not_run_here(c.text) or "NOT TYPED"
            print(f"{c.where:28s} {c.text:60s} {who}")
    problems = check()
    for p in problems:
        print(p, file=sys.stderr)
    if not problems and args.check:
        print("typed: every command a user reads is typed by a test")
    return 1 if problems and args.check else 0


if __name__ == "__main__":
    sys.exit(main())
