"""Where one per-vehicle process's idle memory and CPU go: ``python -m bench.idle``.

Starts a Zenoh router and one MAVLink gateway on a config of free ports (its vehicle's MAVLink peer is a
socket of this tool: no autopilot answers, no mocap flows), waits until it is alive, then measures over
``--seconds``: the CPU of each of its threads (``/proc/<pid>/task/<tid>/schedstat``, ns) and how many
times each woke (``/proc/<pid>/task/<tid>/status``: voluntary context switches), its RSS, and, in a fresh
interpreter, the RSS each import of the gateway's adds (``VmRSS`` after each, in import order).
One process at a time: cheap enough for a shared machine.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.harness import ProcessSet, free_port, python_module, rss_bytes, wait_port

REPO = Path(__file__).resolve().parents[1]

#: The imports of a gateway process, in the order it takes them; each one's RSS is what it adds.
IMPORTS = (
    "msgspec",
    "zenoh",
    "arena_common.core.wire",
    "arena_common.bus.session",
    "arena_common",
    "typer",
    "rich.console",
    "pymavlink.dialects.v20.all",
    "arena_common.mavlink.link",
    "arena_common.gateway.gateway",
    "arena_common.runtime.service",
    "services.mavlink_gateway",
)


def write_config(directory: Path, peer_port: int) -> Path:
    """A config of free ports: a router and one vehicle, x1, whose gateway sends to ``peer_port``."""
    router = free_port(__import__("socket").SOCK_STREAM)
    lines = [
        "[arena]",
        'name = "idle"',
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["tcp/127.0.0.1:{router}"]',
        f'router_listen = ["tcp/127.0.0.1:{router}"]',
        "[hosts.idle]",
        'services = ["router"]',
        'vehicles = ["x1"]',
        "[pipeline]",
        'decimate = "transform"',
        "[vehicles.x1]",
        'rigid_body = "x1"',
        f'mavlink = "udpout:127.0.0.1:{peer_port}"',
        "system_id = 1",
    ]
    path = directory / "idle.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def threads(pid: int) -> dict[int, dict[str, Any]]:
    """Each thread of ``pid``: name, CPU ns so far, voluntary context switches (its wake-ups)."""
    out: dict[int, dict[str, Any]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            ns = int((task / "schedstat").read_text().split()[0])
            status = (task / "status").read_text()
        except (OSError, ValueError):
            continue
        switches = next(
            (int(line.split()[1]) for line in status.splitlines() if line.startswith("voluntary_ctxt")), 0
        )
        out[int(task.name)] = {"name": name, "ns": ns, "wakeups": switches}
    return out


def rollup(pid: int) -> dict[str, float]:
    """``/proc/<pid>/smaps_rollup`` in MB: Rss, Pss (shared pages split among their users), and
    Private (Private_Clean + Private_Dirty: what the process alone holds, freed when it ends)."""
    fields: dict[str, float] = {}
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
            name, value = line.split(":", 1)
            fields[name] = int(value.split()[0]) / 1024
    except (OSError, ValueError, IndexError):
        return {}
    return {
        "rss": fields.get("Rss", 0.0),
        "pss": fields.get("Pss", 0.0),
        "private": fields.get("Private_Clean", 0.0) + fields.get("Private_Dirty", 0.0),
        "anonymous": fields.get("Anonymous", 0.0),
    }


def py_threads(pid: int) -> dict[int, str]:
    """The Python name of each thread of ``pid`` by its thread id (``py-spy dump``; empty without py-spy)."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    try:
        res = subprocess.run([spy, "dump", "--pid", str(pid)], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return {}
    found = re.findall(r'^Thread (0x[0-9A-Fa-f]+|\d+) \([^)]*\): "([^"]*)"', res.stdout, re.M)
    return {int(tid, 0): name for tid, name in found}


def import_rss() -> list[tuple[str, float]]:
    """RSS (MB) each of :data:`IMPORTS` adds, imported in order in a fresh interpreter."""
    code = (
        "import importlib, json, sys\n"
        "def rss():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmRSS:'): return int(line.split()[1]) / 1024\n"
        "out = [('python', rss())]\n"
        "for m in sys.argv[1:]:\n"
        "    importlib.import_module(m); out.append((m, rss()))\n"
        "print(json.dumps(out))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, *IMPORTS], capture_output=True, text=True, cwd=REPO, check=True
    )
    rows = json.loads(res.stdout)
    return [(rows[0][0], rows[0][1])] + [(m, b - a) for (_, a), (m, b) in itertools.pairwise(rows)]


def measure(seconds: float, settle: float = 5.0) -> dict[str, Any]:
    """One idle gateway measured over ``seconds`` after ``settle`` s: threads, CPU, RSS."""
    import socket

    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    with tempfile.TemporaryDirectory(prefix="bench-idle-") as tmp, ProcessSet(Path(tmp)) as procs:
        path = write_config(Path(tmp), peer.getsockname()[1])
        common = ["-c", str(path), "--host", "idle", "--log-level", "WARNING"]
        procs.spawn("router", "router", python_module("arena_common.cli", "router", *common[:2]), REPO)
        router = int(path.read_text().split("tcp/127.0.0.1:")[1].split('"')[0])
        wait_port(router, 30, "the Zenoh router", procs)
        t0 = time.monotonic()
        gw = procs.spawn(
            "gateway", "gateway", python_module("services.mavlink_gateway", *common, "--vehicle", "x1"), REPO
        )
        peer.settimeout(60)
        peer.recv(512)  # its first HEARTBEAT: the gateway is up
        started = time.monotonic() - t0
        time.sleep(settle)
        before = threads(gw.pid)
        time.sleep(seconds)
        after = threads(gw.pid)
        names = py_threads(gw.pid)
        procs.check_alive()
        rss = rss_bytes(gw.pid) or 0
        memory = rollup(gw.pid)
    peer.close()
    rows = []
    for tid, a in after.items():
        b = before.get(tid, {"ns": 0, "wakeups": 0})
        rows.append(
            {
                "name": names.get(tid, a["name"]),
                "cpu": 100 * (a["ns"] - b["ns"]) / 1e9 / seconds,
                "wakeups_per_s": (a["wakeups"] - b["wakeups"]) / seconds,
            }
        )
    rows.sort(key=lambda r: -r["cpu"])
    return {
        "seconds": seconds,
        "start_s": started,
        "rss_mb": rss / 2**20,
        "memory_mb": memory,
        "threads": rows,
        "cpu": sum(r["cpu"] for r in rows),
        "wakeups_per_s": sum(r["wakeups_per_s"] for r in rows),
    }


def main(argv: list[str] | None = None) -> None:
    """Print the idle gateway's threads, CPU and RSS, and the RSS by import."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measurement window (s)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    found = measure(args.seconds)
    found["imports"] = import_rss()
    if args.json:
        print(json.dumps(found, indent=1))
        return
    print(
        f"idle gateway: RSS {found['rss_mb']:.1f} MB, CPU {found['cpu']:.2f} % of a core, "
        f"{found['wakeups_per_s']:.0f} wake-ups/s, {len(found['threads'])} threads, "
        f"first HEARTBEAT {found['start_s']:.1f} s after start"
    )
    mem = found["memory_mb"]
    if mem:
        print(
            f"  memory: Rss {mem['rss']:.1f} MB, Pss {mem['pss']:.1f} MB, private {mem['private']:.1f} MB "
            f"(anonymous {mem['anonymous']:.1f} MB)"
        )
    for r in found["threads"]:
        print(f"  {r['name']:<16} {r['cpu']:6.3f} %  {r['wakeups_per_s']:7.1f} wake-ups/s")
    print("RSS by import (MB added, in import order):")
    for name, mb in found["imports"]:
        print(f"  {name:<32} {mb:6.1f}")


if __name__ == "__main__":
    main()
