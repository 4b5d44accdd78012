"""Faults against the simulated arena in flight, each measured.

One arena for the whole module, run as the lab runs it: ``arena up`` (the supervisor: router, mocap
ingest, frame transform, recorder, d1's downsampler and gateway, each its own process) and the Motive
emulator (``services.sim_mocap``) as processes; the simulated PX4 of d1 runs in this process
(:class:`tests.faultlib.TapAutopilot`) so each test sees exactly what reaches the autopilot and how the
vehicle flies, whatever happens to the arena.  Its MAVLink link goes through a :class:`LossyLink` relay
(lossless unless a test says otherwise), a bad radio link on demand.

Each test brings d1 to a hover at 1 m (AUTO.LOITER, vision fused), breaks one thing, checks that what
happens to the vehicle is what the design says, measures the recovery and records the figures
(``bench-results/faults.json``; docs/safety.md has the table).  The supervisor is killed last.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import socket
import subprocess
import textwrap
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus
from arena_common.client.vehicle import Arena
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import BusError
from arena_common.recording.mcap import RecordingReader
from tests.faultlib import (
    ArenaUp,
    LossyLink,
    TapAutopilot,
    Watch,
    World,
    alive,
    client_bus,
    first_after,
    max_gap,
    peer_bus,
    rate_between,
    record,
    wait_time,
    write_arena_config,
)
from tests.helpers import PYTHON, REPO, Proc, free_port, service_argv, wait_for

pytestmark = pytest.mark.system

HEIGHT = 1.0
FLUSH_S = 0.5
EKF_VISION_TIMEOUT_S = 0.4  # PX4 EKF2 stops fusing vision this long after the last sample
RECORDED = '["arena/*/vision", "arena/*/state"]'
CHILDREN = ("router", "mocap", "transform", "recorder", "downsampler.d1", "gateway.d1")


@dataclass
class Rig:
    """The arena under test and everything that watches it."""

    cfg: ArenaConfig
    cfg_path: Path
    logs: Path
    bus: Bus
    world: World
    link: LossyLink
    up: ArenaUp
    mocap: Proc
    watch: Watch
    arena: Arena

    @property
    def ap(self) -> TapAutopilot:
        return self.world.aps["d1"]

    def odometry(self, after: float = -math.inf, before: float = math.inf) -> list[float]:
        return self.ap.tap.times("ODOMETRY", after, before)

    def context(self) -> str:
        return f"--- arena up\n{self.up.tail(40)}\n--- sim_mocap\n{self.mocap.tail(10)}"


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    tmp = tmp_path_factory.mktemp("faults")
    link = LossyLink(free_port(socket.SOCK_DGRAM))
    path = write_arena_config(
        tmp,
        services=("router", "mocap", "transform", "recorder"),
        recorder=f'directory = "{tmp / "rec"}"\nkeys = {RECORDED}\nflush_s = {FLUSH_S}',
        gateway_ports={"d1": link.gateway[1]},
        sim_links={"d1": f"udpout:127.0.0.1:{link.listen_port}"},
        multicast=os.environ.get("ARENA_FAULTS_MULTICAST", "1") == "1",
    )
    cfg = config_mod.load(path)
    bus = peer_bus(cfg)
    world = World(cfg, bus)
    up = ArenaUp(path, tmp)
    mocap = Proc("sim_mocap", service_argv("sim_mocap", path), tmp)
    watch = Watch(bus)
    arena = Arena(cfg, bus=bus, name="faults")
    rig = Rig(cfg, path, tmp, bus, world, link, up, mocap, watch, arena)
    try:
        up.wait_started(CHILDREN, 60.0)
        try:
            wait_for(
                lambda: (s := watch.state("d1")) is not None and s.vis_fused and s.setup_ok,
                90.0,
                0.05,
                what="d1 fused and set up",
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{rig.context()}") from None
        yield rig
    finally:
        arena.close()
        watch.close()
        mocap.stop()
        rig.mocap.stop()  # a test may have started a new emulator in its place
        up.stop()
        world.close()
        link.close()
        bus.close()


def hovering(ap: TapAutopilot, height: float = HEIGHT) -> bool:
    z = ap.true_pose().position[2]
    return (
        ap.armed
        and ap.mode_name == "AUTO.LOITER"
        and abs(-z - height) < 0.1
        and ap.sim.estimator.vision_fusing
    )


def fly(rig: Rig, height: float = HEIGHT) -> None:
    """Bring d1 to a hover at ``height`` (landing first if it is still coming down)."""
    ap = rig.ap
    if hovering(ap, height):
        return
    try:
        wait_for(lambda: not ap.armed, 30.0, 0.05, what="d1 disarmed on the ground")
        wait_for(
            lambda: (s := rig.watch.state("d1")) is not None and s.vis_fused and s.link and not s.armed,
            60.0,
            0.05,
            what="d1's state: vision fused, link up",
        )
        d1 = rig.arena.vehicle("d1")
        if d1.mode == "OFFBOARD":  # the mode a dead user program left: arming there needs a stream
            d1.hold()
        d1.arm(timeout=10.0)
        d1.takeoff(height, timeout=30.0)
        wait_for(lambda: hovering(ap, height), 20.0, 0.05, what=f"hover at {height} m")
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{rig.context()}") from None


def landed_by_itself(rig: Rig, t0: float, timeout: float = 30.0) -> tuple[float, float]:
    """The autopilot's own landing after ``t0``: (seconds to its failsafe, seconds to touchdown)."""
    w = rig.world
    t_land = w.when("d1", lambda s: s.mode == "AUTO.LAND" or not s.armed, t0, timeout, "lands by itself")
    t_down = w.when("d1", lambda s: s.z >= -0.01, t0, timeout, "touches down")
    assert rig.ap.sim.body.last_impact_speed < 1.5, (
        f"hard landing at {rig.ap.sim.body.last_impact_speed:.2f} m/s"
    )
    return t_land - t0, t_down - t0


def vision_back(rig: Rig, after: float, timeout: float = 60.0) -> float:
    """When the first ODOMETRY after ``after`` reached the autopilot (waiting for it)."""
    t: float = wait_for(lambda: first_after(rig.odometry(), after), timeout, 0.02, what="vision back")
    return t


# -- faults that the vehicle must not notice -----------------------------------------------------------------


def test_recorder_killed_loses_at_most_its_flush_interval(rig: Rig) -> None:
    fly(rig)
    rec_dir = rig.logs / "rec"
    wait_for(lambda: any(rec_dir.glob("*.mcap")), 10.0, what="a recording file")
    time.sleep(2 * FLUSH_S)  # at least one flush of flying data
    before = set(rec_dir.glob("*.mcap"))
    t0 = time.monotonic()
    t_kill_ns = time.time_ns()
    old = rig.up.kill_child("recorder")
    new, t_restart = rig.up.wait_restarted("recorder", old)
    wait_for(lambda: set(rec_dir.glob("*.mcap")) - before, 30.0, what="the restarted recorder's new file")
    t_back = time.monotonic()
    time.sleep(0.5)
    # The killed file is readable up to its last flush.
    killed = max(before, key=lambda p: p.stat().st_mtime)
    reader = RecordingReader(killed)
    times = [m.log_time for m in reader.messages() if m.channel.key == keys.vision("d1")]
    assert times, f"nothing readable in {killed} ({reader.error})"
    lost = (t_kill_ns - max(times)) * 1e-9
    assert lost <= FLUSH_S + 0.35, f"lost the last {lost:.2f} s (flush interval {FLUSH_S} s)"
    # The vehicle did not notice.
    gap = max_gap(rig.odometry(), t0 - 0.2, t_back)
    assert gap < EKF_VISION_TIMEOUT_S, f"vision gap {gap:.3f} s"
    assert hovering(rig.ap) and not rig.ap.tap.invalid
    record(
        "recorder kill -9",
        lost_s=lost,
        flush_s=FLUSH_S,
        restarted_after_s=t_restart - t0,
        new_file_after_s=t_back - t0,
        vision_max_gap_s=gap,
        new_pid=new,
        vehicle="hovers on",
    )


def test_router_killed_peers_on_the_host_keep_flowing(rig: Rig) -> None:
    fly(rig)
    t0 = time.monotonic()
    old = rig.up.kill_child("router")
    _, t_restart = rig.up.wait_restarted("router", old)
    # A program arriving after the restart reaches the gateway through the new router alone.
    fresh: list[Bus] = []

    def ping() -> bool:
        if not fresh:
            try:
                fresh.append(client_bus(rig.cfg))
            except BusError:
                return False  # the new router does not accept yet
        res = fresh[0].request(keys.cmd("d1"), wire.Command(op="ping", src="faults", timeout=1.0), 1.0)
        return res.ok

    try:
        t_ping = wait_time(ping, 60.0, "a new client's ping through the restarted router", 0.05)
    finally:
        for b in fresh:
            b.close()
    time.sleep(1.0)
    gap = max_gap(rig.odometry(), t0 - 0.2, time.monotonic())
    assert gap < EKF_VISION_TIMEOUT_S, f"vision gap {gap:.3f} s while the router was down"
    assert hovering(rig.ap), rig.ap.mode_name
    record(
        "router kill -9",
        vision_max_gap_s=gap,
        router_restarted_after_s=t_restart - t0,
        new_client_reaches_gateway_after_s=t_ping - t0,
        vehicle="hovers on (peers on one host talk directly)",
    )


def test_short_mocap_dropout_is_ridden_through(rig: Rig) -> None:
    fly(rig)
    duration = 0.15
    t0 = time.monotonic()
    end = rig.world.occlude("d1", duration)
    time.sleep(duration + 1.0)
    back = first_after(rig.odometry(), end)
    assert back is not None, "vision never came back"
    gap = max_gap(rig.odometry(), t0 - 0.2, time.monotonic())
    assert gap < EKF_VISION_TIMEOUT_S, f"vision gap {gap:.3f} s"
    assert hovering(rig.ap), rig.ap.mode_name
    record(
        "mocap dropout 0.15 s",
        vision_gap_s=gap,
        vision_back_after_reacquired_s=back - end,
        vehicle="hovers on (gap below EKF2's 0.4 s)",
    )


# -- faults that take the vision away: the autopilot's position-loss failsafe lands it -----------------------


def test_long_mocap_dropout_lands_then_vision_resumes(rig: Rig) -> None:
    fly(rig)
    duration = 1.5
    t0 = time.monotonic()
    end = rig.world.occlude("d1", duration)
    to_land, to_ground = landed_by_itself(rig, t0)
    wait_for(lambda: first_after(rig.odometry(), end) is not None, 10.0, what="vision back")
    back = first_after(rig.odometry(), end)
    assert back is not None
    last_before = max(rig.odometry(before=end), default=t0)
    assert last_before - t0 < 0.1, "a pose of the hidden body reached the autopilot"
    assert not rig.ap.tap.invalid
    record(
        "mocap dropout 1.5 s",
        failsafe_after_s=to_land,
        touchdown_after_s=to_ground,
        vision_back_after_reacquired_s=back - end,
        vehicle="position-loss failsafe: descends and lands",
    )


@pytest.mark.parametrize("service", ["mocap", "transform", "downsampler.d1", "gateway.d1"])
def test_pipeline_service_killed_vehicle_lands_and_vision_recovers(rig: Rig, service: str) -> None:
    fly(rig)
    t0 = time.monotonic()
    old = rig.up.kill_child(service)
    _, t_restart = rig.up.wait_restarted(service, old)
    to_land, to_ground = landed_by_itself(rig, t0)
    t_vision = vision_back(rig, t_restart)
    last_before = max(rig.odometry(before=t_restart), default=t0)
    fused = rig.world.when("d1", lambda s: s.fusing, t_vision, 20.0, "vision fused again")
    assert not rig.ap.tap.invalid
    figures: dict[str, Any] = {}
    if service.startswith("gateway"):

        def new_state() -> float | None:
            return first_after(rig.watch.state_times.get("d1", ()), t_restart)

        figures["state_back_after_s"] = wait_for(new_state, 30.0, 0.02, what="the new gateway's state") - t0
    record(
        f"{service.split('.')[0]} kill -9",
        last_vision_after_kill_s=last_before - t0,
        failsafe_after_s=to_land,
        touchdown_after_s=to_ground,
        restarted_after_s=t_restart - t0,
        vision_back_after_s=t_vision - t0,
        fused_again_after_s=fused - t0,
        vehicle="position-loss failsafe: descends and lands",
        **figures,
    )


def test_gateway_frozen_then_thawed_sends_no_stale_pose(rig: Rig) -> None:
    fly(rig)
    freeze = 1.0
    t0 = time.monotonic()
    rig.up.kill_child("gateway.d1", signal.SIGSTOP)
    try:
        time.sleep(freeze)
    finally:
        rig.up.kill_child("gateway.d1", signal.SIGCONT)
    t_cont = time.monotonic()
    to_land, to_ground = landed_by_itself(rig, t0)
    t_back = first_after(rig.odometry(), t_cont)
    assert t_back is not None
    time.sleep(0.5)
    ages = rig.ap.tap.ages(after=t_cont)
    stale = [a for a in ages if a > 0.2]
    # The poses queued during the freeze are never sent; at most the one the vision thread was already
    # sending when the process stopped (age checked, not yet written) goes out first after the thaw.
    assert all(a <= 0.2 for a in ages[1:]), f"stale poses sent after the thaw: ages {ages[:10]}"
    record(
        "gateway SIGSTOP 1 s",
        failsafe_after_s=to_land,
        touchdown_after_s=to_ground,
        vision_back_after_thaw_s=t_back - t_cont,
        stale_poses_after_thaw=len(stale),
        stale_age_s=max(stale, default=0.0),
        vehicle="position-loss failsafe: descends and lands",
    )


def test_motive_restart_ingest_recovers(rig: Rig) -> None:
    fly(rig)
    t0 = time.monotonic()
    rig.mocap.signal(signal.SIGKILL)
    rig.mocap.wait(10.0)
    rig.mocap.stop()
    to_land, _ = landed_by_itself(rig, t0)
    time.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))
    t_start = time.monotonic()
    rig.mocap = Proc("sim_mocap", service_argv("sim_mocap", rig.cfg_path), rig.logs)
    wait_for(lambda: any("streaming" in line for line in rig.mocap.lines), 30.0, 0.01, what="Motive back")
    t_ready = time.monotonic()
    t_vision = vision_back(rig, t_start)
    fused = rig.world.when("d1", lambda s: s.fusing, t_vision, 20.0, "vision fused again")
    # What the design promises, in order: the failsafe lands the vehicle, the ingest reconnects by itself
    # (its back-off is at most 4 s, the bounds leave room for a busy machine) and vision is fused again.
    assert to_land < 5.0, f"position-loss failsafe after {to_land:.2f} s"
    assert t_ready - t_start < 30.0 and t_vision >= t_ready and fused >= t_vision
    assert t_vision - t_ready < 15.0, f"vision back {t_vision - t_ready:.2f} s after Motive was ready"
    record(
        "Motive restart (emulator kill -9, back 1 s later)",
        failsafe_after_s=to_land,
        motive_ready_after_start_s=t_ready - t_start,
        vision_back_after_motive_ready_s=t_vision - t_ready,
        fused_again_after_motive_ready_s=fused - t_ready,
        vehicle="position-loss failsafe: descends and lands",
    )


USER_PROGRAM = textwrap.dedent(
    """
    import sys, time
    from arena_common import Arena

    with Arena(sys.argv[1], name="doomed") as arena:
        d1 = arena.vehicle("d1")
        d1.wait_until(lambda v: v.position is not None, 30, "a position")
        n, e, d = d1.position
        with d1.offboard() as ctl:
            ctl.position(n, e, d, yaw=0.0)
            print("OFFBOARD", flush=True)
            time.sleep(600)
    """
)


def test_user_program_killed_in_offboard_lands(rig: Rig) -> None:
    fly(rig)
    script = rig.logs / "user_program.py"
    script.write_text(USER_PROGRAM)
    user = Proc("user-program", [PYTHON, str(script), str(rig.cfg_path)], rig.logs)
    try:
        wait_for(lambda: any("OFFBOARD" in line for line in user.lines), 60.0, 0.05, what="offboard engaged")
        wait_for(lambda: rig.ap.mode_name == "OFFBOARD", 5.0, what="the autopilot in OFFBOARD")
        time.sleep(0.5)
        t0 = time.monotonic()
        user.signal(signal.SIGKILL)
        to_land, to_ground = landed_by_itself(rig, t0)
    finally:
        user.stop()
    last_sp = max(rig.ap.tap.times("SET_POSITION_TARGET_LOCAL_NED"), default=t0)
    assert 0.2 < last_sp - t0 < 1.0, f"setpoints went on {last_sp - t0:.2f} s after the program died"
    assert "Failsafe: no offboard signal" in " ".join(t for _, t in rig.ap.statustexts)
    record(
        "user program kill -9 (offboard)",
        setpoints_stopped_after_s=last_sp - t0,
        failsafe_after_s=to_land,
        touchdown_after_s=to_ground,
        vehicle="lease lapses, offboard-loss failsafe (COM_OBL_RC_ACT 4): lands",
    )


# -- a bad link ----------------------------------------------------------------------------------------------


# How test_lossy_delayed_radio_link degrades the link: "relay" (user space, the MAVLink link alone) or
# "netem" (tc netem on the loopback of the network namespace the whole test runs in: every link of the
# arena); test_link_loss_and_delay_with_netem runs it in a namespace of its own with "netem".
LINK_MODE = os.environ.get("ARENA_FAULTS_LINK", "relay")
NETEM_ARGS = ("delay", "15ms", "5ms", "loss", "2%")


@contextmanager
def bad_link(rig: Rig) -> Iterator[str]:
    """Degrade the link for the block; yields what was done."""
    if LINK_MODE == "netem":
        subprocess.run(
            ["tc", "qdisc", "add", "dev", "lo", "root", "netem", *NETEM_ARGS], check=True, timeout=10
        )
        try:
            yield "netem on every link: " + " ".join(NETEM_ARGS)
        finally:
            subprocess.run(["tc", "qdisc", "del", "dev", "lo", "root"], check=False, timeout=10)
    else:
        rig.link.set(loss=0.10, delay=0.030, jitter=0.010)
        try:
            yield "radio link 10 % loss, 30±10 ms delay"
        finally:
            rig.link.set(loss=0.0, delay=0.0, jitter=0.0)


def test_lossy_delayed_radio_link(rig: Rig) -> None:
    """10 % loss and 30 ± 10 ms delay each way on the MAVLink link (a poor radio), in user space."""
    fly(rig)
    t0 = time.monotonic()
    with bad_link(rig) as what:
        time.sleep(4.0)
        t1 = time.monotonic()
        ages = sorted(rig.ap.tap.ages(after=t0 + 0.5, before=t1))
        rate = rate_between(rig.odometry(), t0 + 0.5, t1)
        gap = max_gap(rig.odometry(), t0 + 0.5, t1)
        res = rig.arena.vehicle("d1").command("ping", timeout=5.0)
        assert res.ok
        still = hovering(rig.ap)
    t_clear = time.monotonic()
    time.sleep(1.0)
    ages_after = sorted(rig.ap.tap.ages(after=t_clear + 0.2))
    record(
        what,
        vision_rate_hz=rate,
        vision_age_p50_s=ages[len(ages) // 2],
        vision_age_p99_s=ages[int(len(ages) * 0.99)],
        vision_max_gap_s=gap,
        vision_age_p50_after_s=ages_after[len(ages_after) // 2] if ages_after else math.nan,
        vehicle="hovers on" if still else rig.ap.mode_name,
    )
    assert still, rig.ap.mode_name
    assert 35.0 <= rate <= 50.0, rate
    assert ages[len(ages) // 2] < 0.1, ages[len(ages) // 2]


def _in_namespace(ns: str, *argv: str, timeout: float = 10.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", "netns", "exec", ns, *argv], capture_output=True, text=True, timeout=timeout)


def _netem_reason() -> str:
    """Empty when ``tc … netem`` works in a network namespace here, else why not."""
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None:
        return "network namespaces and tc need root, ip and tc"
    ns = f"arena-netem-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", ns], capture_output=True, text=True, timeout=10)
    if made.returncode != 0:
        return f"'ip netns add' fails: {made.stderr.strip()}"
    try:
        res = _in_namespace(ns, "tc", "qdisc", "add", "dev", "lo", "root", "netem", "delay", "10ms")
        return "" if res.returncode == 0 else f"tc netem unavailable in this kernel: {res.stderr.strip()}"
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


def test_link_loss_and_delay_with_netem() -> None:
    """The radio test again, the whole arena in a network namespace of its own with netem on its links."""
    reason = _netem_reason()
    if reason:
        pytest.skip(f"{reason} (test_lossy_delayed_radio_link measures loss and delay in user space)")
    ns = f"arena-faults-{os.getpid()}"
    subprocess.run(["ip", "netns", "add", ns], check=True, timeout=10)
    try:
        _in_namespace(ns, "ip", "link", "set", "lo", "up")
        env = {**os.environ, "ARENA_FAULTS_LINK": "netem", "ARENA_FAULTS_MULTICAST": "0"}
        argv = [
            PYTHON,
            "-m",
            "pytest",
            "-q",
            "-s",
            "-p",
            "no:cacheprovider",
            f"{__file__}::test_lossy_delayed_radio_link",
        ]
        res = subprocess.run(
            ["ip", "netns", "exec", ns, *argv], capture_output=True, text=True, timeout=300, env=env, cwd=REPO
        )
        print(res.stdout[-4000:])
        assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    finally:
        pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=10)
        for pid in pids.stdout.split():  # nothing should be left; if it is, it goes with the namespace
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


# -- the supervisor itself -----------------------------------------------------------------------------------


def test_supervisor_killed_children_go_and_vehicle_lands(rig: Rig) -> None:
    fly(rig)
    children = dict(rig.up.pids)
    t0 = time.monotonic()
    rig.up.signal(signal.SIGKILL)
    t_gone = wait_time(lambda: not any(alive(p) for p in children.values()), 10.0, "every child gone")
    to_land, to_ground = landed_by_itself(rig, t0)
    assert not rig.ap.tap.invalid
    record(
        "supervisor (arena up) kill -9",
        children_gone_after_s=t_gone - t0,
        failsafe_after_s=to_land,
        touchdown_after_s=to_ground,
        vehicle="every service dies with it (PDEATHSIG): position-loss failsafe lands it",
    )
