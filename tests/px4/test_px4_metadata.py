"""PX4's parameter metadata read from a real PX4 v1.16 SITL over MAVLink (component metadata + FTP), and
compared with the build's own ``parameters.json``: the reboot-required parameters come from PX4.

PX4 is found from ``$PX4_SITL_DIR``, else ``<repo>/../shared/px4-sitl`` (skipped with the reason when
absent).  It runs as an instance among 20–24 (the first free one).  Instances of 10 and above send their
offboard link to port 14549, shared by all of them, until a peer speaks: so the link here is
``udpout:127.0.0.1:<14580+i>`` and speaks first (a heartbeat), and PX4 answers to its address.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from arena_common.mavlink import metadata as pm
from arena_common.mavlink.link import MSG, MavlinkLink, mavlink2
from arena_common.runtime import px4_sitl as sitl

pytestmark = pytest.mark.px4

INSTANCES = range(20, 25)  # the instance numbers this module may use
REBOOT_PARAMS = ("EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_MAG_TYPE")


@dataclass
class Px4Vehicle:
    """A running PX4 SITL instance and an open link to its offboard port."""

    instance: int
    system_id: int
    build: Path
    link: MavlinkLink
    log: Path


def _tail(path: Path, n: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return "(no output)"


@pytest.fixture(scope="module")
def vehicle(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Px4Vehicle]:
    """PX4 started for this module, with a link that PX4 has latched on (it heard our heartbeat)."""
    reason = sitl.build_missing_reason()
    if reason is not None:
        pytest.skip(reason)
    build = sitl.find_build()
    instance = next((i for i in INSTANCES if not sitl.instance_busy(i)), None)
    if instance is None:
        pytest.skip(
            f"every PX4 instance this module may use ({INSTANCES.start}–{INSTANCES.stop - 1}) is busy"
        )
    root = tmp_path_factory.mktemp(f"px4-{instance}")
    tools = sitl.link_tools(build, root / "bin")
    work = root / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_PARAM_")}
    env.update(PATH=f"{tools}{os.pathsep}{env.get('PATH', '')}", PX4_SIM_MODEL="sihsim_quadx")
    env["PX4_PARAM_SDLOG_MODE"] = "-1"  # no flight log
    log = root / "px4.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [str(tools / "px4"), str(build / "etc"), "-i", str(instance), "-d", "-w", str(work)],
            cwd=work,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    system_id = instance + 1
    link = MavlinkLink(f"udpout:127.0.0.1:{14580 + instance}", system_id)
    try:
        link.open()
        heartbeat = link.mav.heartbeat_encode(
            mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0
        )
        until = time.monotonic() + 60.0
        heard = False
        while not heard:
            if proc.poll() is not None:
                pytest.fail(f"PX4 instance {instance} exited ({proc.returncode}):\n{_tail(log)}")
            if time.monotonic() > until:
                pytest.fail(f"no HEARTBEAT from PX4 instance {instance} within 60 s:\n{_tail(log)}")
            link.send(heartbeat)  # until PX4 listens: the first peer it hears is where it answers
            heard = any(f.msgid == MSG["HEARTBEAT"] for f in link.read(0.5))
        yield Px4Vehicle(instance, system_id, build, link, log)
    finally:
        link.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(10.0)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5.0)


class Reader:
    """The gateway's reader in small: reads the link, hands the metadata messages to the client.

    ``lose_every`` > 0 drops every n-th FILE_TRANSFER_PROTOCOL frame, as a lossy radio would.
    """

    def __init__(self, link: MavlinkLink, client: pm.MetadataClient, lose_every: int = 0) -> None:
        self.link = link
        self.lose_every = lose_every
        self.lost = 0
        self.handlers = dict.fromkeys(pm.HANDLED_MESSAGES, client.on_message)
        self.seen: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="px4-test-reader", daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            for frame in self.link.read(0.05):
                handler = self.handlers.get(frame.msgid)
                if handler is None:
                    continue
                if frame.msgid == pm.FILE_TRANSFER_PROTOCOL and self.lose_every:
                    n = self.seen.get(-1, 0) + 1
                    self.seen[-1] = n
                    if n % self.lose_every == 0:
                        self.lost += 1
                        continue
                msg = self.link.decode(frame)
                if msg is not None:
                    self.seen[frame.msgid] = self.seen.get(frame.msgid, 0) + 1
                    handler(msg, time.monotonic())

    def __enter__(self) -> Reader:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


def test_reboot_required_parameters_from_px4(vehicle: Px4Vehicle) -> None:
    client = pm.MetadataClient(vehicle.link, vehicle.system_id)
    with Reader(vehicle.link, client) as reader:
        meta = client.fetch(time.monotonic() + 60.0)
    for name in REBOOT_PARAMS:
        assert meta[name]["rebootRequired"] is True, name
    local = pm.load_parameters_json(vehicle.build / "parameters.json")
    assert pm.reboot_required(meta) == pm.reboot_required(local)
    assert meta == local  # the vehicle serves its build's metadata, entry for entry
    info = client.info
    assert info.source_message == "COMPONENT_METADATA"
    assert info.general_uri.startswith("mftp://") and info.general_uri.endswith("component_general.json.xz")
    assert info.parameter_uri.startswith("mftp://") and info.parameter_uri.endswith("parameters.json.xz")
    assert info.general_crc_ok is True and info.parameter_crc_ok is True
    assert info.ftp["naks"] >= 1  # EOF ends a burst
    assert reader.seen.get(pm.FILE_TRANSFER_PROTOCOL, 0) >= info.parameter_size // pm.FTP_DATA_MAX
    print(f"PX4 instance {vehicle.instance}: {info}")


def test_lossy_link(vehicle: Px4Vehicle) -> None:
    """Every 13th FTP message from PX4 lost: the holes are read again (ReadFile), the result is whole."""
    client = pm.MetadataClient(vehicle.link, vehicle.system_id, timeout=0.3)
    with Reader(vehicle.link, client, lose_every=13) as reader:
        meta = client.fetch(time.monotonic() + 120.0)
    assert reader.lost > 0
    assert meta == pm.load_parameters_json(vehicle.build / "parameters.json")
    assert client.info.ftp["reads"] > 0 or client.info.ftp["resent"] > 0
    print(f"lossy: {reader.lost} lost, {client.info.ftp}, {client.info.seconds['total']:.2f} s")


def test_component_information_answers_too(vehicle: Px4Vehicle) -> None:
    client = pm.MetadataClient(vehicle.link, vehicle.system_id, request_messages=(pm.COMPONENT_INFORMATION,))
    with Reader(vehicle.link, client):
        message, uri, crc = client.general_metadata_uri(time.monotonic() + 20.0)
    assert message == "COMPONENT_INFORMATION"
    assert uri.endswith("component_general.json.xz") and crc != 0


def test_missing_file_is_named_by_px4(vehicle: Px4Vehicle) -> None:
    client = pm.MetadataClient(vehicle.link, vehicle.system_id)
    with Reader(vehicle.link, client), pytest.raises(pm.FtpNak, match="FileNotFound") as info:
        client.read_file("/etc/extras/no-such-file.json", time.monotonic() + 20.0)
    assert info.value.op_name == "OpenFileRO" and info.value.path == "/etc/extras/no-such-file.json"


def test_fetch_with_its_own_reader(vehicle: Px4Vehicle) -> None:
    meta = pm.fetch_parameter_metadata(vehicle.link, vehicle.system_id, time.monotonic() + 60.0)
    assert set(REBOOT_PARAMS) <= pm.reboot_required(meta)
