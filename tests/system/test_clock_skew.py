"""Clocks that disagree, with real processes: a host's wall clock off by ±0.3 s or ±2 s (libfaketime).

The whole chain runs as processes — Motive emulator, ingest, transform, downsampler, gateway and the
simulated autopilot — on one Zenoh router in this test's process.  The processes of the skewed "host"
(the companion computer: downsampler and gateway; or the mocap host: the ingest) read a wall clock
shifted by libfaketime (``FAKETIME``, ``FAKETIME_DONT_FAKE_MONOTONIC=1``: their monotonic clock is
untouched), and say so with ``--host``.  Network namespaces cannot do this: they share one kernel clock.

Each case ends one of two ways, never silently: the vehicle gets its vision fused, arms and takes off
(its gateway corrected the pose times by the measured offset), or arming is refused naming the clock.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from arena_common.bus.session import Bus
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from tests.helpers import REPO, Proc, service_argv, wait_for, write_config

pytestmark = pytest.mark.system

FAKETIME_LIB = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketimeMT.so.1")
needs_faketime = pytest.mark.skipif(
    not FAKETIME_LIB.exists() or shutil.which("faketime") is None,
    reason="libfaketime is not installed (apt-get install faketime)",
)


def skewed_env(seconds: float) -> dict[str, str]:
    """The environment of a process whose wall clock reads ``seconds`` ahead (negative: behind)."""
    return {
        "LD_PRELOAD": str(FAKETIME_LIB),
        "FAKETIME": f"{seconds:+}",
        "FAKETIME_DONT_FAKE_MONOTONIC": "1",
        # Else libfaketime 0.9.10 mistimes pthread_cond_timedwait on the monotonic clock, which the GIL
        # waits on: two busy Python threads then hand the GIL back and forth at full CPU.
        "FAKETIME_FORCE_MONOTONIC_FIX": "0",
        # time.sleep under libfaketime 0.9.10 fails with EINVAL: see tests/faketime/sitecustomize.py.
        "PYTHONPATH": os.pathsep.join([str(REPO / "tests" / "faketime"), str(REPO)]),
    }


class Chain:
    """Every process of one vehicle's chain, and a client bus watching its state and events."""

    def __init__(self, bus: Bus, processes: Callable[..., Proc], cfg_path: Path) -> None:
        self.bus = bus
        self.spawn = processes
        self.cfg_path = cfg_path
        self.states = bus.subscribe(keys.state("d1"), capacity=1, ring=True)
        self.events = bus.subscribe(keys.events("d1"), capacity=10_000, ring=False)
        self.clocks = bus.subscribe(keys.CLOCK_ALL, capacity=10_000, ring=False)
        self.seen_events: list[wire.Event] = []
        self.seen_clocks: dict[str, wire.ClockOffset] = {}
        self.last: wire.State | None = None
        self.procs: dict[str, Proc] = {}

    def start(self, module: str, host: str, skew: float, *extra: str) -> None:
        env = skewed_env(skew) if skew else None
        name = f"{module}.{host}"
        self.procs[name] = self.spawn(name, service_argv(module, self.cfg_path, *extra, host=host), env)

    def state(self) -> wire.State | None:
        item = self.states.channel.drain()
        if item and isinstance(item[-1].payload, wire.State):
            self.last = item[-1].payload
        return self.last

    def poll(self) -> dict[str, wire.ClockOffset]:
        """Take what arrived; the last ClockOffset of each key."""
        self.seen_events += [
            i.payload for i in self.events.channel.drain() if isinstance(i.payload, wire.Event)
        ]
        for i in self.clocks.channel.drain():
            if isinstance(i.payload, wire.ClockOffset):
                self.seen_clocks[i.key] = i.payload
        return self.seen_clocks

    def cmd(self, op: str, timeout: float = 10.0, **args: object) -> wire.CommandResult:
        return self.bus.request(
            keys.cmd("d1"), wire.Command(op=op, args=dict(args), src="test", timeout=timeout)
        )

    def logs(self) -> str:
        return "\n".join(f"--- {n}\n{p.tail(15)}" for n, p in self.procs.items())


def run_chain(
    tmp_path: Path,
    router_endpoint: str,
    bus: Bus,
    processes: Callable[..., Proc],
    *,
    gateway_skew: float = 0.0,
    ingest_skew: float = 0.0,
    clock: str = "",
) -> tuple[Chain, wire.CommandResult]:
    """Start the chain with the skews given; answer the arm command once the gateway is ready."""
    path = write_config(tmp_path, router_endpoint, 1, extra=clock, speed=1.0)
    path.write_text(path.read_text().replace("[mocap]\n", "[mocap]\nmulticast = false\n", 1))
    config_mod.load(path)
    chain = Chain(bus, processes, path)
    chain.start("sim_vehicle", "ground", 0.0)
    chain.start("sim_mocap", "ground", 0.0)
    chain.start("mocap_ingest", "mocap-pc" if ingest_skew else "ground", ingest_skew)
    chain.start("frame_transform", "ground", 0.0)
    companion = "cc1" if gateway_skew else "ground"
    chain.start("downsampler", companion, gateway_skew, "--vehicle", "d1")
    chain.start("mavlink_gateway", companion, gateway_skew, "--vehicle", "d1")
    try:
        wait_for(lambda: (s := chain.state()) is not None and s.link and s.setup_ok, 90.0, what="link, setup")
        # The gateway's host measures its offset (a few exchanges), then vision flows — or cannot.
        wait_for(
            lambda: keys.clock(companion, "gateway.d1") in chain.poll(),
            30.0,
            what="the gateway host's clock offset published",
        )
        try:
            wait_for(
                lambda: (s := chain.state()) is not None and s.vis_fused and s.vis_rate >= 40.0,
                20.0,
                what="vision fused at its rate",
            )
        except (AssertionError, TimeoutError):
            pass  # arming says why
        result = chain.cmd("arm")
        for _ in range(3):  # a busy two-core machine may pause the chain a few hundred ms at start-up
            if not result.reason.startswith("vision stale"):
                break
            result = chain.cmd("arm")
    except BaseException:
        print(chain.logs())
        raise
    return chain, result


def expect_flight(chain: Chain, result: wire.CommandResult) -> None:
    assert result.ok, f"arm: {result.result} {result.reason}\n{chain.logs()}"
    takeoff = chain.cmd("takeoff", 20.0, height=1.0)
    assert takeoff.ok, f"takeoff: {takeoff.result} {takeoff.reason}"
    try:
        wait_for(
            lambda: (
                (s := chain.state()) is not None
                and s.landed == "in_air"
                and s.p is not None
                and -s.p[2] > 0.8
            ),
            30.0,
            what="in the air above 0.8 m",
        )
    except BaseException:
        chain.poll()
        print(chain.last, [e.text for e in chain.seen_events][-20:], chain.logs(), sep="\n")
        raise
    s = chain.state()
    assert s is not None and s.vis_fused and "vision_stale" not in s.fs


@needs_faketime
@pytest.mark.parametrize("skew", [0.3, -0.3, 2.0, -2.0])
def test_companion_computer_clock_off_still_flies(
    skew: float,
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    processes: Callable[..., Proc],
) -> None:
    chain, result = run_chain(tmp_path, router_endpoint, bus_factory(), processes, gateway_skew=skew)
    chain.poll()
    off = chain.seen_clocks[keys.clock("cc1", "gateway.d1")]
    # Measured: the mocap host's clock minus the companion's is -skew, within its bound (+ the few ms
    # between libfaketime's start-up and ours).
    assert off.state == "ok" and off.ref == "ground" and off.off is not None and off.unc is not None
    assert abs(off.off + skew) <= off.unc + 0.005, off
    expect_flight(chain, result)
    chain.poll()
    # (A first exchange on a busy machine may have been uncertain: that event comes first, then this one.)
    warned = [e for e in chain.seen_events if e.kind == "clock" and "the clock of cc1 is" in e.text]
    assert warned and "chrony" in warned[-1].text and warned[-1].sev == 4, [e.text for e in chain.seen_events]
    s = chain.state()
    assert s is not None and "clock_offset" in s.fs


@needs_faketime
@pytest.mark.parametrize("skew", [0.3, -0.3, 2.0, -2.0])
def test_mocap_host_clock_off_still_flies(
    skew: float,
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    processes: Callable[..., Proc],
) -> None:
    chain, result = run_chain(tmp_path, router_endpoint, bus_factory(), processes, ingest_skew=skew)
    chain.poll()
    off = chain.seen_clocks[keys.clock("ground", "gateway.d1")]
    assert off.state == "ok" and off.ref == "mocap-pc" and off.off is not None and off.unc is not None
    assert abs(off.off - skew) <= off.unc + 0.005, off
    assert chain.seen_clocks[keys.clock("mocap-pc", "mocap")].state == "reference"
    expect_flight(chain, result)


@needs_faketime
def test_an_uncertain_offset_refuses_arming_naming_the_clock(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], processes: Callable[..., Proc]
) -> None:
    # No exchange is certain to 1 µs: the companion computer's offset (2 s) is known, but not well enough.
    chain, result = run_chain(
        tmp_path,
        router_endpoint,
        bus_factory(),
        processes,
        gateway_skew=2.0,
        clock="[clock]\nmax_uncertainty = 0.000001",
    )
    assert result.result == "REFUSED", result
    assert result.reason.startswith("clock: the offset of the clock of cc1 to the mocap host's (ground)")
    assert "uncertain" in result.reason and "chrony" in result.reason
    chain.poll()
    assert any(e.kind == "clock" and "arming refused" in e.text for e in chain.seen_events)
    s = chain.state()
    assert s is not None and not s.armed and "clock_uncertain" in s.fs
