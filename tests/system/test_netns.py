"""Several computers on one machine: Linux network namespaces joined by veth pairs on a bridge.

* ``ground`` — the router, mocap ingest, frame transform and the simulated world (``arena up --host ground``);
* ``cc1``, ``cc2`` — companion computers, each with its vehicle's downsampler and gateway
  (``arena up --host cc1``), reaching the router (and the simulated autopilot) over their own link;
* ``user`` — a user program on :class:`arena_common.client.vehicle.Arena`.

The whole chain runs across them (d1 takes off from the user's laptop); cutting cc1's link makes its
presence vanish within the configured lease and d1's failsafe land it, while d2 stays served; restoring
the link brings cc1 back without any process being restarted.  Every address is inside namespaces this
test creates (10.213.7.0/24); they are deleted, and every process killed, at the end.
"""

from __future__ import annotations

import json
import queue
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import wait_for
from tests.netnslib import Lab, drain, namespaces_usable

pytestmark = [pytest.mark.netns, pytest.mark.system]

SUBNET = "10.213.7"
ADDRESS = {"ground": f"{SUBNET}.1", "cc1": f"{SUBNET}.11", "cc2": f"{SUBNET}.12", "user": f"{SUBNET}.21"}
LEASE_MS = 1000

CONFIG = """
[arena]
name = "netns"
[mocap]
server = "127.0.0.1"
interface = "127.0.0.1"
multicast = false
[security]
insecure = true  # plain peers on the namespaces' network: the insecure topology, on purpose
[zenoh]
mode = "peer"
connect = ["tcp/{ground}:7447"]
router_listen = ["tcp/{ground}:7447"]
lease_ms = {lease}
[hosts.ground]
address = "{ground}"
services = ["router", "sim", "mocap", "transform"]
[hosts.cc1]
address = "{cc1}"
vehicles = ["d1"]
[hosts.cc2]
address = "{cc2}"
vehicles = ["d2"]
[hosts.user]
address = "{user}"
[vehicles.d1]
rigid_body = "d1"
mavlink = "udpin:{cc1}:14541"
system_id = 1
sim = {{ start = [-1.0, 0.0] }}
[vehicles.d2]
rigid_body = "d2"
mavlink = "udpin:{cc2}:14542"
system_id = 2
sim = {{ start = [1.0, 0.0] }}
"""

# The user program: reports what it sees every 0.2 s as JSON lines; takes "takeoff NAME HEIGHT" on stdin.
USER_PROGRAM = textwrap.dedent(
    """
    import json, sys, threading, time
    from arena_common import Arena
    from arena_common.core import keys

    def report(**kw):
        print(json.dumps(kw), flush=True)

    # A laptop's program is a client of the router: it needs no endpoint of its own.
    with Arena(sys.argv[1], mode="client", name="netns-user") as arena:
        vehicles = {n: arena.vehicle(n) for n in ("d1", "d2")}
        truth = {n: arena.bus.subscribe(keys.truth(n), capacity=1) for n in vehicles}
        last_truth = {}

        def fly(name, height):
            try:
                v = vehicles[name]
                v.wait_until(lambda x: x.state is not None, timeout=30, what="first state")
                v.arm()
                v.takeoff(height, timeout=40)
                report(done=f"takeoff {name}")
            except Exception as exc:
                report(error=f"{type(exc).__name__}: {exc}")

        def commands():
            for line in sys.stdin:
                op, name, height = line.split()
                threading.Thread(target=fly, args=(name, float(height)), daemon=True).start()

        threading.Thread(target=commands, daemon=True).start()
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            for n, sub in truth.items():
                item = sub.channel.drain()
                if item and item[-1].payload is not None:
                    last_truth[n] = item[-1].payload.p[2]
            snap = {}
            for n, v in vehicles.items():
                s = v.state
                snap[n] = {"age": v.state_age if s is not None else None, "link": bool(s and s.link),
                           "armed": bool(s and s.armed), "z": last_truth.get(n)}
            report(t=time.time(), alive=arena.bus.alive("arena/sys/alive/**", 0.5), **snap)
            time.sleep(0.2)
    """
)


@pytest.fixture
def lab() -> Iterator[Lab]:
    reason = namespaces_usable()
    if reason:
        pytest.skip(reason)
    the_lab = Lab(ADDRESS)
    try:
        the_lab.build()
        yield the_lab
    finally:
        the_lab.teardown()


class Watcher:
    """The latest report of the user program, and every line it printed."""

    def __init__(self, lines: queue.Queue[str]) -> None:
        self.lines = lines
        self.latest: dict[str, Any] = {}
        self.messages: list[dict[str, Any]] = []
        self.raw: list[str] = []

    def pump(self) -> dict[str, Any]:
        while not self.lines.empty():
            line = self.lines.get()
            self.raw.append(line)
            if not line.startswith("{"):
                continue
            msg = json.loads(line)
            if "alive" in msg:
                self.latest = msg
            else:
                self.messages.append(msg)
        return self.latest

    def alive(self, host: str) -> list[str]:
        return [k for k in self.pump().get("alive", []) if k.startswith(f"arena/sys/alive/{host}/")]

    def fresh(self, vehicle: str, max_age: float = 1.0) -> bool:
        v = self.pump().get(vehicle) or {}
        return v.get("age") is not None and v["age"] < max_age and v["link"]

    def z(self, vehicle: str) -> float | None:
        v = self.pump().get(vehicle) or {}
        return v.get("z")


CC1 = {"gateway.d1", "downsampler.d1", "supervisor"}


def services(alive: list[str]) -> set[str]:
    """Service names of presence keys."""
    return {k.rsplit("/", 1)[1] for k in alive}


@pytest.mark.timeout(420)
def test_several_computers_link_loss_and_recovery(lab: Lab, tmp_path: Path) -> None:
    cfg = tmp_path / "netns.toml"
    cfg.write_text(CONFIG.format(lease=LEASE_MS, **ADDRESS))
    user_program = tmp_path / "user_program.py"
    user_program.write_text(USER_PROGRAM)
    up = [sys.executable, "-m", "arena_common.cli", "up", str(cfg), "--host"]
    logs: dict[str, list[str]] = {h: [] for h in ("ground", "cc1", "cc2")}
    outs = {}
    for host in ("ground", "cc1", "cc2"):
        _, outs[host] = lab.spawn(host, *up, host)

    def pump_logs() -> None:
        for host, q in outs.items():
            drain(q, logs[host])

    # The user's program is a client: it needs the router up when it starts.
    def router_up() -> bool:
        pump_logs()
        return any("routing on" in line for line in logs["ground"])

    wait_for(router_up, timeout=60, what="the router")
    user, user_lines = lab.spawn("user", sys.executable, str(user_program), str(cfg), stdin=True)
    watch = Watcher(user_lines)

    def context() -> str:
        pump_logs()
        tail = {h: "".join(lines[-15:]) for h, lines in logs.items()}
        tail["user"] = "".join(line for line in watch.raw[-15:] if "alive" not in line)
        return json.dumps(watch.latest)[:2000] + "\n" + "\n".join(f"--- {h}\n{t}" for h, t in tail.items())

    try:
        # The whole chain across the namespaces: both vehicles' states reach the user's laptop.
        try:
            wait_for(
                lambda: watch.fresh("d1") and watch.fresh("d2"),
                timeout=120,
                interval=0.2,
                what="d1, d2 states",
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{context()}") from None
        try:  # the supervisor's own token joins a few seconds after its children's (its connect retries)
            wait_for(
                lambda: services(watch.alive("cc1")) >= CC1, timeout=30, interval=0.2, what="cc1 services"
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{context()}") from None
        wait_for(lambda: "transform" in services(watch.alive("ground")), 10.0, 0.2, what="ground's transform")

        # d1 takes off from the user's program: mocap → ground → Wi-Fi → cc1 → autopilot, commands back.
        def takeoff_reported() -> bool:
            watch.pump()
            return any("done" in m or "error" in m for m in watch.messages)

        assert user.stdin is not None
        user.stdin.write("takeoff d1 1.0\n")
        user.stdin.flush()
        try:
            wait_for(takeoff_reported, timeout=90, interval=0.2, what="d1's takeoff")
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{context()}") from None
        assert not [m for m in watch.messages if "error" in m], watch.messages
        z = watch.z("d1")
        assert z is not None and z < -0.8, z
        pump_logs()
        cc1_started = [line for line in logs["cc1"] if line.startswith("[arena] started")]

        # Cut cc1's link: its presence vanishes within the lease (plus a report period), d2 stays served.
        lab.link("cc1", up=False)
        t_cut = time.monotonic()
        wait_for(
            lambda: not watch.alive("cc1"), timeout=LEASE_MS / 1000 * 3 + 3, interval=0.05, what="cc1 gone"
        )
        vanished_after = time.monotonic() - t_cut
        # The failsafe: no more vision for d1, its autopilot lands it on its own.
        try:
            wait_for(
                lambda: (z := watch.z("d1")) is not None and z > -0.15,
                timeout=60,
                interval=0.2,
                what="d1 down",
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{context()}") from None
        assert watch.fresh("d2"), context()

        # Restore the link: everything comes back, nothing restarted.
        lab.link("cc1", up=True)
        t_restore = time.monotonic()
        try:
            wait_for(lambda: services(watch.alive("cc1")) >= CC1, timeout=60, interval=0.2, what="cc1 back")
            wait_for(lambda: watch.fresh("d1"), timeout=60, interval=0.2, what="d1's state back at the user")
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{context()}") from None
        back_after = time.monotonic() - t_restore
        pump_logs()
        for host in ("ground", "cc1", "cc2"):
            restarts = [line for line in logs[host] if "restarting in" in line or "restarted " in line]
            assert not restarts, f"{host}: {restarts}"
        assert [line for line in logs["cc1"] if line.startswith("[arena] started")] == cc1_started
        print(f"cc1 presence vanished {vanished_after:.2f} s after the cut (lease {LEASE_MS} ms); "
              f"back {back_after:.2f} s after the link returned")  # fmt: skip
    finally:
        if user.stdin is not None:
            try:
                user.stdin.close()
            except OSError:
                pass
