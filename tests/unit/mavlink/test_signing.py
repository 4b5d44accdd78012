"""MAVLink 2 signing between the gateway and its (simulated) PX4, and the EKF origin the gateway gives it.

Key files and the spec's rules are checked on their own; then real links on 127.0.0.1: a signed flight
through the gateway with a tap recording every datagram (all signed, pymavlink's own check agrees, the
origin goes to the vehicle's system id, a captured arm command replayed later is refused), plain pymavlink
scripts without the key, with a wrong key and with a replayed frame against the simulated vehicle, a
gateway with the wrong key, and the gateway service as a real process.  No test ever sees the key in a log.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from arena_common.bus.session import Bus
from arena_common.cli import app
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.gateway.gateway import Gateway, GatewayOptions
from arena_common.mavlink import px4
from arena_common.mavlink.link import FrameSplitter, MavlinkLink, mavlink2
from arena_common.mavlink.signing import (
    EPOCH_2015,
    GATEWAY_UNSIGNED,
    LinkSigning,
    SigningError,
    SigningKey,
    generate_key_file,
    key_path,
    load_key,
    parse_key,
    setup_signing,
    signing_timestamp,
    vehicle_key,
    write_px4_secret,
)
from arena_common.runtime.service import running
from arena_common.sim.autopilot import AutopilotLoop, SimAutopilot, SimClock
from services.sim_vehicle import build_autopilots
from tests.helpers import REPO, Proc, free_port, service_argv, wait_for, write_config

SPEED = 2.0
ARENA_PARAMS: dict[str, Any] = {name: value for name, (value, _) in px4.ARENA_REQUIRED_PARAMS.items()}
ORIGIN = (47.397742, 8.545594, 488.0)
FORCE = float(px4.ARM_DISARM_FORCE_MAGIC)


def secrets_of(*keys_: SigningKey) -> list[str]:
    """Every spelling of the keys that must never appear in a log or an event."""
    out = []
    for k in keys_:
        out += [k.secret.hex(), k.secret.hex().upper(), repr(k.secret), str(list(k.secret))[1:-1]]
    return out


def assert_secret_free(text: str, *keys_: SigningKey) -> None:
    for s in secrets_of(*keys_):
        assert s not in text, "a signing key leaked"


def signed_config(tmp_path: Path, router_endpoint: str, key_file: str, speed: float = SPEED) -> ArenaConfig:
    """A one-vehicle config (private ports) whose d1 signs with ``key_file``."""
    path = write_config(tmp_path, router_endpoint, 1, speed=speed)
    text = path.read_text().replace("[vehicles.d1]\n", f'[vehicles.d1]\nsigning_key_file = "{key_file}"\n')
    path.write_text(text)
    return config_mod.load(path)


def with_sim_link(cfg: ArenaConfig, url: str) -> ArenaConfig:
    v = cfg.vehicle("d1")
    return cfg.replace(vehicles={"d1": v.replace(sim=v.sim.replace(mavlink=url))})


def encoder(sysid: int, key: SigningKey | None = None, link_id: int = 0) -> Any:
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    if key is not None:
        LinkSigning(key, link_id=link_id).attach(mav)
    return mav


def frames_of(datagrams: list[bytes]) -> list[Any]:
    splitter = FrameSplitter(stream=False)
    return [f for d in datagrams for f in splitter.feed(d)]


# ----------------------------------------------------------------------------------------- key files
def test_key_files_generate_load_and_fail_clearly(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    path = tmp_path / "d1.key"
    key = generate_key_file(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    text = path.read_text()
    assert len(text) == 65 and text.endswith("\n") and bytes.fromhex(text.strip()) == key.secret
    assert load_key(path) == key and load_key(path).fingerprint == key.fingerprint
    assert len(key.fingerprint) == 8 and key.fingerprint not in key.secret.hex()
    with pytest.raises(SigningError, match="exists already"):
        generate_key_file(path)
    other = generate_key_file(path, overwrite=True)
    assert other != key and load_key(path) == other
    assert parse_key(f"  {key.secret.hex().upper()}\n") == key  # whitespace and upper case are fine

    bad = tmp_path / "bad.key"
    cases = {
        "": "found 0 characters",
        key.secret.hex()[:40]: "expected 64 hex digits",
        key.secret.hex() + "ab": "found 66 characters",
        key.secret.hex()[:-1] + "g": "character 64 of 64 is not",
        "00" * 32: "all zeros",
    }
    for content, message in cases.items():
        bad.write_text(content)
        bad.chmod(0o600)
        with pytest.raises(SigningError, match=message) as err:
            load_key(bad)
        assert str(bad) in str(err.value)
        if len(content) > 8:
            assert content[:8] not in str(err.value)  # the error never echoes the key material
    bad.write_bytes(b"\xff" * 64)
    with pytest.raises(SigningError, match="not a text file"):
        load_key(bad)
    with pytest.raises(SigningError, match=r"does not exist.*arena px4 keygen"):
        load_key(tmp_path / "missing.key")
    with pytest.raises(SigningError, match="not a regular file"):
        load_key(tmp_path)
    assert isinstance(SigningError("x"), config_mod.ConfigError)  # services report it like a config error

    # Readable by others: loaded, with a warning that names the file and the fix (never the key).
    path.chmod(0o644)
    caplog.clear()
    assert load_key(path) == other
    assert "accessible to other users (mode 644): chmod 600" in caplog.text and str(path) in caplog.text
    assert_secret_free(caplog.text, key, other)

    # PX4's own file: 32 bytes of key, then the u64 little-endian timestamp.
    px4_file = tmp_path / "secret"
    write_px4_secret(px4_file, other, timestamp=123456789)
    raw = px4_file.read_bytes()
    assert raw[:32] == other.secret and int.from_bytes(raw[32:], "little") == 123456789 and len(raw) == 40
    assert stat.S_IMODE(px4_file.stat().st_mode) == 0o600


def test_the_key_never_shows(tmp_path: Path) -> None:
    key = generate_key_file(tmp_path / "k")
    signing = LinkSigning(key)
    shown = " ".join([repr(key), str(key), f"{key}", repr(signing), str(signing)])
    assert key.fingerprint in shown
    assert_secret_free(shown, key)
    with pytest.raises(TypeError):
        pickle.dumps(key)
    with pytest.raises(SigningError):
        SigningKey(b"short")
    with pytest.raises(SigningError, match="link id"):
        LinkSigning(key, link_id=256)


def test_vehicle_key_path_is_relative_to_the_config(
    tmp_path: Path, router_endpoint: str, arena_config: Callable[..., ArenaConfig]
) -> None:
    assert vehicle_key(arena_config(), "d1") is None  # no signing_key_file: no signing
    key = generate_key_file(tmp_path / "d1.key")
    cfg = signed_config(tmp_path, router_endpoint, "d1.key")
    assert key_path(cfg, "d1") == tmp_path / "d1.key"
    assert vehicle_key(cfg, "d1") == key
    absolute = signed_config(tmp_path, router_endpoint, str(tmp_path / "d1.key"))
    assert vehicle_key(absolute, "d1") == key
    missing = signed_config(tmp_path, router_endpoint, "nope.key")
    with pytest.raises(
        SigningError, match=r"vehicles\.d1\.signing_key_file: .*nope\.key: signing key file does"
    ):
        vehicle_key(missing, "d1")
    with pytest.raises(SigningError, match="signing_key_file"):
        Gateway(missing, "d1", None)  # a gateway with a bad key file never starts


def test_keygen_command(tmp_path: Path) -> None:
    runner = CliRunner()
    path = tmp_path / "lab" / "d1.key"
    path.parent.mkdir()
    result = runner.invoke(app, ["px4", "keygen", str(path), "--px4-file", str(tmp_path / "secret")])
    assert result.exit_code == 0, result.output
    key = load_key(path)
    assert key.fingerprint in result.output
    assert_secret_free(result.output, key)
    assert (tmp_path / "secret").read_bytes()[:32] == key.secret
    again = runner.invoke(app, ["px4", "keygen", str(path)])
    assert again.exit_code == 2 and "exists already" in again.output and load_key(path) == key
    forced = runner.invoke(app, ["px4", "keygen", str(path), "--force"])
    assert forced.exit_code == 0 and load_key(path) != key


# ------------------------------------------------------------------------------------- the spec rules
def test_signing_rules_of_the_spec(tmp_path: Path) -> None:
    key = generate_key_file(tmp_path / "a.key")
    wrong = generate_key_file(tmp_path / "b.key")
    assert signing_timestamp(EPOCH_2015 + 1.5) == 150_000  # 10 µs units since 2015-01-01
    assert abs(signing_timestamp() - (time.time() - EPOCH_2015) * 1e5) < 1e5

    vehicle = encoder(1, key)
    rx = LinkSigning(key)  # the gateway's view
    hb = vehicle.heartbeat_encode(2, 12, 0, 0, 3)
    f1 = bytes(hb.pack(vehicle))
    f2 = bytes(vehicle.sys_status_encode(0, 0, 0, 500, 12000, -1, 90, 0, 0, 0, 0, 0, 0).pack(vehicle))
    assert f1[2] & 0x01 and len(f1) == 12 + f1[1] + 13  # incompat flag, 13 signature bytes
    ts1 = int.from_bytes(f1[-12:-6], "little")
    assert abs(ts1 - signing_timestamp()) < 2e5 and int.from_bytes(f2[-12:-6], "little") == ts1 + 1
    # Signed frames survive the gateway's own framing, in a stream cut anywhere and in datagrams.
    splitter = FrameSplitter(stream=True)
    stream = f1 + f2
    got = [f for i in range(0, len(stream), 7) for f in splitter.feed(stream[i : i + 7])]
    assert [f.raw for f in got] == [f1, f2] and [f.msgid for f in got] == [0, 1]
    assert [f.raw for f in FrameSplitter(stream=False).feed(f1 + f2)] == [f1, f2]

    assert rx.check(f1, 0, 1, 1) is None
    assert rx.check(f1, 0, 1, 1) == "replayed"  # the same frame again
    assert rx.check(f2, 1, 1, 1) is None
    tampered = bytearray(f2)
    tampered[12] ^= 0x01  # one payload bit
    assert rx.check(bytes(tampered), 1, 1, 1) == "bad signature"
    other = encoder(1, wrong)
    assert rx.check(bytes(hb.pack(other)), 0, 1, 1) == "bad signature"
    plain = encoder(1)
    assert rx.check(bytes(plain.heartbeat_encode(2, 12, 0, 0, 3).pack(plain)), 0, 1, 1) == "unsigned"
    radio = bytes(plain.radio_status_encode(200, 190, 90, 10, 12, 0, 0).pack(plain))
    assert rx.check(radio, 109, 1, 1) is None and rx.accepted_unsigned == 1  # radios cannot sign
    assert 109 in GATEWAY_UNSIGNED and 0 not in GATEWAY_UNSIGNED

    # A new stream (another link id) more than a minute behind our timestamp is stale; within, accepted.
    old = encoder(1, key, link_id=3)
    old.signing.timestamp = rx.timestamp - 61 * 100_000
    assert rx.check(bytes(hb.pack(old)), 0, 1, 1) == "stale timestamp"
    recent = encoder(1, key, link_id=4)
    recent.signing.timestamp = rx.timestamp - 50 * 100_000
    assert rx.check(bytes(hb.pack(recent)), 0, 1, 1) is None

    # A forged frame with a timestamp far ahead does not lock the real sender out (the signature is
    # checked before the timestamp is recorded), and a genuine one from the future moves our clock.
    forged = bytearray(hb.pack(vehicle))
    forged[-12:-6] = (ts1 + 10**9).to_bytes(6, "little")
    assert rx.check(bytes(forged), 0, 1, 1) == "bad signature"
    assert rx.check(bytes(hb.pack(vehicle)), 0, 1, 1) is None
    ahead = encoder(1, key, link_id=5)
    ahead.signing.timestamp = rx.timestamp + 10**8
    assert rx.check(bytes(hb.pack(ahead)), 0, 1, 1) is None
    ours = encoder(200)
    rx.attach(ours)
    rx.refresh()
    assert ours.signing.timestamp >= ts1 + 10**8
    assert dict(rx.rejected) == {"replayed": 1, "bad signature": 3, "unsigned": 1, "stale timestamp": 1}

    # pymavlink's own check agrees with ours on frames we sign.
    check = mavlink2.MAVLink(None)
    check.signing.secret_key = key.secret
    sent = [bytes(hb.pack(ours)) for _ in range(3)]
    for raw in sent:
        assert check.decode(bytearray(raw)).get_type() == "HEARTBEAT"
    assert check.signing.goodsig_count == 3 and check.signing.badsig_count == 0
    assert len({int.from_bytes(r[-12:-6], "little") for r in sent}) == 3  # one timestamp per frame


def test_link_verifies_before_anything_sees_a_frame(tmp_path: Path) -> None:
    key = generate_key_file(tmp_path / "k")
    port = free_port(socket.SOCK_DGRAM)
    rejected: list[tuple[str, int]] = []
    link = MavlinkLink(
        f"udpin:127.0.0.1:{port}",
        1,
        signing=LinkSigning(key),
        on_reject=lambda reason, frame: rejected.append((reason, frame.msgid)),
    )
    link.open()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        plain, signed = encoder(1), encoder(1, key)
        sock.sendto(bytes(plain.heartbeat_encode(2, 12, 0, 0, 3).pack(plain)), ("127.0.0.1", port))
        assert not wait_for_frames(link, 0.3) and rejected == [("unsigned", 0)]
        assert not link.can_send()  # an unsigned frame does not tell the link where the vehicle is
        good = bytes(signed.heartbeat_encode(2, 12, 0, 0, 3).pack(signed))
        sock.sendto(good, ("127.0.0.1", port))
        frames = wait_for_frames(link, 2.0)
        assert [f.raw for f in frames] == [good] and link.can_send()
        assert link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
        sock.settimeout(2.0)
        out, _ = sock.recvfrom(1024)
        assert out[2] & 0x01 and LinkSigning(key).check(out, 0, 245, 191) is None
    finally:
        sock.close()
        link.close()


def wait_for_frames(link: MavlinkLink, timeout: float) -> list[Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        frames = link.read(0.05)
        if frames:
            return frames
    return []


# ----------------------------------------------------------------------------------- the whole link
class Tap:
    """A UDP relay between the simulated vehicle (``udpout`` to :attr:`port`) and the gateway's ``udpin``
    port, recording every datagram both ways; :meth:`inject` sends bytes to the vehicle as if the gateway
    had."""

    def __init__(self, gateway_port: int) -> None:
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.port = int(self.front.getsockname()[1])
        self.gateway = ("127.0.0.1", gateway_port)
        self.vehicle: Any = None
        self.to_vehicle: list[bytes] = []
        self.to_gateway: list[bytes] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.05)
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    continue
                with self._lock:
                    if sock is self.front:
                        self.vehicle = addr
                        self.to_gateway.append(data)
                        self.back.sendto(data, self.gateway)
                    elif self.vehicle is not None:
                        self.to_vehicle.append(data)
                        self.front.sendto(data, self.vehicle)

    def inject(self, data: bytes) -> None:
        self.front.sendto(data, self.vehicle)

    def sent_to_vehicle(self) -> list[bytes]:
        with self._lock:
            return list(self.to_vehicle)

    def sent_to_gateway(self) -> list[bytes]:
        with self._lock:
            return list(self.to_gateway)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.front.close()
        self.back.close()


class SignedRig:
    """A simulated vehicle (built as ``arena sim vehicle`` builds it), its gateway in a thread, a vision
    feeder and state/event collection, on one bus."""

    def __init__(
        self, cfg: ArenaConfig, sim_cfg: ArenaConfig, bus: Bus, options: GatewayOptions | None
    ) -> None:
        self.cfg, self.bus = cfg, bus
        self.ap: SimAutopilot = build_autopilots(sim_cfg, SimClock(SPEED))[0]
        self.loop = AutopilotLoop([self.ap]).start()
        self.states: list[wire.State] = []
        self.events: list[wire.Event] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._vision = bus.stream_publisher(keys.vision("d1"), wire.Pose)
        self._state_sub = bus.subscribe(keys.state("d1"), capacity=64, ring=True)
        self._event_sub = bus.subscribe(keys.events("d1"), capacity=10_000, ring=False)
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._feed, self._collect)]
        self.gw: Gateway | None = None
        self._gw_stop = threading.Event()
        ready = threading.Event()

        def run() -> None:
            with (
                running("gateway", cfg, vehicle="d1", stop=self._gw_stop) as svc,
                Gateway(cfg, "d1", svc.bus, options=options, stats=svc.stats, log=svc.log) as gw,
            ):
                self.gw = gw
                ready.set()
                gw.run(svc.stop)

        self._threads.append(threading.Thread(target=run, daemon=True))
        for t in self._threads:
            t.start()
        assert ready.wait(10.0), "the gateway did not start"

    def _feed(self) -> None:
        while not self._stop.wait(0.02):
            tp = self.ap.true_pose()
            self._vision.put(
                wire.Pose(
                    t=time.time_ns(), p=tp.position, q=tp.q, ok=True, v=tp.velocity, w=tp.rates, vok=True
                )
            )

    def _collect(self) -> None:
        while not self._stop.wait(0.01):
            for item in self._state_sub.channel.drain():
                if isinstance(item.payload, wire.State):
                    with self._lock:
                        self.states.append(item.payload)
            for item in self._event_sub.channel.drain():
                if isinstance(item.payload, wire.Event):
                    with self._lock:
                        self.events.append(item.payload)

    def cmd(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        return self.bus.request(keys.cmd("d1"), wire.Command(op=op, args=args, src="test", timeout=timeout))

    def ok(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        result = self.cmd(op, timeout, **args)
        assert result.result == "ACCEPTED", f"{op}: {result.result} {result.reason}"
        return result

    def wait_state(self, pred: Callable[[wire.State], bool], timeout: float, what: str) -> wire.State:
        def last() -> wire.State | None:
            with self._lock:
                s = self.states[-1] if self.states else None
            return s if s is not None and pred(s) else None

        state: wire.State = wait_for(last, timeout, what=what)
        return state

    def wait_event(self, pred: Callable[[wire.Event], bool], timeout: float, what: str) -> wire.Event:
        def find() -> wire.Event | None:
            with self._lock:
                return next((e for e in self.events if pred(e)), None)

        event: wire.Event = wait_for(find, timeout, what=what)
        return event

    def event_text(self) -> str:
        with self._lock:
            return "\n".join(f"{e.kind} {e.text} {e.data}" for e in self.events)

    def close(self) -> None:
        self._gw_stop.set()
        self._stop.set()
        for t in self._threads:
            t.join(10.0)
        self.loop.stop()
        self.ap.close()


@pytest.fixture
def rigs() -> Iterator[list[SignedRig]]:
    made: list[SignedRig] = []
    yield made
    for rig in made:
        rig.close()


def test_signed_flight_origin_and_a_replayed_command(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    rigs: list[SignedRig],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG)
    key = generate_key_file(tmp_path / "d1.key")
    cfg = signed_config(tmp_path, router_endpoint, "d1.key")
    cfg = cfg.replace(vehicles={"d1": cfg.vehicle("d1").replace(origin=ORIGIN)})  # the config's origin
    tap = Tap(int(cfg.vehicle("d1").mavlink.rsplit(":", 1)[1]))
    try:
        rig = SignedRig(
            cfg,
            with_sim_link(cfg, f"udpout:127.0.0.1:{tap.port}"),
            bus_factory(),
            None,
        )
        rigs.append(rig)
        ap, gw = rig.ap, rig.gw
        assert gw is not None and gw.signing is not None and ap.signing is not None
        assert ap.signing.key == key == gw.signing.key  # both read the config's key file

        # The link comes up, the vehicle fuses vision and takes the origin: everything signed.
        wait_for(lambda: rig.cmd("ping", timeout=1.0).ok, 15.0, what="the gateway answers")
        rig.wait_state(lambda s: s.link and s.vis_fused and s.setup_ok, 15.0, "link up, vision fused, set up")
        rig.wait_event(lambda e: e.kind == "setup" and "EKF origin set" in e.text, 10.0, "origin confirmed")
        assert ap.gps_origin == pytest.approx(ORIGIN, abs=1e-6)
        assert rig.ok("param_get", name="EKF2_EV_CTRL").value["value"] == 15

        rig.ok("arm")
        rig.ok("takeoff", height=0.6)
        rig.wait_state(
            lambda s: s.landed == "in_air" and s.p is not None and abs(-s.p[2] - 0.6) < 0.1,
            15.0,
            "hover at 0.6 m",
        )
        rig.ok("land")
        rig.wait_state(lambda s: s.landed == "on_ground", 15.0, "landed")
        rig.ok("disarm")
        wait_for(lambda: not ap.armed, 5.0, what="disarmed")
        assert not ap.refused and not gw.signing.rejected, (ap.refused, gw.signing.rejected)
        assert gw.signing.accepted > 100 and ap.signing.accepted > 100

        # Every datagram both ways carried signed frames only, and pymavlink's own check accepts the
        # gateway's (increasing timestamps per stream, the right key).
        to_vehicle, to_gateway = frames_of(tap.sent_to_vehicle()), frames_of(tap.sent_to_gateway())
        assert len(to_vehicle) > 100 and len(to_gateway) > 100
        assert all(f.raw[2] & 0x01 for f in to_vehicle + to_gateway)
        checker = mavlink2.MAVLink(None)
        checker.signing.secret_key = key.secret
        decoded = [checker.decode(bytearray(f.raw)) for f in to_vehicle]
        assert checker.signing.goodsig_count == len(to_vehicle) and checker.signing.badsig_count == 0

        # SET_GPS_GLOBAL_ORIGIN went to the vehicle's system id, never 0.
        origins = [m for m in decoded if m.get_type() == "SET_GPS_GLOBAL_ORIGIN"]
        assert origins and all(m.target_system == 1 for m in origins)
        assert (origins[0].latitude, origins[0].longitude, origins[0].altitude) == (
            473977420,
            85455940,
            488000,
        )

        # A captured arm command replayed later is refused: the vehicle stays disarmed and says so.
        arm = next(
            f.raw
            for f, m in zip(to_vehicle, decoded, strict=True)
            if m.get_type() == "COMMAND_LONG" and m.command == 400 and m.param1 == 1.0
        )
        tap.inject(arm)
        wait_for(lambda: ap.refused["replayed COMMAND_LONG"] >= 1, 5.0, what="the replay refused")
        rig.wait_event(
            lambda e: "Signing: refused replayed COMMAND_L" in e.text, 5.0, "the vehicle's STATUSTEXT"
        )
        time.sleep(0.3)
        assert not ap.armed and rig.states[-1].armed is False

        # After a reboot the vehicle lost its origin; the gateway gives it again.
        n_origin, n_set = len(origins), ap.origin_sets
        rig.ok("reboot")
        rig.wait_event(lambda e: "rebooted" in e.text, 10.0, "reboot noticed")
        wait_for(lambda: ap.origin_sets > n_set, 10.0, what="origin given again after the reboot")
        assert ap.gps_origin == pytest.approx(ORIGIN, abs=1e-6)
        again = [f for f in frames_of(tap.sent_to_vehicle()) if f.msgid == 48]
        assert len(again) > n_origin
        rig.wait_state(lambda s: s.link and s.vis_fused, 10.0, "fused again after the reboot")
        assert set(ap.refused) <= {"replayed COMMAND_LONG"}

        # The key never reached a log line or an event.
        assert_secret_free(caplog.text + rig.event_text(), key)
        assert key.fingerprint in caplog.text
    finally:
        tap.close()


def test_a_script_without_the_key_cannot_command_the_vehicle(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    key = generate_key_file(tmp_path / "d1.key")
    wrong = generate_key_file(tmp_path / "other.key")
    port = free_port(socket.SOCK_DGRAM)
    # A plain pymavlink script, as QGroundControl would be (255/190), where the vehicle sends.
    script = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{port}", source_system=255, source_component=190, dialect="common"
    )
    ap = SimAutopilot(
        f"udpout:127.0.0.1:{port}", 1, clock=SimClock(SPEED), params=ARENA_PARAMS, signing_key=key
    )
    loop = AutopilotLoop([ap]).start()
    try:
        hb = script.recv_match(type="HEARTBEAT", blocking=True, timeout=10.0)
        assert hb is not None and hb.get_srcSystem() == 1 and hb.get_msgbuf()[2] & 0x01  # signed output
        ev_ctrl = ap.param("EKF2_EV_CTRL")

        def send_all() -> None:
            script.mav.command_long_send(1, 1, 400, 0, 1, FORCE, 0, 0, 0, 0, 0)  # force arm, right target
            script.mav.param_set_send(1, 1, b"EKF2_EV_CTRL", 0.0, px4.MAV_PARAM_TYPE_INT32)
            script.mav.set_position_target_local_ned_send(
                0, 1, 1, 1, 2552, 1.0, 1.0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0
            )
            script.mav.odometry_send(
                int(time.time() * 1e6),
                20,
                12,
                3.0,
                0.0,
                0.0,
                [1, 0, 0, 0],
                *([float("nan")] * 6),
                [float("nan")] * 21,
                [float("nan")] * 21,
                0,
                px4.MAV_ESTIMATOR_TYPE_VISION,
                100,
            )

        # Unsigned: refused, whatever the message.
        send_all()
        names = ("COMMAND_LONG", "PARAM_SET", "SET_POSITION_TARGET_LOCAL_NED", "ODOMETRY")
        wait_for(lambda: all(ap.refused[f"unsigned {n}"] >= 1 for n in names), 5.0, what="unsigned refused")
        # The vehicle says why (PX4 sends STATUSTEXT only to links where it hears a ground station: this
        # script is none, so the text is read from the vehicle's own record).
        said = wait_for(
            lambda: next((t for _, t in list(ap.statustexts) if "Signing" in t), None), 5.0, what="the text"
        )
        assert said.startswith("Signing: refused unsigned")
        # Signed with another key: refused too.
        setup_signing(script, wrong)
        send_all()
        wait_for(
            lambda: all(ap.refused[f"bad signature {n}"] >= 1 for n in names), 5.0, what="wrong key refused"
        )
        time.sleep(0.3)
        assert not ap.armed and ap.param("EKF2_EV_CTRL") == ev_ctrl and ap.last_vision_sample_us < 0
        assert ap.messages_in == 0  # nothing reached a handler

        # With the key the same script is obeyed: the refusals above were the signing's.
        setup_signing(script, key)
        arm = script.mav.command_long_encode(1, 1, 400, 0, 1, FORCE, 0, 0, 0, 0, 0)
        captured = bytes(arm.pack(script.mav))
        script.write(captured)
        ack = script.recv_match(type="COMMAND_ACK", blocking=True, timeout=5.0)
        assert ack is not None and ack.command == 400 and ack.result == px4.MAV_RESULT_ACCEPTED
        wait_for(lambda: ap.armed, 5.0, what="armed by the signed command")
        script.mav.command_long_send(1, 1, 400, 0, 0, FORCE, 0, 0, 0, 0, 0)
        wait_for(lambda: not ap.armed, 5.0, what="disarmed")
        # The captured signed arm command, replayed: refused.
        script.write(captured)
        wait_for(lambda: ap.refused["replayed COMMAND_LONG"] >= 1, 5.0, what="replay refused")
        time.sleep(0.3)
        assert not ap.armed
        assert_secret_free(caplog.text, key, wrong)
    finally:
        loop.stop()
        ap.close()
        script.close()


def test_a_gateway_with_the_wrong_key_drops_everything(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    rigs: list[SignedRig],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG)
    gateway_key = generate_key_file(tmp_path / "d1.key")
    vehicle_key_file = tmp_path / "vehicle.key"
    vehicle_secret = generate_key_file(vehicle_key_file)
    cfg = signed_config(tmp_path, router_endpoint, "d1.key")
    sim_cfg = signed_config(tmp_path, router_endpoint, str(vehicle_key_file))
    sim_cfg = with_sim_link(sim_cfg, cfg.vehicle("d1").sim_mavlink())
    rig = SignedRig(cfg, sim_cfg, bus_factory(), None)
    rigs.append(rig)
    gw = rig.gw
    assert gw is not None and gw.signing is not None
    event = rig.wait_event(
        lambda e: e.kind == "link" and e.text.startswith("signing:"),
        10.0,
        "the gateway reports the refused frames",
    )
    assert "dropped" in event.text and "bad signature" in event.text and gateway_key.fingerprint in event.text
    assert event.sev == 4 and event.data["dropped"] >= 1 and event.data["signing"]["bad signature"] >= 1
    assert gw.signing.rejected["bad signature"] >= 1 and gw.signing.accepted == 0
    assert gw.stats.rejected.get("mavlink: bad signature", 0) >= 1
    result = rig.cmd("arm")
    assert result.result == "REFUSED" and "no link" in result.reason
    s = rig.wait_state(lambda s: True, 5.0, "a state")
    assert not s.link and not rig.ap.armed
    assert_secret_free(caplog.text + rig.event_text(), gateway_key, vehicle_secret)


def test_gateway_service_process_signs_and_never_logs_the_key(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], processes: Callable[..., Proc]
) -> None:
    key = generate_key_file(tmp_path / "d1.key")
    cfg = signed_config(tmp_path, router_endpoint, "d1.key")
    ap = build_autopilots(cfg, SimClock(SPEED))[0]
    loop = AutopilotLoop([ap]).start()
    bus = bus_factory()
    argv = service_argv("mavlink_gateway", cfg.path, "--vehicle", "d1", "--log-level", "DEBUG", host=None)
    proc = processes("gateway", [*argv, "--origin", "-33.86,151.21,5"])
    try:

        def request(op: str) -> wire.CommandResult:
            return bus.request(keys.cmd("d1"), wire.Command(op=op, src="test", timeout=5.0))

        wait_for(lambda: request("ping").ok, 60.0, what="the gateway process answers")
        wait_for(lambda: request("check").ok, 30.0, what="parameters read over the signed link")
        wait_for(lambda: ap.gps_origin is not None, 10.0, what="origin")
        assert ap.gps_origin == pytest.approx((-33.86, 151.21, 5.0), abs=1e-6)
        assert ap.signing is not None and ap.signing.accepted > 10 and not ap.refused
    finally:
        proc.stop(10.0, signal.SIGTERM)
        loop.stop()
        ap.close()
    text = proc.output()
    assert f"MAVLink 2 signing with key {key.fingerprint}" in text
    assert_secret_free(text, key)

    # A broken key file stops the service at once with a clear error (and no key material).
    (tmp_path / "d1.key").write_text(key.secret.hex()[:50])
    failed = subprocess.run(
        [sys.executable, "-m", "services.mavlink_gateway", "--vehicle", "d1", "-c", cfg.path],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert failed.returncode == 2
    assert "signing_key_file" in failed.stderr and "expected 64 hex digits" in failed.stderr
    assert key.secret.hex()[:50] not in failed.stderr + failed.stdout
