"""Computers on one machine for tests: Linux network namespaces joined by veth pairs on a bridge.

Every address lives inside namespaces the test creates (a private /24 of its own); they are deleted, and
every process in them killed, at the end.
"""

from __future__ import annotations

import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import uuid
from pathlib import Path

from tests.helpers import REPO


def run(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run a command (30 s at most), its output captured."""
    return subprocess.run(list(args), capture_output=True, text=True, timeout=30, check=check)


def namespaces_usable() -> str:
    """Empty when this machine can build namespaces, else the reason it cannot."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    probe = f"arena-probe-{uuid.uuid4().hex[:6]}"
    res = run("ip", "netns", "add", probe, check=False)
    if res.returncode != 0:
        return f"'ip netns add' fails here: {res.stderr.strip()}"
    run("ip", "netns", "del", probe, check=False)
    return ""


class Lab:
    """Namespaces named after hosts (the first is the bridge's), their links, the processes run in them."""

    def __init__(self, addresses: dict[str, str]) -> None:
        tag = uuid.uuid4().hex[:5]
        self.address = dict(addresses)
        self.bridge_host = next(iter(addresses))
        self.ns = {h: f"arena-{tag}-{h}" for h in addresses}
        self.veth = {h: f"ar{tag}{h[:3]}{i}" for i, h in enumerate(addresses) if h != self.bridge_host}
        self.procs: list[subprocess.Popen[str]] = []

    def build(self) -> None:
        g = self.ns[self.bridge_host]
        for ns in self.ns.values():
            run("ip", "netns", "add", ns)
            run("ip", "-n", ns, "link", "set", "lo", "up")
        run("ip", "-n", g, "link", "add", "br0", "type", "bridge")
        run("ip", "-n", g, "addr", "add", f"{self.address[self.bridge_host]}/24", "dev", "br0")
        run("ip", "-n", g, "link", "set", "br0", "up")
        for host, veth in self.veth.items():
            ns = self.ns[host]
            run("ip", "link", "add", veth, "netns", g, "type", "veth", "peer", "name", "eth0", "netns", ns)
            run("ip", "-n", g, "link", "set", veth, "master", "br0", "up")
            run("ip", "-n", ns, "addr", "add", f"{self.address[host]}/24", "dev", "eth0")
            run("ip", "-n", ns, "link", "set", "eth0", "up")

    def link(self, host: str, up: bool) -> None:
        run("ip", "-n", self.ns[host], "link", "set", "eth0", "up" if up else "down")

    def listening(self, host: str) -> set[tuple[str, str, int]]:
        """``(protocol, address, port)`` of every socket listening in ``host``'s namespace (``ss``)."""
        out = run("ip", "netns", "exec", self.ns[host], "ss", "-lntuH").stdout
        found = set()
        for line in out.splitlines():
            cols = line.split()
            if len(cols) < 5:
                continue
            address, _, port = cols[4].rpartition(":")
            found.add((cols[0], address.strip("[]"), int(port)))
        return found

    def spawn(
        self,
        host: str,
        *argv: str,
        stdin: bool = False,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
    ) -> tuple[subprocess.Popen[str], queue.Queue[str]]:
        """Start ``argv`` in ``host``'s namespace (in ``cwd``, default the repository); its output lines
        arrive in the returned queue."""
        proc = subprocess.Popen(
            ["ip", "netns", "exec", self.ns[host], *argv],
            cwd=cwd or REPO,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        self.procs.append(proc)
        lines: queue.Queue[str] = queue.Queue()

        def pump() -> None:
            for line in proc.stdout or ():
                lines.put(line)

        threading.Thread(target=pump, daemon=True).start()
        return proc, lines

    def teardown(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in reversed(self.procs):
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        for ns in self.ns.values():
            # Anything still inside (it should not be) goes with its namespace.
            for pid in run("ip", "netns", "pids", ns, check=False).stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            run("ip", "netns", "del", ns, check=False)


def drain(lines: queue.Queue[str], into: list[str]) -> list[str]:
    """Move every waiting line of ``lines`` to ``into``."""
    while not lines.empty():
        into.append(lines.get())
    return into
