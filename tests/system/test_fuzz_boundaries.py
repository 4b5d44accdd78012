"""Bad input at every boundary of the arena, through the real services.

- **The bus**: malformed payloads of every type on every key (wrong types, missing fields, NaN and
  infinity, values out of range, truncated msgpack, random bytes, a wrong schema version or an unknown
  schema in the encoding) reach the real services (Motive emulator, ingest, transform, downsampler,
  gateway, recorder, each its ``main`` in a thread of this process) while d1 is tracked; each must be
  refused with the service's own error and counted in its stats, no service (or thread of one) may die,
  and nothing they carry may reach the simulated autopilot (every ODOMETRY, SET_POSITION_TARGET and
  COMMAND_LONG it receives is checked).  Commands that do not decode are answered ERROR.
- **Valid payloads that are still dangerous** (another type on a key, numbers MAVLink cannot carry, a
  time stamp from the future) against a fresh gateway each.
- **Unsafe commands**: setpoints and gotos outside the rules, arming with stale mocap, offboard without
  a stream: refused with a reason (CommandResult REFUSED + an Event).
- **MAVLink from the vehicle's side**: garbage, truncated frames, bad CRCs, other system ids.
- **NatNet into the ingest's socket**: real Motive captures, mutated.
- **Config files** (random TOML mutations: only ConfigError) and **command-line arguments**.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import random
import socket
import struct
import threading
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

os.environ.setdefault("MAVLINK20", "1")

import services.downsampler
import services.frame_transform
import services.mavlink_gateway
import services.mocap_ingest
import services.recorder
import services.sim_mocap
from arena_common.bus.session import Bus
from arena_common.cli import app as arena_app
from arena_common.client.vehicle import Arena
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.core.wire import Spec
from arena_common.mavlink.link import mavlink2
from arena_common.mocap import natnet
from arena_common.runtime.options import parse_config, read_config
from arena_common.sim.natnet_server import TickClock, load_recording
from tests.faultlib import (
    ServiceThread,
    TapAutopilot,
    ThreadDeaths,
    Watch,
    World,
    peer_bus,
    router,
    write_arena_config,
)
from tests.helpers import REPO, free_port, wait_for

pytestmark = pytest.mark.system

CAPTURE = REPO / "tests" / "data" / "natnet" / "motive-2.1-natnet-3.0" / "traffic.pcapng"
FUZZ = settings(deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))


def fuzz(examples: int) -> settings:
    """Deterministic, bounded hypothesis settings: ``examples`` examples, no deadline, no database."""
    return settings(FUZZ, max_examples=examples)


WATCHED = ("ODOMETRY", "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG")


@pytest.fixture(scope="module")
def deaths() -> Iterator[ThreadDeaths]:
    d = ThreadDeaths().install()
    try:
        yield d
    finally:
        d.uninstall()


def rejected(watch: Watch, service: str, reasons: tuple[str, ...] = ()) -> int:
    """The service's rejected inputs so far (only ``reasons`` when given), from its latest stats."""
    st_ = watch.stat(service)
    if st_ is None:
        return 0
    return sum(int(v) for k, v in st_.rejected.items() if not reasons or k in reasons)


def dropped(watch: Watch, service: str) -> int:
    """Samples the service's input queue could not hold, from its latest stats."""
    st_ = watch.stat(service)
    return int(st_.counts.get("dropped", 0)) if st_ is not None else 0


def fresh_stats(watch: Watch, services: list[str], timeout: float = 10.0) -> None:
    """Wait until every service published stats after now."""
    t0 = time.monotonic()
    wait_for(
        lambda: all(watch.fresh_stat(s, t0) is not None for s in services),
        timeout,
        0.05,
        what=f"fresh stats of {services}",
    )


def put(bus: Bus, key: str, raw: bytes, encoding: str = "") -> None:
    """Publish bytes as they are, reliably, with ``encoding`` (none when empty)."""
    kw: dict[str, Any] = {"congestion_control": zenoh.CongestionControl.BLOCK}
    if encoding:
        kw["encoding"] = zenoh.Encoding(encoding)
    bus.session.put(key, raw, **kw)


def query(bus: Bus, key: str, raw: bytes, encoding: str = "", timeout: float = 5.0) -> wire.CommandResult:
    """Send a query whose payload is ``raw`` and decode the answer."""
    kw: dict[str, Any] = {"payload": raw, "timeout": timeout}
    if encoding:
        kw["encoding"] = zenoh.Encoding(encoding)
    for reply in bus.session.get(key, **kw):
        if reply.ok is not None:
            return wire.CommandResult.decode(reply.ok.payload.to_bytes(), key)
        return wire.CommandResult(False, "ERROR", f"zenoh error reply: {reply.err}")
    return wire.CommandResult(False, "TIMEOUT", "no reply")


# -- payloads that must not decode ---------------------------------------------------------------------------

TYPES_BY_KEY: dict[str, type[wire.Payload]] = {
    keys.mocap("d1"): wire.MocapPose,
    keys.FRAMES: wire.MocapFrame,
    keys.pose("d1"): wire.Pose,
    keys.vision("d1"): wire.Pose,
    keys.setpoint("d1"): wire.Setpoint,
    keys.truth("d1"): wire.Pose,
    keys.state("d1"): wire.State,
    keys.events("d1"): wire.Event,
    keys.telemetry("d1", "HEARTBEAT"): wire.Telemetry,
    keys.ESTOP: wire.Estop,
    keys.stats("fuzz", "nobody"): wire.Stats,
    keys.body("stranger"): wire.MocapPose,
}


def valid_example(cls: type[wire.Payload]) -> wire.Payload:
    """A valid payload of ``cls`` to mutate."""
    now = wire.now_ns()
    examples: dict[type[wire.Payload], wire.Payload] = {
        wire.MocapPose: wire.MocapPose(t=now, fn=1, id=1, p=(0.1, 0.2, 0.3), q=(1.0, 0.0, 0.0, 0.0), ok=True),
        wire.MocapFrame: wire.MocapFrame(
            t=now, fn=1, b=(wire.MocapBody("d1", 1, (0.1, 0.2, 0.3), (1.0, 0.0, 0.0, 0.0), True),)
        ),
        wire.Pose: wire.Pose(t=now, p=(0.1, 0.2, -0.3), q=(1.0, 0.0, 0.0, 0.0), ok=True),
        wire.Setpoint: wire.Setpoint(t=now, p=(0.0, 0.0, -1.0)),
        wire.State: wire.State(t=now, q=(1.0, 0.0, 0.0, 0.0)),
        wire.Event: wire.Event(t=now, kind="info", text="fuzz"),
        wire.Telemetry: wire.Telemetry(t=now, msg="HEARTBEAT"),
        wire.Estop: wire.Estop(t=now),
        wire.Stats: wire.Stats(t=now, service="nobody", host="fuzz"),
        wire.Command: wire.Command(op="ping"),
    }
    return examples[cls]


def wrong_values(spec: Spec) -> list[Any]:
    """Values a field of this spec must refuse (None only where nil is not allowed)."""
    out: list[Any] = []
    if not spec.optional and not spec.nan_ok:
        out.append(None)
    if spec.kind == "int":
        out += ["7", 1.5, [1], {"a": 1}, True, b"\x00", 2**64 - 1]
        if spec.lo is not None:
            out.append(int(spec.lo) - 1)
        if spec.hi is not None:
            out.append(int(spec.hi) + 1)
    elif spec.kind == "float":
        out += ["1.0", [1.0], True, {"a": 1}, math.inf, -math.inf]
        if not spec.nan_ok:
            out.append(math.nan)
        if spec.lo is not None:
            out.append(float(spec.lo) - 1.0)
        if spec.hi is not None:
            out.append(float(spec.hi) + 1.0)
    elif spec.kind == "bool":
        out += [1, "true", 0.0, [True]]
    elif spec.kind == "str":
        out += [5, ["x"], b"bytes", "x" * 5000]
        if spec.choices:
            out.append("bogus")
    elif spec.kind == "vec3":
        out += [[1.0, 2.0], [1.0, 2.0, 3.0, 4.0], "abc", 7, [1.0, "x", 2.0], [math.nan, 0.0, 0.0]]
        out += [[math.inf, 0.0, 0.0], {"a": 1}, [True, 0.0, 0.0]]
    elif spec.kind == "quat":
        out += [[1.0, 0.0, 0.0], [math.nan, 0.0, 0.0, 0.0], "q", 5, [-math.inf, 0.0, 0.0, 1.0]]
    elif spec.kind == "map":
        out += [[1, 2], "x", 5]
    elif spec.kind == "strs":
        out += [[1, 2], "x", 5, ["a"] * 300]
    elif spec.kind == "items":
        body = {"v": "d1", "id": 1, "p": [0.0, 0.0, 0.0], "q": [1.0, 0.0, 0.0, 0.0], "ok": True}
        out += [5, "x", [5], [{**body, "p": [0.0, "x", 0.0]}], [{**body, "v": "sys"}], [{**body, "ok": 1}]]
        out += [
            [{**body, "q": [2.0, 0.0, 0.0, 0.0]}],
            [body] * 300,
            [{k: v for k, v in body.items() if k != "id"}],
        ]
    return out


def cross_field_breaks(cls: type[wire.Payload], m: dict[str, Any]) -> list[dict[str, Any]]:
    """Maps whose fields are each fine but break a rule between fields."""
    if cls is wire.Setpoint:
        return [{"t": m["t"]}, {**m, "yaw": 0.1, "yr": 0.1}]
    if cls in (wire.Pose, wire.MocapPose, wire.State):
        return [{**m, "q": [2.0, 0.0, 0.0, 0.0]}]
    return []


MUTATIONS = ("wrong_value", "missing", "cross", "truncated", "random", "not_a_map", "version", "schema")


@dataclass(frozen=True)
class Bad:
    key: str
    raw: bytes
    encoding: str
    how: str


def decodes(key: str, raw: bytes, encoding: str) -> bool:
    try:
        wire.decode_any(key, raw, encoding)
    except wire.PayloadError:
        return False
    return True


@st.composite
def bad_samples(draw: st.DrawFn, key_choices: tuple[str, ...] = tuple(sorted(TYPES_BY_KEY))) -> Bad:
    """A sample that must not decode on its key, built so by construction."""
    key = draw(st.sampled_from(key_choices))
    cls = TYPES_BY_KEY.get(key, wire.Command)  # queries carry a Command
    m = valid_example(cls).to_dict()
    encoding = draw(st.sampled_from((cls.encoding(), "")))
    how = draw(st.sampled_from(MUTATIONS))
    specs = [spec for _, spec in cls._specs]
    if how == "wrong_value":
        spec = draw(st.sampled_from(specs))
        m[spec.wire] = draw(st.sampled_from(wrong_values(spec)))
        raw = msgpack.packb(m, use_bin_type=True)
    elif how == "missing":
        required = [
            spec.wire for name, spec in cls._specs if wire.default_of(cls, name) is dataclasses.MISSING
        ]
        del m[draw(st.sampled_from(required))]
        raw = msgpack.packb(m, use_bin_type=True)
    elif how == "cross" and cross_field_breaks(cls, m):
        raw = msgpack.packb(draw(st.sampled_from(cross_field_breaks(cls, m))), use_bin_type=True)
    elif how == "truncated":
        full = msgpack.packb(m, use_bin_type=True)
        raw = full[: draw(st.integers(0, len(full) - 1))]
    elif how == "not_a_map":
        raw = msgpack.packb(draw(st.sampled_from([1, "pose", [1.0, 2.0, 3.0], None, 2.5, True, b"\x01"])))
    elif how == "version":
        raw = msgpack.packb(m, use_bin_type=True)
        encoding = (
            f"{wire.ENCODING_PREFIX}arena.{cls.SCHEMA}/{draw(st.sampled_from(['0', '2', '99', 'x', '']))}"
        )
    elif how == "schema":
        raw = msgpack.packb(m, use_bin_type=True)
        encoding = f"{wire.ENCODING_PREFIX}arena.{draw(st.sampled_from(['Bogus', 'pose', 'Pose2', '']))}/1"
    else:
        how = "random"
        raw = draw(st.binary(max_size=48))
        if decodes(key, raw, encoding):  # astronomically rare: random bytes that make a valid payload
            raw = b"\xc1"  # the one byte msgpack never uses
    return Bad(key, raw, encoding, how)


# -- the pipeline --------------------------------------------------------------------------------------------


@dataclass
class Pipeline:
    cfg: ArenaConfig
    bus: Bus
    world: World
    services: dict[str, ServiceThread]
    watch: Watch
    arena: Arena
    deaths: ThreadDeaths

    @property
    def ap(self) -> TapAutopilot:
        return self.world.aps["d1"]

    def alive_services(self) -> set[str]:
        return {k.rsplit("/", 1)[1] for k in self.bus.alive("arena/sys/alive/test/**")}


SERVICE_IDS = ["sim-motive", "mocap", "transform", "downsampler.d1", "gateway.d1", "recorder"]


@pytest.fixture(scope="module")
def pipe(tmp_path_factory: pytest.TempPathFactory, deaths: ThreadDeaths) -> Iterator[Pipeline]:
    tmp = tmp_path_factory.mktemp("fuzz")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    own_router = router(endpoint)  # the module's other tests have routers of their own
    path = write_arena_config(
        tmp,
        services=("mocap", "transform", "recorder"),
        mocap_rate=100.0,
        endpoint=endpoint,
        recorder=f'directory = "{tmp / "rec"}"\nflush_s = 1.0',
    )
    cfg = config_mod.load(path)
    bus = peer_bus(cfg)
    world = World(cfg, bus, truth_rate=100.0)
    svcs: dict[str, ServiceThread] = {}
    watch = Watch(bus)
    arena = Arena(cfg, bus=bus, name="fuzz")
    try:
        svcs["sim-motive"] = ServiceThread("sim-motive", services.sim_mocap.main, cfg, host="test")
        svcs["mocap"] = ServiceThread("mocap", services.mocap_ingest.main, cfg, host="test")
        svcs["transform"] = ServiceThread("transform", services.frame_transform.main, cfg, host="test")
        svcs["downsampler.d1"] = ServiceThread(
            "downsampler", services.downsampler.main, cfg, vehicle="d1", host="test"
        )
        svcs["gateway.d1"] = ServiceThread(
            "gateway", services.mavlink_gateway.main, cfg, vehicle="d1", host="test"
        )
        svcs["recorder"] = ServiceThread("recorder", services.recorder.main, cfg, host="test")
        wait_for(
            lambda: (s := watch.state("d1")) is not None and s.vis_fused and s.setup_ok,
            60.0,
            0.05,
            what="d1 tracked, fused and set up",
        )
        d1 = arena.vehicle("d1")  # a user program's view, subscribed before the fuzz
        wait_for(lambda: d1.state_age < 1.0, 10.0, what="the user program's view of d1")
        yield Pipeline(cfg, bus, world, svcs, watch, arena, deaths)
    finally:
        arena.close()
        for svc in reversed(list(svcs.values())):
            svc.stop()
        watch.close()
        world.close()
        bus.close()
        own_router.close()


def assert_healthy(pipe: Pipeline, deaths_before: int) -> None:
    """Every service runs, holds its presence, and the vision still reaches the autopilot."""
    assert not pipe.deaths.since(deaths_before), pipe.deaths.since(deaths_before)
    dead = [n for n, s in pipe.services.items() if not s.alive or s.error]
    assert not dead, {n: pipe.services[n].error for n in dead}
    # A liveliness query can come back empty on a loaded machine (its replies late): ask until every
    # token answers (bounded); a service that really died fails the checks above, or this one.
    wait_for(lambda: set(SERVICE_IDS) <= pipe.alive_services(), 10.0, 0.1, what=f"presence of {SERVICE_IDS}")
    t0 = time.monotonic()
    wait_for(lambda: len(pipe.ap.tap.times("ODOMETRY", after=t0)) >= 10, 5.0, what="vision still flowing")


def test_bad_payloads_on_every_key_are_refused_counted_and_never_reach_the_vehicle(pipe: Pipeline) -> None:
    ap = pipe.ap
    n_deaths = len(pipe.deaths.deaths)
    fresh_stats(pipe.watch, SERVICE_IDS)
    ds_dropped_before = dropped(pipe.watch, "downsampler.d1")
    before = {
        "transform": rejected(pipe.watch, "transform", ("bad_payload",)),
        "downsampler.d1": rejected(pipe.watch, "downsampler.d1", ("bad_payload",)),
        "vision": rejected(pipe.watch, "gateway.d1", ("vision: undecodable",)),
        "setpoint": rejected(pipe.watch, "gateway.d1", ("setpoint",)),
        "estop": rejected(pipe.watch, "gateway.d1", ("estop: undecodable",)),
        "recorder": rejected(pipe.watch, "recorder", ("undecodable",)),
        "sim-motive": rejected(pipe.watch, "sim-motive", ("truth",)),
    }
    counts = Counter({name: ap.tap.count(name) for name in WATCHED})
    sent: Counter[str] = Counter()
    hows: Counter[str] = Counter()
    t_start = time.monotonic()
    true_p = ap.true_pose().position

    @fuzz(500)
    @given(bad=bad_samples())
    def publish(bad: Bad) -> None:
        put(pipe.bus, bad.key, bad.raw, bad.encoding)
        sent[bad.key] += 1
        hows[bad.how] += 1
        time.sleep(0.002)  # the downsampler's 16-deep queue must not overflow with legitimate poses

    publish()
    want = {
        "transform": sent[keys.FRAMES],
        "downsampler.d1": sent[keys.pose("d1")],
        "estop": sent[keys.ESTOP],
        "recorder": sum(sent.values()),
        "sim-motive": sent[keys.truth("d1")],
    }
    now = {
        "transform": lambda: rejected(pipe.watch, "transform", ("bad_payload",)),
        "downsampler.d1": lambda: rejected(pipe.watch, "downsampler.d1", ("bad_payload",)),
        "estop": lambda: rejected(pipe.watch, "gateway.d1", ("estop: undecodable",)),
        "recorder": lambda: rejected(pipe.watch, "recorder", ("undecodable",)),
        "sim-motive": lambda: rejected(pipe.watch, "sim-motive", ("truth",)),
    }
    # On a loaded computer the downsampler's 16-deep queue may overflow: what it dropped (counted, with
    # legitimate poses) it could not refuse.
    slack = {"downsampler.d1": lambda: dropped(pipe.watch, "downsampler.d1") - ds_dropped_before}

    def counted() -> bool:
        return all(now[k]() - before[k] + slack.get(k, lambda: 0)() >= want[k] for k in want)

    wait_for(counted, 15.0, 0.1, what="every bad sample counted")
    time.sleep(1.2)  # one more stats period: nothing counted twice
    fresh_stats(pipe.watch, SERVICE_IDS)
    got = {k: now[k]() - before[k] for k in want}
    ds_slack = slack["downsampler.d1"]()
    assert want["downsampler.d1"] - ds_slack <= got.pop("downsampler.d1") <= want.pop("downsampler.d1")
    assert got == want, (got, want, dict(hows))
    # The gateway's vision and setpoint inputs keep only the latest samples (rings): what it saw, it refused.
    vision = rejected(pipe.watch, "gateway.d1", ("vision: undecodable",)) - before["vision"]
    setpoint = rejected(pipe.watch, "gateway.d1", ("setpoint",)) - before["setpoint"]
    assert 0 < vision <= sent[keys.vision("d1")], (vision, sent[keys.vision("d1")])
    assert 0 < setpoint <= sent[keys.setpoint("d1")], (setpoint, sent[keys.setpoint("d1")])
    assert any("setpoint refused: undecodable" in t for t in pipe.watch.event_texts("d1", t_start))
    # Nothing reached the autopilot but the true pose.
    assert not ap.tap.invalid, ap.tap.invalid[:5]
    assert ap.tap.count("SET_POSITION_TARGET_LOCAL_NED") == counts["SET_POSITION_TARGET_LOCAL_NED"]
    assert ap.tap.count("COMMAND_LONG") == counts["COMMAND_LONG"]
    far = [p for p in ap.tap.positions("ODOMETRY", t_start) if math.dist(p, true_p) > 0.02]
    assert not far, far[:5]
    assert_healthy(pipe, n_deaths)
    # A user program's view survived too.
    assert pipe.arena.vehicle("d1").state_age < 1.0
    print(f"\nbad samples: {sum(sent.values())} on {len(sent)} keys; mutations {dict(hows)}")


ODD_VALUES = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(2**63), 2**64 - 1),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=20),
        st.binary(max_size=20),
    ),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


def test_valid_payloads_with_unusual_contents_are_recorded(pipe: Pipeline) -> None:
    """Maps of anything (bytes, NaN, 64-bit integers, nesting) are valid Telemetry/Event payloads: the
    recorder keeps them, counts none as undecodable, and goes on."""
    n_deaths = len(pipe.deaths.deaths)
    fresh_stats(pipe.watch, ["recorder"])
    st0 = pipe.watch.stat("recorder")
    assert st0 is not None
    in0, undecodable0 = int(st0.counts.get("in", 0)), rejected(pipe.watch, "recorder", ("undecodable",))
    sent = 0

    @fuzz(100)
    @given(fields=st.dictionaries(st.text(max_size=8), ODD_VALUES, max_size=5), event=st.booleans())
    def publish(fields: dict[str, Any], event: bool) -> None:
        nonlocal sent
        payload: wire.Payload = (
            wire.Event(t=wire.now_ns(), kind="info", text="odd", data=fields)
            if event
            else wire.Telemetry(t=wire.now_ns(), msg="ODD", f=fields)
        )
        key = keys.events("d9") if event else keys.telemetry("d9", "ODD")
        put(pipe.bus, key, payload.encode(), payload.encoding())
        sent += 1
        time.sleep(0.002)

    publish()

    def counted() -> bool:
        s = pipe.watch.stat("recorder")
        return s is not None and int(s.counts.get("in", 0)) - in0 >= sent

    wait_for(counted, 10.0, 0.1, what="the recorder counting every odd payload")
    assert rejected(pipe.watch, "recorder", ("undecodable",)) == undecodable0
    assert_healthy(pipe, n_deaths)


@st.composite
def bad_commands(draw: st.DrawFn) -> tuple[bytes, str, str]:
    """(query payload, encoding, kind): a Command that does not decode, or one whose arguments are wrong."""
    kind = draw(st.sampled_from(("payload", "args")))
    if kind == "payload":
        # (The encoding of a query is not looked at: see test_command_with_a_wrong_schema_version.)
        bad = draw(
            bad_samples(key_choices=(keys.cmd("d1"),)).filter(lambda b: b.how not in ("version", "schema"))
        )
        return bad.raw, bad.encoding, kind
    bad_args: list[tuple[str, dict[str, Any]]] = [
        ("takeoff", {"height": "high"}),
        ("takeoff", {"height": math.nan}),
        ("takeoff", {"height": math.inf}),
        ("takeoff", {"height": [1.0]}),
        ("goto", {"p": [math.nan, 0.0, -1.0]}),
        ("goto", {"p": [0.0, 0.0]}),
        ("goto", {"p": "home"}),
        ("goto", {"p": [0.0, 0.0, -1.0], "yaw": "north"}),
        ("goto", {"p": [0.0, 0.0, -1.0], "tol": math.inf}),
        ("goto", {}),
        ("mode", {"mode": "BANANA"}),
        ("mode", {"mode": 6}),
        ("mode", {}),
        ("param_get", {"name": ""}),
        ("param_get", {"name": "X" * 17}),
        ("param_get", {"name": "É"}),
        ("param_set", {"name": "MPC_XY_P", "value": "fast"}),
        ("param_set", {"name": "MPC_XY_P", "value": math.nan}),
        ("param_set", {"name": "MPC_XY_P"}),
        ("start", {}),
        ("stop", {}),
    ]
    choice = draw(st.sampled_from(bad_args))
    op, args = choice
    cmd = wire.Command(op=op, args=args, src="fuzz", timeout=2.0)
    return cmd.encode(), wire.Command.encoding(), kind


def test_bad_commands_are_answered_error_and_never_reach_the_vehicle(pipe: Pipeline) -> None:
    ap = pipe.ap
    n_deaths = len(pipe.deaths.deaths)
    before = ap.tap.count("COMMAND_LONG")
    results: Counter[str] = Counter()

    @fuzz(120)
    @given(case=bad_commands())
    def ask(case: tuple[bytes, str, str]) -> None:
        raw, encoding, kind = case
        res = query(pipe.bus, keys.cmd("d1"), raw, encoding)
        assert (res.ok, res.result) == (False, "ERROR"), (kind, raw[:80], res)
        assert res.reason, res
        results[res.result] += 1

    ask()
    # The recorder's control answers the same way.
    res = query(pipe.bus, keys.rec_control("test"), b"\x93\x01\x02", wire.Command.encoding())
    assert (res.ok, res.result) == (False, "ERROR") and "msgpack" in res.reason + "map", res
    assert ap.tap.count("COMMAND_LONG") == before
    assert not ap.tap.invalid
    assert_healthy(pipe, n_deaths)


@pytest.mark.parametrize("schema", ["arena.Command/0", "arena.Command/2", "arena.Pose/1"])
def test_command_with_a_wrong_schema_version_is_refused(pipe: Pipeline, schema: str) -> None:
    raw = wire.Command(op="ping", src="fuzz", timeout=2.0).encode()
    res = query(pipe.bus, keys.cmd("d1"), raw, wire.ENCODING_PREFIX + schema)
    assert (res.ok, res.result) == (False, "ERROR"), res


# -- valid payloads that must still never reach (or break) a gateway -----------------------------------------


class GatewayRig:
    """d1's gateway service (its real ``main`` in a thread), the tapped simulated PX4 and a 50 Hz vision feed
    of the vehicle's true pose, as the pipeline would give it."""

    def __init__(self, tmp: Path, endpoint: str, speed: float = 1.0) -> None:
        path = write_arena_config(
            tmp, services=(), vehicle_services=("gateway",), endpoint=endpoint, speed=speed
        )
        self.cfg = config_mod.load(path)
        self.bus = peer_bus(self.cfg)
        self.world = World(self.cfg, self.bus, truth_rate=0)
        self.ap = self.world.aps["d1"]
        self.watch = Watch(self.bus)
        self.feeding = True
        self._vision = self.bus.stream_publisher(keys.vision("d1"), wire.Pose)
        self._stop = threading.Event()
        self._feeder = threading.Thread(target=self._feed, name="vision-feed", daemon=True)
        self._feeder.start()
        self.gateway = ServiceThread(
            "gateway", services.mavlink_gateway.main, self.cfg, vehicle="d1", host="test"
        )
        wait_for(
            lambda: (s := self.watch.state("d1")) is not None and s.vis_fused and s.setup_ok and s.link,
            30.0,
            0.05,
            what="d1's gateway ready",
        )

    def _feed(self) -> None:
        while not self._stop.wait(0.02):
            if self.feeding:
                tp = self.ap.true_pose()
                self._vision.put(
                    wire.Pose(t=wire.now_ns(), p=tp.position, q=tp.q, ok=True, v=tp.velocity, vok=True)
                )

    def cmd(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        return self.bus.request(keys.cmd("d1"), wire.Command(op=op, args=args, src="fuzz", timeout=timeout))

    def odometry_since(self, t0: float) -> int:
        return len(self.ap.tap.times("ODOMETRY", after=t0))

    def event(self, t0: float, text: str, timeout: float = 3.0) -> str:
        found: str = wait_for(
            lambda: next((e for e in self.watch.event_texts("d1", t0) if text in e), None),
            timeout,
            0.02,
            what=f"an event saying {text!r}",
        )
        return found

    def fly(self, height: float = 1.0) -> None:
        assert self.cmd("arm").ok
        assert self.cmd("takeoff", height=height).ok
        wait_for(
            lambda: (
                self.ap.mode_name == "AUTO.LOITER" and abs(self.ap.true_pose().position[2] + height) < 0.1
            ),
            20.0,
            0.05,
            what=f"hover at {height} m",
        )

    def close(self) -> None:
        self._stop.set()
        self._feeder.join(2.0)
        self.gateway.stop()
        self.watch.close()
        self.world.close()
        self.bus.close()


@pytest.fixture
def gw(tmp_path: Path, router_endpoint: str) -> Iterator[GatewayRig]:
    rig = GatewayRig(tmp_path, router_endpoint)
    try:
        yield rig
    finally:
        rig.close()


_PROBES = itertools.count(1)


def still_working(gw: GatewayRig, deaths: ThreadDeaths, n_deaths: int) -> None:
    """The gateway sends vision, answers, and judges setpoints: none of its threads died.

    The setpoint thread is probed with a setpoint of a fresh stream just outside the safe volume (a
    distinct distance each time, so no event is rate-limited away): it is refused, with its reason, and
    nothing reaches the vehicle — whether the vehicle stands or flies (a stream that does not hold the
    vehicle never flies, docs/safety.md §2.1)."""
    died = deaths.since(n_deaths)
    t0 = time.monotonic()
    time.sleep(0.5)
    assert gw.odometry_since(t0) >= 15, f"vision stopped; threads died: {died}"
    k = next(_PROBES)
    north = 10.0 + 0.01 * k
    sp = gw.bus.stream_publisher(keys.setpoint("d1"), wire.Setpoint)
    sp.put(wire.Setpoint(t=wire.now_ns(), p=(north, 0.0, -1.0), lease=0.2, stream=f"probe-{k}", seq=1))
    gw.event(t0, f"setpoint refused: position outside the safe volume: north {north:.2f} m outside")
    assert not died, died


def test_the_health_check_passes_on_a_healthy_gateway(gw: GatewayRig, deaths: ThreadDeaths) -> None:
    """The reference for the tests below: what they check does hold when nothing is wrong."""
    n = len(deaths.deaths)
    still_working(gw, deaths, n)
    t0 = time.monotonic()
    gw.bus.put(keys.ESTOP, wire.Estop(t=wire.now_ns(), reason="fuzz", src="fuzz"))
    gw.event(t0, "estop (fuzz)")


@pytest.mark.parametrize(
    ("key", "payload"),
    [
        (keys.vision("d1"), wire.State(t=1)),
        (keys.setpoint("d1"), wire.Estop(t=1)),
        (keys.ESTOP, wire.Setpoint(t=1, p=(0.0, 0.0, -1.0))),
    ],
    ids=["State-on-vision", "Estop-on-setpoint", "Setpoint-on-estop"],
)
def test_another_type_on_a_gateway_key_is_refused(
    gw: GatewayRig, deaths: ThreadDeaths, key: str, payload: wire.Payload
) -> None:
    n = len(deaths.deaths)
    put(gw.bus, key, payload.replace(t=wire.now_ns()).encode(), payload.encoding())
    time.sleep(0.3)
    still_working(gw, deaths, n)
    if key == keys.ESTOP:  # the estop must still work
        t0 = time.monotonic()
        gw.bus.put(keys.ESTOP, wire.Estop(t=wire.now_ns(), reason="fuzz", src="fuzz"))
        gw.event(t0, "estop (fuzz)")


def test_vision_pose_beyond_float32_is_refused(gw: GatewayRig, deaths: ThreadDeaths) -> None:
    n = len(deaths.deaths)
    gw.feeding = False
    time.sleep(0.1)
    gw.bus.put(
        keys.vision("d1"), wire.Pose(t=wire.now_ns(), p=(1e300, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True)
    )
    time.sleep(0.2)
    gw.feeding = True
    still_working(gw, deaths, n)
    assert not gw.ap.tap.invalid


def test_vision_pose_from_the_future_is_refused(gw: GatewayRig, deaths: ThreadDeaths) -> None:
    n = len(deaths.deaths)
    p = gw.ap.true_pose().position
    gw.bus.put(
        keys.vision("d1"), wire.Pose(t=wire.now_ns() + 3600 * 10**9, p=p, q=(1.0, 0.0, 0.0, 0.0), ok=True)
    )
    time.sleep(0.2)
    assert not gw.ap.tap.invalid, gw.ap.tap.invalid[:3]
    still_working(gw, deaths, n)


@pytest.mark.parametrize("field", ["yaw", "yr"])
def test_setpoint_yaw_beyond_float32_is_refused(gw: GatewayRig, deaths: ThreadDeaths, field: str) -> None:
    n = len(deaths.deaths)
    t0 = time.monotonic()
    sp = wire.Setpoint(t=wire.now_ns(), p=(0.0, 0.0, -1.0))
    gw.bus.put(keys.setpoint("d1"), sp.replace(**{field: 1e300}))
    gw.event(t0, "setpoint refused")
    still_working(gw, deaths, n)


# -- unsafe commands -----------------------------------------------------------------------------------------


def test_unsafe_setpoints_and_commands_are_refused_with_a_reason(
    gw: GatewayRig, deaths: ThreadDeaths
) -> None:
    n = len(deaths.deaths)
    ap = gw.ap
    sp_pub = gw.bus.stream_publisher(keys.setpoint("d1"), wire.Setpoint)
    before_sp = ap.tap.count("SET_POSITION_TARGET_LOCAL_NED")
    now = wire.now_ns
    t0 = time.monotonic()
    # Setpoints: NaN (does not decode), outside the safe volume, too fast: an Event each, nothing sent.
    put(gw.bus, keys.setpoint("d1"), msgpack.packb({"t": now(), "p": [math.nan, 0.0, -1.0]}), "")
    gw.event(t0, "setpoint refused: undecodable")
    for sp, text in (
        (wire.Setpoint(t=now(), p=(0.0, 0.0, 0.5)), "outside the safe volume: down 0.50"),
        (wire.Setpoint(t=now(), p=(0.0, 9.0, -1.0)), "outside the safe volume: east 9.00"),
        (wire.Setpoint(t=now(), v=(2.5, 0.0, 0.0)), "horizontal speed 2.50 m/s above max_speed"),
        (wire.Setpoint(t=now(), v=(0.0, 0.0, 3.0)), "vertical speed 3.00 m/s above max_climb"),
    ):
        sp_pub.put(sp)
        gw.event(t0, text)
    # Commands: REFUSED with the reason, and an Event of kind "command" saying so.
    refusals: dict[str, tuple[dict[str, Any], str]] = {
        "takeoff": (dict(height=5.0), "takeoff height 5.00 m outside"),
        "goto": (dict(p=[0.0, 0.0, -5.0]), "goal outside the safe volume"),
        "mode": (dict(mode="OFFBOARD"), "disarmed: take off first"),  # nothing flies from the floor
    }
    for op, (args, reason) in refusals.items():
        res = gw.cmd(op, **args)
        assert (res.ok, res.result) == (False, "REFUSED") and reason in res.reason, (op, res)
        gw.event(t0, f"{op} → REFUSED: {res.reason}")
    # Arming with the mocap stale: refused.
    gw.feeding = False
    time.sleep(0.4)
    res = gw.cmd("arm")
    assert (res.result, "vision stale") == ("REFUSED", res.reason[: len("vision stale")]), res
    gw.event(t0, "arm → REFUSED: vision stale")
    assert not ap.armed
    assert ap.tap.count("SET_POSITION_TARGET_LOCAL_NED") == before_sp
    assert not ap.tap.invalid
    assert not deaths.since(n)


def test_goto_with_a_yaw_beyond_float32_is_refused_in_flight(gw: GatewayRig, deaths: ThreadDeaths) -> None:
    n = len(deaths.deaths)
    gw.fly()
    res = gw.cmd("goto", p=[0.0, 0.0, -1.0], yaw=1e300)
    assert res.result in ("REFUSED", "ERROR"), res
    assert gw.cmd("hold").ok
    time.sleep(0.3)
    still_working(gw, deaths, n)


# -- MAVLink from the vehicle's side -------------------------------------------------------------------------


def real_frames(system_id: int) -> list[bytes]:
    """A few valid MAVLink 2 frames a PX4 with ``system_id`` sends."""
    mav = mavlink2.MAVLink(None, srcSystem=system_id, srcComponent=1)
    msgs = [
        mav.heartbeat_encode(2, 12, 0x1D, (4 << 16) | (3 << 24), 4),
        mav.sys_status_encode(0, 0, 0, 500, 12000, -1, 80, 0, 0, 0, 0, 0, 0),
        mav.local_position_ned_encode(0, 5.0, 5.0, -3.0, 0.0, 0.0, 0.0),
        mav.statustext_encode(2, b"Fuzz says hello"),
        mav.command_ack_encode(400, 0),
    ]
    return [bytes(m.pack(mav)) for m in msgs]


@st.composite
def bad_mavlink(draw: st.DrawFn) -> bytes:
    """Datagrams the gateway must ignore: garbage, truncated frames, bad CRC, another system's frames."""
    own, other = real_frames(1), real_frames(7)
    how = draw(st.sampled_from(("garbage", "truncated", "crc", "other_system", "mixed", "v1_garbage")))
    if how == "garbage":
        return draw(st.binary(min_size=1, max_size=300))
    if how == "truncated":
        frame = draw(st.sampled_from(own))
        return frame[: draw(st.integers(1, len(frame) - 1))]
    if how == "crc":
        flipped = bytearray(draw(st.sampled_from(own)))
        i = draw(st.integers(1, len(flipped) - 1))
        flipped[i] ^= draw(st.integers(1, 255))
        return bytes(flipped)
    if how == "other_system":
        return draw(st.sampled_from(other))
    if how == "v1_garbage":
        return b"\xfe" + draw(st.binary(min_size=0, max_size=40))
    parts = draw(
        st.lists(st.sampled_from([*other, b"\xfd\x09", b"\x00" * 7, b"\xfd" * 12]), min_size=2, max_size=6)
    )
    return b"".join(parts)


def test_mavlink_garbage_from_the_vehicle_side_is_ignored(gw: GatewayRig, deaths: ThreadDeaths) -> None:
    n = len(deaths.deaths)
    port = int(gw.cfg.vehicle("d1").mavlink.rsplit(":", 1)[1])
    state = gw.watch.state("d1")
    assert state is not None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))

        @fuzz(300)
        @given(data=bad_mavlink())
        def send(data: bytes) -> None:
            sock.sendto(data, ("127.0.0.1", port))
            time.sleep(0.001)

        send()
    time.sleep(0.3)
    s = gw.watch.state("d1")
    assert s is not None and s.sysid == 1 and s.link and s.mode == state.mode, s
    assert s.p is not None and math.dist(s.p, gw.ap.true_pose().position) < 0.2, (
        s.p
    )  # not the fuzzer's 5, 5, -3
    assert not any("Fuzz says" in t for t in gw.watch.event_texts("d1")), "another system's status text"
    assert gw.cmd("ping").ok
    still_working(gw, deaths, n)


def forged_frame(system_id: int, msgid: int = 0xABCDEF) -> bytes:
    """A MAVLink 2 frame with the vehicle's system id, a message id no dialect knows and a wrong CRC."""
    payload = b"\x01\x02\x03\x04"
    header = struct.pack("<BBBBBBB", 0xFD, len(payload), 0, 0, 0, system_id, 1)
    return header + msgid.to_bytes(3, "little") + payload + b"\x00\x00"


def test_a_corrupt_frame_with_the_vehicles_id_does_not_divert_the_link(gw: GatewayRig) -> None:
    port = int(gw.cfg.vehicle("d1").mavlink.rsplit(":", 1)[1])
    got = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:  # one corrupt frame a millisecond, as a noisy link might deliver
            sock.sendto(forged_frame(1), ("127.0.0.1", port))
            time.sleep(0.001)
            try:
                got += len(sock.recv(65535))
            except BlockingIOError:
                pass
    assert not got, f"the gateway sent {got} bytes to the forger"


# -- NatNet into the ingest's socket -------------------------------------------------------------------------


def mutate(data: Callable[[st.SearchStrategy[Any]], Any], frame: bytes) -> bytes:
    """One mutation of a NatNet datagram (bytes flipped, cut, grown, its header or some numbers changed)."""
    b = bytearray(frame)
    how = data(st.sampled_from(("flip", "cut", "grow", "header", "numbers", "splice")))
    if how == "flip":
        for _ in range(data(st.integers(1, 8))):
            i = data(st.integers(0, len(b) - 1))
            b[i] ^= data(st.integers(1, 255))
    elif how == "cut":
        b = b[: data(st.integers(0, len(b) - 1))]
    elif how == "grow":
        b += data(st.binary(min_size=1, max_size=64))
    elif how == "header":
        struct.pack_into("<HH", b, 0, data(st.sampled_from((7, 5, 1, 0, 99, 7))), data(st.integers(0, 65535)))
    elif how == "numbers":
        # Overwrite a float32 in the rigid-body area with NaN, infinity or an absurd value.
        i = data(st.integers(4, min(len(b) - 4, 200)))
        struct.pack_into("<f", b, i, data(st.sampled_from((math.nan, math.inf, -math.inf, 3e38, 0.0, 2.0))))
    else:
        i, j = sorted((data(st.integers(0, len(b))), data(st.integers(0, len(b)))))
        b = b[:i] + b[j:]
    return bytes(b)


class IngestRig:
    """The ingest service (its ``main`` in a thread) connected to a NatNet server that sends what it is told,
    serving the real capture's server info and model definitions; "RaceQuad" is d1's rigid body."""

    def __init__(self, tmp: Path, endpoint: str) -> None:
        self.rec = load_recording(CAPTURE)
        assert self.rec.version is not None and self.rec.models is not None
        path = write_arena_config(tmp, services=("mocap",), vehicle_services=(), endpoint=endpoint)
        path.write_text(path.read_text().replace('rigid_body = "d1"', 'rigid_body = "RaceQuad"'))
        self.cfg = cfg = config_mod.load(path)
        self.server = services.sim_mocap.build_server(
            cfg, self.rec.version, models=self.rec.models, clock=TickClock(self.rec.clock_frequency)
        ).start()
        self.server.clock.align(self.rec.frames[0].transmit or 0, time.perf_counter_ns(), 1.0)
        self.bus = peer_bus(cfg)
        self.watch = Watch(self.bus)
        self.sub = self.bus.subscribe("arena/*/mocap", capacity=100_000, ring=False, typed=False)
        self.bodies = self.bus.subscribe("arena/sys/bodies/*", capacity=100_000, ring=False, typed=False)
        self.ingest = ServiceThread("mocap", services.mocap_ingest.main, cfg, host="test")
        self.index = 0
        wait_for(lambda: self.server.clients or self.send_real(5), 20.0, 0.05, what="the ingest connected")
        wait_for(lambda: self.send_real(10) or len(self.sub.channel) > 0, 20.0, 0.01, what="RaceQuad as d1")

    def send_real(self, count: int) -> bool:
        """Send the capture's next ``count`` frames as they were recorded (4 ms apart)."""
        for _ in range(count):
            self.server.send_datagram(self.rec.raw[self.index % len(self.rec.raw)])
            self.index += 1
            time.sleep(0.004)
        return False

    def close(self) -> None:
        self.ingest.stop()
        self.server.close()
        self.watch.close()
        self.bus.close()


@pytest.fixture
def ingest(tmp_path: Path, router_endpoint: str) -> Iterator[IngestRig]:
    rig = IngestRig(tmp_path, router_endpoint)
    try:
        yield rig
    finally:
        rig.close()


def test_mutated_motive_captures_into_the_ingest_socket(ingest: IngestRig, deaths: ThreadDeaths) -> None:
    n = len(deaths.deaths)
    fresh_stats(ingest.watch, ["mocap"])
    before = rejected(ingest.watch, "mocap")
    rng = random.Random(3)
    raw = ingest.rec.raw

    @fuzz(400)
    @given(data=st.data())
    def send(data: st.DataObject) -> None:
        ingest.server.send_datagram(mutate(data.draw, raw[rng.randrange(len(raw))]))
        time.sleep(0.001)

    send()
    published = [*ingest.sub.channel.drain(), *ingest.bodies.channel.drain()]
    wait_for(
        lambda: ingest.send_real(10) or len(ingest.sub.channel) >= 10, 30.0, 0.01, what="poses after the fuzz"
    )
    fresh_stats(ingest.watch, ["mocap"])
    stats = ingest.watch.stat("mocap")
    assert stats is not None
    assert rejected(ingest.watch, "mocap") - before > 50, stats.rejected
    assert ingest.ingest.alive and ingest.ingest.error is None, ingest.ingest.error
    assert not deaths.since(n), deaths.since(n)
    wait_for(
        lambda: "arena/sys/alive/test/mocap" in ingest.bus.alive("arena/sys/alive/test/**"),
        10.0,
        0.1,
        what="the ingest's presence",
    )
    # No tracked pose with non-finite numbers, none with an implausible time, during the fuzz or after.
    published += [*ingest.sub.channel.drain(), *ingest.bodies.channel.drain()]
    invalid = 0
    for item in published:
        m = msgpack.unpackb(item.raw)
        try:
            wire.MocapPose.decode(item.raw, item.key)
        except wire.PayloadError:
            invalid += 1  # see test_ingest_publishes_only_valid_payloads
        if m["ok"]:
            assert all(math.isfinite(x) for x in (*m["p"], *m["q"])), m
            assert abs(math.sqrt(sum(c * c for c in m["q"])) - 1.0) < 2e-3, m
        assert m["tp"] - 11 * 10**9 <= m["t"] <= m["tp"] + 50_000_000, m
    print(
        f"\ningest: rejected {stats.rejected}; {len(published)} poses checked, {invalid} not valid payloads"
    )


@pytest.mark.parametrize("change", [{"frame_number": -5}, {"timestamp": math.nan}], ids=["fn<0", "mts=NaN"])
def test_ingest_publishes_only_valid_payloads(ingest: IngestRig, change: dict[str, Any]) -> None:
    ingest.sub.channel.drain()
    base = ingest.rec.frames[0]
    for k in range(20):
        changed = dataclasses.replace(base, **change)
        if "frame_number" in change:
            changed = dataclasses.replace(changed, frame_number=change["frame_number"] + k)
        ingest.server.send_datagram(natnet.encode_frame(changed, ingest.rec.version))  # type: ignore[arg-type]
        time.sleep(0.005)
    time.sleep(0.3)
    items = ingest.sub.channel.drain()
    assert items, "nothing published"
    bad = []
    for item in items:
        try:
            wire.MocapPose.decode(item.raw, item.key)
        except wire.PayloadError as exc:
            bad.append(str(exc))
    assert not bad, bad[:3]


# -- config files --------------------------------------------------------------------------------------------

CONFIGS = [REPO / "deploy" / "sim.toml", REPO / "deploy" / "lab.example.toml"]
TOML_VALUES = [
    '"x"',
    "1",
    "-1",
    "0",
    "1e400",
    "nan",
    "inf",
    "true",
    "[]",
    "[1, 2]",
    '["a", 3]',
    "{}",
    "1979-05-27",
    '""',
]


@st.composite
def mutated_toml(draw: st.DrawFn) -> str:
    text = CONFIGS[draw(st.integers(0, len(CONFIGS) - 1))].read_text()
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        how = draw(st.sampled_from(("value", "delete", "duplicate", "garble", "truncate", "rename", "table")))
        i = draw(st.integers(0, len(lines) - 1))
        line = lines[i]
        if how == "value" and "=" in line and not line.lstrip().startswith("#"):
            lines[i] = line.split("=", 1)[0] + "= " + draw(st.sampled_from(TOML_VALUES))
        elif how == "delete":
            del lines[i]
        elif how == "duplicate":
            lines.insert(i, line)
        elif how == "garble" and line:
            j = draw(st.integers(0, len(line)))
            lines[i] = line[:j] + draw(st.text(max_size=5)) + line[j:]
        elif how == "truncate":
            lines = lines[:i]
        elif how == "rename" and "=" in line and not line.lstrip().startswith("#"):
            lines[i] = (
                draw(st.sampled_from(("bogus", "size", "vehicles", "sys"))) + " =" + line.split("=", 1)[1]
            )
        elif how == "table":
            lines.insert(
                i,
                draw(
                    st.sampled_from(("[vehicles.sys]", "[hosts.x]", "[arena]", "[[arena]]", "[vehicles.d9]"))
                ),
            )
        if not lines:
            lines = [""]
    return "\n".join(lines) + "\n"


@fuzz(300)
@given(text=mutated_toml())
def test_config_mutations_raise_only_config_error(text: str) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "arena.toml"
        path.write_text(text)
        try:
            cfg = read_config(path)
        except ConfigError as exc:
            assert str(path) in str(exc), exc  # the message names the file
            return
        assert isinstance(cfg, ArenaConfig)


@st.composite
def mutated_tree(draw: st.DrawFn) -> dict[str, Any]:
    """A parsed config with one leaf replaced by a value of any TOML type (or removed, or added)."""
    data: dict[str, Any] = tomllib.loads(CONFIGS[draw(st.integers(0, 1))].read_text())
    node: Any = data
    while isinstance(node, dict) and node:
        k = draw(st.sampled_from(sorted(node)))
        if not isinstance(node[k], dict) or draw(st.booleans()):
            how = draw(st.sampled_from(("replace", "delete", "add")))
            value = draw(
                st.one_of(
                    st.integers(-(2**63), 2**63 - 1),
                    st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=20),
                    st.booleans(),
                    st.lists(st.one_of(st.integers(), st.text(max_size=4), st.floats()), max_size=4),
                    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
                )
            )
            if how == "replace":
                node[k] = value
            elif how == "delete":
                del node[k]
            else:
                node[draw(st.text(min_size=1, max_size=8))] = value
            break
        node = node[k]
    return data


@fuzz(300)
@given(data=mutated_tree())
def test_config_tree_mutations_raise_only_config_error(data: dict[str, Any]) -> None:
    try:
        cfg = parse_config(data, "fuzz.toml")
    except ConfigError as exc:
        assert str(exc).startswith("fuzz.toml: "), exc
        return
    assert isinstance(cfg, ArenaConfig)


# -- command-line arguments ----------------------------------------------------------------------------------


def run_cli(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(arena_app, list(args))
    text = result.output
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(
            f"arena {' '.join(args)}: {type(result.exception).__name__}: {result.exception}\n{text}"
        )
    assert "Traceback" not in text, text
    return result.exit_code, text


@fuzz(60)
@given(text=mutated_toml())
def test_cli_config_check_on_mutated_files(text: str) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "arena.toml"
        path.write_text(text)
        code, out = run_cli("config", "check", str(path))
        assert code in (0, 2), (code, out)
        assert ("ok" in out) if code == 0 else ("error:" in out), out


def test_cli_arguments_that_are_not_numbers_or_names(tmp_path: Path, router_endpoint: str) -> None:
    cfg = write_arena_config(tmp_path, services=(), endpoint=router_endpoint)  # a bus with no gateway
    assert run_cli("config", "check", str(tmp_path / "missing.toml"))[0] == 2
    assert run_cli("config", "check")[0] == 2
    assert run_cli("config", "check", str(tmp_path))[0] == 2  # a directory
    args: tuple[str, ...]
    for args in (
        ("goto", "d1", "--", "north", "0", "-1"),
        ("goto", "d1", "1", "2"),
        ("goto", "d1", "--timeout", "soon", "--", "1", "0", "-1"),
        ("takeoff", "d1", "high"),
        ("arm", "d1", "--timeout", "x"),
        ("goto", "d1", "--config", str(tmp_path / "missing.toml"), "--", "0", "0", "-1"),
        ("estop", "--bogus"),
    ):
        code, out = run_cli(*args)
        assert code == 2, (args, code, out)
    for args in (
        ("goto", "d1", "-c", str(cfg), "--timeout", "1", "--", "nan", "0", "-1"),
        ("goto", "d1", "-c", str(cfg), "--timeout", "1", "--", "1e308", "0", "-1"),
        ("takeoff", "d1", "-c", str(cfg), "--timeout", "1", "--", "-5"),
    ):
        code, out = run_cli(*args)
        assert code == 1 and "error" in out, (args, code, out)


def test_cli_goto_accepts_a_negative_down(tmp_path: Path, router_endpoint: str) -> None:
    cfg = write_arena_config(tmp_path, services=(), endpoint=router_endpoint)
    _, out = run_cli("goto", "d1", "1", "0", "-1", "-c", str(cfg), "--timeout", "1")
    assert "No such option" not in out, out


def test_cli_invalid_vehicle_name_is_a_clean_error(tmp_path: Path, router_endpoint: str) -> None:
    cfg = write_arena_config(tmp_path, services=(), endpoint=router_endpoint)
    code, out = run_cli("arm", "bad*name", "-c", str(cfg), "--timeout", "1")
    assert code in (1, 2) and "error" in out.lower(), (code, out)


def test_cli_unreachable_router_is_a_clean_error(tmp_path: Path) -> None:
    cfg = write_arena_config(tmp_path, services=())  # nobody listens on its router
    code, out = run_cli("arm", "d1", "-c", str(cfg), "--mode", "client", "--timeout", "1")
    assert code in (1, 2) and "error" in out.lower(), (code, out)
