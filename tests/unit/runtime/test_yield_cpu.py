"""The recorder and the live viewer yield the CPU to the vision pipeline, and the pipeline's stages go first,
under autogroup scheduling too.

Linux's autogroup scheduling (on by default in most distributions) shares the CPU between sessions first and
weighs a niceness only among the processes of one session, and ``arena up`` starts every service in a session
of its own: a viewer at niceness 10 then took as much of the CPU as each stage of the pipeline, and the first
arm of a vehicle was refused for stale vision.  Each check reads what the kernel says (``/proc``): niceness,
session, scheduling group, CPU time; none judges a duration.
"""

from __future__ import annotations

import os
import re
import signal
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from arena_common.core.services import ROUTER_CPU, SERVICES
from arena_common.runtime.service import BACKGROUND_NICE, VISION_NICE
from tests.helpers import PYTHON, Proc, free_port, service_argv, wait_for, write_config

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/autogroup").exists(), reason="Linux autogroup scheduling is not in this kernel"
)


def stat(pid: int) -> tuple[int, int, int]:
    """``(parent, session, niceness)`` of ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[1]), int(fields[3]), int(fields[16])


def group(pid: int) -> tuple[str, int]:
    """``(name, niceness)`` of the autogroup of ``pid`` (``/autogroup-42 nice 0``)."""
    name, _, nice = Path(f"/proc/{pid}/autogroup").read_text().split()
    return name, int(nice)


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if stat(int(entry.name))[0] == pid:
                    found.append(int(entry.name))
            except (OSError, IndexError, ValueError):
                pass  # gone meanwhile
    return found


def cpu_ns(pid: int) -> int:
    """CPU time of ``pid`` so far (``/proc/<pid>/schedstat``), ns."""
    return int(Path(f"/proc/{pid}/schedstat").read_text().split()[0])


def test_the_recorder_as_arena_up_starts_it_lowers_its_session_group(
    tmp_path: Path, router_endpoint: str, processes: Callable[..., Proc]
) -> None:
    cfg = write_config(
        tmp_path, router_endpoint, services=("recorder",), extra=f'[recorder]\ndirectory = "{tmp_path}"'
    )
    # A session of its own, as `arena up` starts it.
    rec = processes("recorder", service_argv("recorder", cfg))
    wait_for(lambda: "CPU niceness" in rec.output(), 60.0, 0.05, "the recorder lowering its priority")
    assert stat(rec.pid)[1] == rec.pid  # it leads its session: nothing else shares its group
    assert stat(rec.pid)[2] == BACKGROUND_NICE
    assert group(rec.pid)[1] == BACKGROUND_NICE, rec.output()
    assert "the vision pipeline goes first" in rec.output(), rec.output()


def test_arena_view_typed_in_a_terminal_yields_in_a_session_of_its_own(
    tmp_path: Path, router_endpoint: str, processes: Callable[..., Proc]
) -> None:
    cfg = write_config(tmp_path, router_endpoint)
    view = f"{PYTHON} -m arena_common.cli view -c {cfg} --port {free_port()} --log-level INFO"
    # A shell that leads its session, as a terminal's does, running the command as typed in it.
    shell = processes("shell", ["/bin/sh", "-c", f"{view}; exit $?"])
    wait_for(lambda: "live 3D view on ws://" in shell.output(), 60.0, 0.05, "the viewer ready")
    (typed,) = children(shell.pid)  # what the shell started: it stays in the terminal's session
    moved = children(typed)
    assert len(moved) == 1, f"the viewer did not move to a session of its own: {shell.output()}"
    viewer = moved[0]
    assert stat(typed)[1] == shell.pid and stat(viewer)[1] == viewer  # the viewer leads a session of its own
    assert group(viewer)[0] != group(shell.pid)[0]
    assert group(viewer)[1] == BACKGROUND_NICE and stat(viewer)[2] == BACKGROUND_NICE
    # The terminal's other jobs keep their share.
    assert group(shell.pid)[1] == 0 and stat(shell.pid)[2] == os.nice(0)
    os.kill(typed, signal.SIGINT)  # Ctrl-C reaches what the shell started: it passes it on
    assert shell.wait(30.0) == 0, shell.output()
    out = shell.output()
    assert out.index("live 3D view on ws://") < out.index("arena.viewer: stopped"), out
    assert not Path(f"/proc/{viewer}").exists() and not Path(f"/proc/{typed}").exists()


def test_a_refusal_is_said_once_and_its_status_passes_through(
    tmp_path: Path, router_endpoint: str, processes: Callable[..., Proc]
) -> None:
    cfg = write_config(tmp_path, router_endpoint)
    view = f"{PYTHON} -m arena_common.cli view -c {cfg} --address 0.0.0.0 --port {free_port()}"
    shell = processes("shell", ["/bin/sh", "-c", f"{view}; exit $?"])
    assert shell.wait(60.0) == 2, shell.output()
    assert len(re.findall(r"error: --address 0\.0\.0\.0", shell.output())) == 1, shell.output()


def may_raise_priority() -> bool:
    """Whether this process may lower a niceness (CAP_SYS_NICE), as the services started from it may."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.nice(0) - 1)
    except OSError:
        return False
    os.setpriority(os.PRIO_PROCESS, 0, os.nice(0) + 1)
    return True


def test_the_table_favours_every_stage_a_pose_passes_and_nothing_else() -> None:
    vision = {s.name for s in SERVICES if s.cpu == "vision"}
    assert vision == {
        "mocap",
        "transform",
        "downsampler",
        "gateway",
        "sim-vehicle",
        "sim-motive",
        "sim-world",
    }
    assert ROUTER_CPU == "vision"
    assert {s.name for s in SERVICES if s.cpu == "background"} == {"recorder"}


def test_a_vision_stage_as_arena_up_starts_it_goes_first(
    tmp_path: Path, router_endpoint: str, processes: Callable[..., Proc]
) -> None:
    cfg = write_config(tmp_path, router_endpoint)
    stage = processes("transform", service_argv("frame_transform", cfg))  # a session of its own
    wait_for(lambda: "CPU niceness" in stage.output(), 60.0, 0.05, "the transform taking its share")
    assert stat(stage.pid)[1] == stage.pid
    if may_raise_priority():
        assert stat(stage.pid)[2] == VISION_NICE, stage.output()
        assert group(stage.pid)[1] == VISION_NICE, stage.output()
        assert "the vision pipeline goes first" in stage.output(), stage.output()
    else:  # without CAP_SYS_NICE it runs as before, and says why
        assert stat(stage.pid)[2] == os.nice(0), stage.output()
        assert f"cannot raise it to {VISION_NICE}" in stage.output(), stage.output()


SPIN = textwrap.dedent(
    """
    import os, sys
    os.sched_setaffinity(0, {int(sys.argv[1])})
    if sys.argv[2] == "yield":
        from arena_common.runtime.service import yield_cpu
        yield_cpu()
    elif sys.argv[2] == "favour":
        from arena_common.runtime.service import favour_cpu
        favour_cpu()
    print("spinning", flush=True)
    while True:
        pass
    """
)


def share_one_cpu(processes: Callable[..., Proc], stage: str, other: str) -> tuple[int, int]:
    """CPU time (ns) of two spinning processes on one CPU, each the leader of its session as `arena up`
    starts them, over the stage's first second of CPU: ``stage`` and ``other`` say what each calls first
    (``yield``, ``favour``, or nothing)."""
    cpu = str(max(os.sched_getaffinity(0)))
    first = processes("stage", [PYTHON, "-c", SPIN, cpu, stage])  # run in the checkout, as the services
    second = processes("other", [PYTHON, "-c", SPIN, cpu, other])
    wait_for(lambda: all("spinning" in p.output() for p in (first, second)), 60.0, 0.05, "both spinning")
    start = cpu_ns(first.pid), cpu_ns(second.pid)
    wait_for(lambda: cpu_ns(first.pid) - start[0] >= 1_000_000_000, 120.0, 0.05, "1 s of CPU for the stage")
    return cpu_ns(first.pid) - start[0], cpu_ns(second.pid) - start[1]


def test_a_yielding_process_leaves_a_shared_cpu_to_a_pipeline_stage(processes: Callable[..., Proc]) -> None:
    # A pipeline stage at niceness 0 and a process that called yield_cpu (what the recorder and the viewer do).
    stage_ns, background_ns = share_one_cpu(processes, "stage", "yield")
    # Weights 1024 and 110 (niceness 10): about a tenth; without the group's niceness, half each.
    assert background_ns < 0.3 * stage_ns, (stage_ns, background_ns)


@pytest.mark.skipif(not may_raise_priority(), reason="raising a priority needs CAP_SYS_NICE")
def test_a_favoured_stage_takes_a_shared_cpu_from_a_busy_program(processes: Callable[..., Proc]) -> None:
    # A favoured stage and a CPU-bound program of the user's at niceness 0.
    stage_ns, busy_ns = share_one_cpu(processes, "favour", "busy")
    # Weights 3121 (niceness -5) and 1024: about three to one; without the group's niceness, half each.
    assert busy_ns < 0.55 * stage_ns, (busy_ns, stage_ns)
