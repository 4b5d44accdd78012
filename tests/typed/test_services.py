"""``arena`` as a user types it: the real console script, in a session of its own as a terminal runs a
job, on a config of free ports whose vehicles are not the default config's.

The shared options (``-c/--config``, ``--connect``, ``--listen``…), before or after the sub-command,
reach every ``arena run`` and ``arena sim`` service: each serves the named config's ports and vehicles
(seen from its presence on this test's private router, the ports it binds and its log).  A named config
that cannot be read is an error naming it, for every command.  Ctrl-C, a closed terminal (SIGHUP),
SIGTERM and a double Ctrl-C end each command with nothing of it left running.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from arena_common.bus.session import Bus
from arena_common.core.waiting import wait_until
from tests.helpers import REPO, free_port, wait_for
from tests.typed.harness import (
    ARENA,
    START_S,
    Command,
    Typed,
    _udp_free,
    alive_ids,
    bound,
    leftovers,
    stops_cleanly,
)

# -- every service serves the config named on the command line -----------------------------------------------

# (id, command line, presence ids, a log line, ports it binds); {CFG}, {cmd}… are the config's.
SERVICES: list[tuple[str, list[str], set[str], str, list[tuple[str, str]]]] = [
    (
        "sim-vehicle",
        ["sim", "vehicle", "-c", "{CFG}"],
        {"sim-vehicle"},
        r"simulating x7 \(sysid 7, udpout:127\.0\.0\.1:{x7}\)",
        [],
    ),
    (
        "sim-motive",
        ["sim", "motive", "-c", "{CFG}"],
        {"sim-motive"},
        r"server on 127\.0\.0\.1:{cmd}",
        [("udp", "{cmd}")],
    ),
    (
        "sim-motive-config-first",
        ["-c", "{CFG}", "sim", "motive"],
        {"sim-motive"},
        r"streaming x7 \(id",
        [("udp", "{cmd}")],
    ),
    (
        "sim-motive-long-option",
        ["sim", "motive", "--config", "{CFG}"],
        {"sim-motive"},
        r"server on 127\.0\.0\.1:{cmd}",
        [("udp", "{cmd}")],
    ),
    (
        "sim-world",
        ["sim", "world", "-c", "{CFG}", "--host", "typed"],
        {"sim-vehicle", "sim-motive"},
        r"\[sim-motive\] .*streaming x7",
        [("udp", "{cmd}")],
    ),
    (
        "run-mocap",
        ["run", "mocap", "-c", "{CFG}"],
        {"mocap"},
        r"source natnet \(server 127\.0\.0\.1:{cmd},",
        [],
    ),
    (
        "run-transform",
        ["--config", "{CFG}", "run", "transform"],
        {"transform"},
        r"arena\.transform: started",
        [],
    ),
    (
        "run-downsampler",
        ["run", "downsampler", "--vehicle", "x7", "--config={CFG}"],
        {"downsampler.x7"},
        r"arena/x7/pose → arena/x7/vision",
        [],
    ),
    (
        "run-gateway",
        ["run", "gateway", "-c", "{CFG}", "--vehicle", "x7"],
        {"gateway.x7"},
        r"gateway for x7: udpin:127\.0\.0\.1:{x7}, system 7",
        [("udp", "{x7}")],
    ),
    ("run-recorder", ["run", "recorder", "-c", "{CFG}"], {"recorder"}, r"recording to {rec}/", []),
    (
        "run-px4-truth",
        ["run", "px4-truth", "-c", "{CFG}", "--vehicle", "x8"],
        {"px4-truth.x8"},
        r"udp 127\.0\.0\.1:{truth} \(PX4 SITL instance",
        [("udp", "{truth}")],
    ),
]


@pytest.mark.covers(
    "arena sim vehicle", "arena sim motive", "arena sim world", "arena run mocap", "arena run transform",
    "arena run downsampler", "arena run gateway", "arena run recorder", "arena run px4-truth",
)  # fmt: skip
@pytest.mark.parametrize(
    ("args", "ids", "line", "ports"), [s[1:] for s in SERVICES], ids=[s[0] for s in SERVICES]
)
def test_each_service_serves_the_named_config_and_stops_on_ctrl_c(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    typed: Callable[..., Command],
    args: list[str],
    ids: set[str],
    line: str,
    ports: list[tuple[str, str]],
) -> None:
    cfg = Typed(tmp_path, router_endpoint)
    if "px4-truth" in args and not _udp_free(cfg.truth_port):
        pytest.skip(f"udp port {cfg.truth_port} of PX4 SITL instance {cfg.instance} is in use")
    bus = bus_factory()
    cmd = typed(*(cfg.fill(a) for a in args))
    cmd.wait_line(cfg.fill(line))
    wait_until(lambda: ids <= alive_ids(bus), START_S, f"presence of {ids}", interval=0.2, check=cmd.running)
    for kind, port in ports:
        assert bound(kind, int(cfg.fill(port))), f"{kind} port {cfg.fill(port)} not bound:\n{cmd.output()}"
    assert stops_cleanly(cmd, [str(tmp_path)]) == 0, cmd.output()


@pytest.mark.covers("arena run px4-sitl")
def test_px4_sitl_flies_the_named_configs_vehicle(tmp_path: Path, typed: Callable[..., Command]) -> None:
    """x8 is only in the named config: the service reaches the build it was given (none here)."""
    cfg = Typed(tmp_path, f"tcp/127.0.0.1:{free_port()}")
    nowhere = tmp_path / "no-px4-build"
    cmd = typed("run", "px4-sitl", "--vehicle", "x8", "-c", str(cfg.path), "--build", str(nowhere))
    assert cmd.exits_within(30) == 2, cmd.output()
    assert f"no PX4 SITL build (bin/px4 and etc/) found: looked at {nowhere}" in cmd.output()


def test_the_bus_options_reach_the_service_too(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], typed: Callable[..., Command]
) -> None:
    """--connect (before the sub-command) and --listen (after it) replace the config's endpoints."""
    dead = f"tcp/127.0.0.1:{free_port()}"  # the config's router: nobody listens there
    cfg = Typed(tmp_path, dead, connect=dead)
    port = free_port()
    bus = bus_factory()
    cmd = typed("-e", router_endpoint, "run", "transform", "-c", str(cfg.path), "-l", f"tcp/127.0.0.1:{port}")
    cmd.wait_line(r"arena\.transform: started")
    wait_for(
        lambda: "transform" in alive_ids(bus), timeout=START_S, interval=0.2, what="presence via --connect"
    )
    wait_for(lambda: bound("tcp", port), timeout=10, what=f"a listener on tcp {port} (--listen)")
    assert stops_cleanly(cmd, [str(tmp_path)]) == 0, cmd.output()


# -- a named config that cannot be read --------------------------------------------------------------------

RUN = ["mocap", "transform", "downsampler", "gateway", "recorder", "px4-sitl", "px4-truth"]
SIM = ["vehicle", "motive", "world"]
MISSING: list[list[str]] = [
    *(["run", name, "--vehicle", "x7", "-c", "{MISSING}"] for name in RUN),
    *(["sim", name, "-c", "{MISSING}"] for name in SIM),
    ["-c", "{MISSING}", "sim", "motive"],
    ["run", "gateway", "--vehicle", "x7", "--config={MISSING}"],
    ["up", "-c", "{MISSING}"],
    ["-c", "{MISSING}", "up"],
    ["demo", "-c", "{MISSING}"],
    ["view", "-c", "{MISSING}"],
    ["status", "--config", "{MISSING}"],
    ["echo", "arena/**", "-c", "{MISSING}"],
    ["keys", "-c", "{MISSING}"],
]


@pytest.mark.parametrize("args", MISSING, ids=[" ".join(a).replace("{MISSING}", "M") for a in MISSING])
def test_a_named_config_that_cannot_be_read_is_an_error_naming_it(tmp_path: Path, args: list[str]) -> None:
    missing = tmp_path / "missing.toml"
    environ = {k: v for k, v in os.environ.items() if k != "ARENA_CONFIG"}
    res = subprocess.run(
        [str(ARENA), *(a.replace("{MISSING}", str(missing)) for a in args)],
        cwd=REPO,  # where deploy/sim.toml is: it must not be used instead
        env=environ,
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert res.returncode == 2, res
    assert f"error: {missing}: cannot read: No such file or directory" in res.stderr, res
    assert "deploy/sim.toml" not in res.stderr + res.stdout


@pytest.mark.parametrize("args", [["up", "{A}", "-c", "{B}"], ["sim", "world", "{A}", "--config", "{B}"]])
def test_two_different_configs_named_are_an_error(tmp_path: Path, args: list[str]) -> None:
    a, b = Typed(tmp_path, "tcp/127.0.0.1:1").path, tmp_path / "other.toml"
    b.write_text(a.read_text())
    res = subprocess.run(
        [str(ARENA), *(x.replace("{A}", str(a)).replace("{B}", str(b)) for x in args)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2, res
    assert f"two config files named: {a} (argument) and {b} (--config)" in res.stderr


# -- signals: nothing outlives its terminal ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("sig", "twice"),
    [(signal.SIGHUP, False), (signal.SIGTERM, False), (signal.SIGINT, True)],
    ids=["SIGHUP", "SIGTERM", "SIGINT-twice"],
)
def test_sim_world_and_its_children_end_on_any_stop_signal(
    tmp_path: Path, router_endpoint: str, typed: Callable[..., Command], sig: int, twice: bool
) -> None:
    cfg = Typed(tmp_path, router_endpoint)
    cmd = typed("sim", "world", "-c", str(cfg.path), "--host", "typed")
    cmd.wait_line(r"\[sim-motive\] .*streaming x7")
    cmd.wait_line(r"\[sim-vehicle\] .*simulating x7")
    assert len(leftovers([str(cfg.path)])) >= 3  # the supervisor and its two children
    code = stops_cleanly(cmd, [str(tmp_path)], sig, r"^\[arena\] stopping " if twice else None)
    assert code == 0, cmd.output()


@pytest.mark.parametrize("args", [["run", "gateway", "--vehicle", "x7"], ["view", "--port", "0"]])
def test_a_closed_terminal_stops_a_service_in_order(
    tmp_path: Path, router_endpoint: str, typed: Callable[..., Command], args: list[str]
) -> None:
    """SIGHUP is an orderly stop, as Ctrl-C: the service says it stopped."""
    cfg = Typed(tmp_path, router_endpoint)
    cmd = typed(*args, "-c", str(cfg.path), "--log-level", "INFO")
    cmd.wait_line(r": started \(host")
    assert stops_cleanly(cmd, [str(tmp_path)], signal.SIGHUP) == 0, cmd.output()
    assert re.search(r"arena\.\S+: stopped$", cmd.output(), re.M), cmd.output()


STOP_SIGNALS_SCRIPT = """
import signal, sys, threading, time
from arena_common.runtime.process import StopSignals
stop, again = threading.Event(), []
with StopSignals(stop, again=again.append) as signals:
    print("ready", flush=True)
    stop.wait(30)
    print("stopped", signal.Signals(signals.received[0]).name, flush=True)
    deadline = time.monotonic() + 30
    while not again and time.monotonic() < deadline:
        time.sleep(0.01)
    print("received", *(signal.Signals(s).name for s in signals.received), flush=True)
    print("again", *(signal.Signals(s).name for s in again), flush=True)
"""


@pytest.mark.parametrize("nohup", [False, True], ids=["terminal", "nohup-background"])
def test_stop_signals_first_stops_a_further_one_hurries(tmp_path: Path, nohup: bool) -> None:
    """The first stop signal stops, a further SIGINT/SIGTERM hurries, a further SIGHUP does not; a
    SIGINT ignored from the start (a shell script's background job) is handled, an ignored SIGHUP
    (``nohup``) stays ignored."""
    script = tmp_path / "signals.py"
    script.write_text(STOP_SIGNALS_SCRIPT)

    def setup() -> None:
        for sig in (signal.SIGINT, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN if nohup else signal.SIG_DFL)

    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=setup,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        first = signal.SIGINT if nohup else signal.SIGHUP
        if nohup:
            proc.send_signal(signal.SIGHUP)  # ignored: SIGINT below is the first one taken
        proc.send_signal(first)
        assert proc.stdout.readline() == f"stopped {first.name}\n"
        proc.send_signal(signal.SIGHUP)  # nohup: ignored; else taken, but no hurry
        proc.send_signal(signal.SIGTERM)
        received = [first.name] + ([] if nohup else ["SIGHUP"]) + ["SIGTERM"]
        assert sorted(proc.stdout.readline().split()[1:]) == sorted(received)
        assert proc.stdout.readline() == "again SIGTERM\n"
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait(5)
