"""``arena up`` with ``autopilot = "px4-sitl"`` vehicles: it boots their PX4 SITL instances and truth
bridges with the rest, PX4 fuses the arena's vision, a rebooted PX4 comes back with its saved parameters,
and everything (PX4 included) stops with the arena."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from arena_common import Arena
from arena_common.runtime.px4_sitl import instance_busy, is_true, listener, run_tool
from tests.conftest import REPO, free_port, wait_for
from tests.px4.harness import HOST, InstancePool, write_px4_config


def test_arena_up_boots_px4_sitl_and_stops_it(tmp_path: Path, px4_pool: InstancePool) -> None:
    n = px4_pool.take()
    try:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        cfg = write_px4_config(
            tmp_path / "arena.toml", endpoint, {"d1": n}, services=("router", "sim", "mocap", "transform")
        )
        log = open(tmp_path / "arena.log", "wb")  # noqa: SIM115 - closed in the finally below
        up = subprocess.Popen(
            [sys.executable, "-m", "arena_common.cli", "up", cfg.path, "--host", HOST],
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=REPO,
        )
        try:
            with Arena(cfg, name="px4-tier") as arena:
                d1 = arena.vehicle("d1")
                wait_for(
                    lambda: d1.link and d1.state is not None and d1.state.vis_fused and d1.state.setup_ok,
                    timeout=90,
                    interval=0.2,
                    what="d1: link, vision fused and setup verified",
                )
                alive = {k.rsplit("/", 1)[-1] for k in arena.bus.alive("arena/sys/alive/**", 2.0)}
                assert {"px4-sitl.d1", "px4-truth.d1", "sim-motive", "gateway.d1"} <= alive, alive
                assert "sim-vehicle" not in alive  # no vehicle is simulated: the Motive emulator runs alone
                flags = wait_for(
                    lambda: (f := listener(n, "estimator_status_flags")) and f.get("cs_yaw_align") and f,
                    timeout=30,
                    interval=0.5,
                    what="PX4 aligning its yaw on vision",
                )
                assert is_true(flags, "cs_ev_pos") and is_true(flags, "cs_ev_hgt"), flags
                assert d1.mocap is not None and abs(d1.mocap.p[0] + 1.0) < 0.05  # at sim.start, seen by mocap

                # A SITL's reboot: px4 exits (SITL answers MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN with DENIED, so
                # `px4-shutdown` it is) and px4-sitl.d1 boots it again with the parameters it saved.
                assert run_tool(n, "param", "set", "MPC_XY_CRUISE", "3.5").returncode == 0
                assert run_tool(n, "param", "save").returncode == 0
                run_tool(n, "shutdown")
                wait_for(
                    lambda: "(boot 2, " in (tmp_path / "arena.log").read_text(), timeout=30, what="boot 2"
                )
                wait_for(
                    lambda: (f := listener(n, "estimator_status_flags")) and is_true(f, "cs_ev_pos") and f,
                    timeout=60,
                    interval=0.5,
                    what="the rebooted PX4 fusing the arena's vision again",
                )
                wait_for(lambda: d1.link, timeout=30, interval=0.2, what="d1: link after the reboot")
                shown = run_tool(n, "param", "show", "MPC_XY_CRUISE").stdout
                assert "MPC_XY_CRUISE" in shown and "3.5000" in shown, shown
        finally:
            if up.poll() is None:
                os.killpg(up.pid, signal.SIGINT)
                try:
                    up.wait(30)
                except subprocess.TimeoutExpired:
                    os.killpg(up.pid, signal.SIGKILL)
                    up.wait(5)
            log.close()
        assert up.returncode == 0, (tmp_path / "arena.log").read_text()[-3000:]
        assert not instance_busy(n)  # PX4 stopped with the arena
        text = (tmp_path / "arena.log").read_text(errors="replace")
        assert "[px4-sitl.d1] INFO  [px4] Startup script returned successfully" in text
    finally:
        px4_pool.give_back(n)
