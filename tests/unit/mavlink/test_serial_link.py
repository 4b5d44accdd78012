"""A gateway on a serial line (``serial:DEVICE:BAUD``): a companion computer wired to the autopilot.

End to end through a real pseudo-terminal pair made by socat: the gateway opens one end, the simulated
autopilot the other; MAVLink bytes cross the kernel's tty layer as they would a UART.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from arena_common.bus.session import Bus
from arena_common.core import config as config_mod
from arena_common.mavlink.link import Frame, MavlinkLink
from arena_common.mavlink.transports import MavlinkLinkError, open_transport, parse_serial
from tests.helpers import Proc, wait_for, write_config
from tests.unit.gateway.test_gateway import ARENA_PARAMS, Rig

SOCAT = shutil.which("socat")
needs_socat = pytest.mark.skipif(SOCAT is None, reason="socat is not installed (apt-get install socat)")


def pty_pair(processes: Callable[..., Proc], tmp_path: Path) -> tuple[str, str]:
    """Two linked pseudo-terminals (raw, no echo) made by socat: paths of the two ends."""
    a, b = tmp_path / "tty-gateway", tmp_path / "tty-autopilot"
    assert SOCAT is not None
    processes(
        "socat",
        [SOCAT, "-d", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
    )
    wait_for(lambda: a.exists() and b.exists(), 10.0, what="socat's pseudo-terminals")
    return str(a), str(b)


def test_serial_connection_strings() -> None:
    assert parse_serial("/dev/ttyTHS1:921600", "serial:/dev/ttyTHS1:921600") == ("/dev/ttyTHS1", 921600)
    assert parse_serial("/dev/ttyUSB0", "serial:/dev/ttyUSB0") == ("/dev/ttyUSB0", 57600)
    with pytest.raises(MavlinkLinkError, match="baud rate 7 out of"):
        parse_serial("/dev/ttyUSB0:7", "serial:/dev/ttyUSB0:7")
    with pytest.raises(MavlinkLinkError, match=r"expected serial:DEVICE\[:BAUD\]"):
        parse_serial(":921600", "serial::921600")
    with pytest.raises(
        MavlinkLinkError, match="cannot open MAVLink connection 'serial:/nonexistent/tty:9600'"
    ):
        open_transport("serial:/nonexistent/tty:9600")


@needs_socat
def test_frames_cross_a_pseudo_terminal_pair(processes: Callable[..., Proc], tmp_path: Path) -> None:
    a, b = pty_pair(processes, tmp_path)
    gw = MavlinkLink(f"serial:{a}:921600", 1)
    ap = MavlinkLink(f"serial:{b}:921600", 245, source_system=1, source_component=1)
    gw.open()
    ap.open()
    try:
        for i in range(50):
            assert ap.send(ap.mav.heartbeat_encode(2, 12, 0, i, 4))
        got: list[Frame] = []

        def fifty() -> bool:
            got.extend(gw.read(0.05))
            return len(got) >= 50

        wait_for(fifty, 5.0, what="50 frames")
        assert [f.msgid for f in got] == [0] * 50 and gw.bad_crc == 0 and gw.garbage == 0
        msg = gw.decode(got[-1])
        assert msg is not None and msg.get_type() == "HEARTBEAT" and msg.system_status == 4
    finally:
        gw.close()
        ap.close()


@needs_socat
def test_gateway_flies_a_vehicle_over_a_serial_line(
    processes: Callable[..., Proc], tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]
) -> None:
    a, b = pty_pair(processes, tmp_path)
    # Real time: at 2x a busy machine's starved vision stream reaches PX4's 1 s no-aid timeout in 0.3 s.
    path = write_config(tmp_path, router_endpoint, 1, speed=1.0)
    text = re.sub(r'mavlink = "udpin:[^"]+"', f'mavlink = "serial:{a}:921600"', path.read_text())
    text = text.replace("sim = { start = [", f'sim = {{ mavlink = "serial:{b}:921600", start = [')
    path.write_text(text)
    cfg = config_mod.load(path)
    assert cfg.vehicle("d1").mavlink == f"serial:{a}:921600"
    rig = Rig(cfg, bus_factory(), speed=1.0, params=ARENA_PARAMS)
    try:
        gw = rig.start_gateway("d1")
        rig.wait_ready("d1", 20.0)
        rig.fly("d1", 1.0)  # vision fused, armed, took off to 1 m and holds: all through the tty pair
        assert gw.link.frames_in > 100 and gw.link.bad_crc == 0
        assert gw.timesync.answered > 0  # the autopilot's TIMESYNC crossed both ways
        rig.ok("d1", "land", timeout=20.0)
        rig.wait_state("d1", lambda s: not s.armed, 30.0, "landed and disarmed")
    finally:
        rig.close()
