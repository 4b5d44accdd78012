"""Motive emulator: the simulated vehicles' true poses streamed as NatNet, or a recorded session replayed.

Simulation: every configured vehicle (or those named with ``--vehicle``) is a rigid body named after its
``rigid_body`` (or the vehicle when that is an integer id), with id ``index + 1`` (or the integer). Its true
pose (``arena/<name>/truth``, arena NED/FRD) is converted to Motive's frame (``mocap.up_axis`` and the
inverse of the arena calibration) and streamed at ``sim.mocap_rate`` on a drift-free clock, with
``sim.noise_m`` noise, ``sim.dropout`` dropped frames (seed ``sim.seed``), Motive-like latency and
occlusions (``--occlude d1:2.0:0.5``: d1 hidden 2 s after start for 0.5 s). A body is defined and streamed
from the start, **untracked** (bit 0 clear, zero pose) until its first true pose, and again when its true
pose is older than :data:`~arena_common.sim.natnet_server.TRUTH_TIMEOUT` or says ``ok=False``: Motive does the
same for a defined rigid body the cameras do not see.

Replay (``--replay FILE``, pcap/pcapng or JSON lines): the frames are sent at their recorded timing
(``--speed``), byte for byte when the NatNet version is the recorded one, re-encoded otherwise; the
capture's SERVERINFO (application, clock) and MODELDEF are served (JSON lines hold neither: bodies are named
after the configured vehicle with the same id, else ``RigidBody<id>``, and the clock is estimated). The
service returns when the replay ends.

Clients: the server listens on ``mocap.server``:``mocap.command_port`` and streams to the group
``mocap.group``:``mocap.data_port`` (``mocap.multicast``), or by unicast as Motive serves each generation of
client: NatNet 4 SDK clients on the socket that sent CONNECT, from the data port; older clients
(libmotioncapture, NatNet SDK 3.x) on the data port of their address (:mod:`arena_common.sim.natnet_sessions`).

Stats (every second): ``frames`` sent, ``dropped``, ``occluded`` and ``untracked`` body-frames, ``late``
frames skipped because the loop fell behind, ``truth`` poses received, ``clients`` connected (a level).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError, InvalidName
from arena_common.core.services import by_module
from arena_common.geometry.frames import Calibration, FrameError, FrameTransform, UpAxis
from arena_common.mocap.capture import CaptureError
from arena_common.mocap.natnet import ModelDefs, NatNetError, RigidBodyDef, Version
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import Service, running
from arena_common.sim.natnet_scene import rigid_bodies
from arena_common.sim.natnet_server import (
    CAMERA_LATENCY,
    SOFTWARE_LATENCY,
    TRUTH_TIMEOUT,
    NatNetServer,
    Recording,
    SimScene,
    TickClock,
    iter_schedule,
    load_recording,
    sleep_until,
)

SERVICE = by_module("services.sim_mocap").name  # its one name: arena_common/core/services.py
VERSIONS = ("3.0", "3.1", "4.0", "4.1")
Occlusion = tuple[str, float, float]  # vehicle, start (s after start), duration (s)


def parse_occlusion(text: str) -> Occlusion:
    """Parse ``NAME:START:DURATION`` (seconds) into an occlusion; :class:`ConfigError` when malformed."""
    parts = text.split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        name, start, duration = parts[0], float(parts[1]), float(parts[2])
    except ValueError:
        raise ConfigError(
            f"occlusion {text!r}: expected VEHICLE:START_S:DURATION_S, e.g. d1:2.0:0.5"
        ) from None
    if not name or start < 0 or not duration > 0:
        raise ConfigError(f"occlusion {text!r}: needs a vehicle, a start >= 0 and a duration > 0")
    return (name, start, duration)


def build_server(cfg: ArenaConfig, version: Version, **kwargs: object) -> NatNetServer:
    """A :class:`NatNetServer` on the config's mocap addresses and ports."""
    m = cfg.mocap
    return NatNetServer(
        host=m.server,
        command_port=m.command_port,
        data_port=m.data_port,
        multicast=m.multicast,
        group=m.group,
        interface=m.interface,
        version=version,
        **kwargs,  # type: ignore[arg-type]
    )


def _parse_version(value: str | Version) -> Version:
    try:
        version = value if isinstance(value, Version) else Version.parse(str(value))
    except NatNetError:
        version = None
    if version is None or f"{version.major}.{version.minor}" not in VERSIONS:
        raise ConfigError(f"NatNet version must be one of {', '.join(VERSIONS)}, got {value!r}")
    return version


def _sync(svc: Service, name: str, value: int) -> None:
    """Make counter ``name`` read ``value`` (counters only add)."""
    svc.stats.count(name, value - svc.stats.counts.get(name, 0))


def _simulate(
    svc: Service, server: NatNetServer, scene: SimScene, rate: float, occlusions: Sequence[Occlusion]
) -> None:
    sub = svc.bus.subscribe("arena/*/truth", capacity=4096, ring=False)
    period = 1e9 / rate
    start = time.perf_counter_ns()
    for name, at, duration in occlusions:
        scene.occlude(name, duration, start + round(at * 1e9))
    wall_to_perf = time.perf_counter_ns() - time.time_ns()
    k, late, next_sync = 0, 0, 0.0
    while True:
        deadline = start + round(k * period)
        if not sleep_until(deadline, svc.stop):
            break
        now = time.perf_counter_ns()
        behind = int((now - deadline) // period)
        if behind >= 2:  # stalled: the frames of the past are lost, like a camera system's dropped frames
            k += behind
            late += behind
        for item in sub.channel.drain():
            if item.payload is None or not isinstance(item.payload, wire.Pose):
                svc.reject("truth", f"{item.key}: {item.error or 'not a Pose'}")
                continue
            try:
                vehicle = keys.parse(item.key).drone or ""
                pose = item.payload
                arrived = item.t_recv + wall_to_perf
                if scene.update(
                    vehicle,
                    pose.p,
                    pose.q,
                    pose.ok,
                    arrived,
                    stamp_ns=pose.t,
                    v_ned=pose.v if pose.vok else None,
                ):
                    svc.stats.count("truth")
            except (FrameError, InvalidName) as exc:
                svc.reject("truth", f"{item.key}: {exc}")
        number = k + 1
        frame = scene.frame(number, number / rate, time.perf_counter_ns(), server.clock)
        if frame is not None:
            server.send_frame(frame)
        k += 1
        if time.monotonic() >= next_sync:
            next_sync = time.monotonic() + 0.25
            wall_to_perf = time.perf_counter_ns() - time.time_ns()
            c = scene.counters
            for name, value in (
                ("frames", server.counters.frames),
                ("dropped", c.dropped),
                ("occluded", c.occluded),
                ("untracked", c.untracked),
                ("late", late),
                ("clients", len(server.clients)),
            ):
                _sync(svc, name, value)


def _replay(svc: Service, server: NatNetServer, rec: Recording, speed: float) -> None:
    start = time.perf_counter_ns()
    first = rec.frames[0]
    server.clock.align(first.transmit or 0, start, speed)
    for index, deadline in iter_schedule(rec.times, start, speed):
        if not sleep_until(deadline, svc.stop):
            return
        server.send_datagram(rec.datagram(index, server.version))
        svc.stats.count("frames")
        if index % 64 == 0:
            _sync(svc, "clients", len(server.clients))
    svc.log.info("replay of %s done: %d frames in %.2f s", rec.path, len(rec), rec.duration / speed)


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
    natnet_version: str | Version | None = None,
    replay: str | Path | None = None,
    speed: float = 1.0,
    rate: float | None = None,
    vehicles: Sequence[str] = (),
    occlusions: Sequence[Occlusion] = (),
    camera_latency: float = CAMERA_LATENCY,
    software_latency: float = SOFTWARE_LATENCY,
    truth_timeout: float = TRUTH_TIMEOUT,
) -> None:
    """Emulate Motive until ``stop`` is set (or SIGINT/SIGTERM), or until the replay ends.

    ``natnet_version`` overrides ``sim.natnet_version`` (replay: the recorded version); ``rate`` overrides
    ``sim.mocap_rate``. Bad arguments raise :class:`ConfigError` or :class:`NatNetServerError` before any
    socket is opened.
    """
    version = _parse_version(natnet_version) if natnet_version is not None else None
    if not speed > 0:
        raise ConfigError(f"replay speed must be positive, got {speed}")
    if replay is not None:
        rec = load_recording(replay)
        version = version or rec.version or Version.parse(cfg.sim.natnet_version)
        # Decoded frames carry no names: a configured vehicle's body name for its id, else RigidBody<id>.
        names = {body_id: name for _, name, body_id in rigid_bodies(cfg)}
        ids = sorted({b.id for f in rec.frames for b in f.rigid_bodies})
        models = rec.models or ModelDefs(tuple(RigidBodyDef(names.get(i, f"RigidBody{i}"), i) for i in ids))
        info = rec.server_info
        server = build_server(
            cfg,
            version,
            app_name=info.app_name if info else "Motive",
            app_version=info.app_version if info else None,
            clock=TickClock(rec.clock_frequency),
            frame_rate=round(rec.frame_rate, 3),
            models=models,
            allow_bitstream_change=True,
        )
        with running(SERVICE, cfg, options, host=host, stop=stop) as svc, server.start():
            svc.log.info(
                "replaying %s: %d frames, %.1f s, NatNet %s", rec.path, len(rec), rec.duration, version
            )
            _replay(svc, server, rec, speed)
        return

    rate = float(cfg.sim.mocap_rate if rate is None else rate)
    if not 0 < rate <= 1000:
        raise ConfigError(f"mocap rate must be in (0, 1000] Hz, got {rate}")
    bodies = rigid_bodies(cfg, vehicles)
    c = cfg.calibration
    scene = SimScene(
        FrameTransform(UpAxis.parse(cfg.mocap.up_axis), Calibration.from_degrees(c.yaw_deg, c.offset)),
        noise_m=cfg.sim.noise_m,
        dropout=cfg.sim.dropout,
        seed=cfg.sim.seed,
        camera_latency=camera_latency,
        software_latency=software_latency,
        truth_timeout=truth_timeout,
    )
    for vehicle, name, body_id in bodies:
        scene.add_body(name, body_id, key=vehicle)
    for name, _, _ in occlusions:
        cfg.vehicle(name)
        if name not in scene.keys:
            raise ConfigError(
                f"cannot occlude {name!r}: it is not streamed (streamed: {', '.join(scene.keys)})"
            )
    server = build_server(
        cfg, version or Version.parse(cfg.sim.natnet_version), frame_rate=rate, models=scene.model_defs()
    )
    with running(SERVICE, cfg, options, host=host, stop=stop) as svc, server.start():
        svc.log.info(
            "streaming %s at %g Hz (NatNet %s, %s-up)",
            ", ".join(f"{n} (id {i})" for _, n, i in bodies),
            rate,
            server.version,
            cfg.mocap.up_axis,
        )
        _simulate(svc, server, scene, rate, occlusions)


@service_command
def cli(
    shared: Shared,
    natnet_version: Annotated[
        str | None,
        typer.Option("--natnet-version", "-n", help="3.0, 3.1, 4.0 or 4.1 (default: sim.natnet_version)."),
    ] = None,
    replay: Annotated[
        Path | None, typer.Option("--replay", help="Replay a pcap/pcapng capture or JSON lines of frames.")
    ] = None,
    speed: Annotated[float, typer.Option("--speed", help="Replay speed (1 = recorded timing).")] = 1.0,
    rate: Annotated[
        float | None, typer.Option("--rate", help="Frames per second (default: sim.mocap_rate).")
    ] = None,
    vehicle: Annotated[
        list[str] | None, typer.Option("--vehicle", "-v", help="Stream only this vehicle (repeatable).")
    ] = None,
    occlude: Annotated[
        list[str] | None,
        typer.Option("--occlude", help="VEHICLE:START_S:DURATION_S — hide a body for a while (repeatable)."),
    ] = None,
) -> None:
    """Motive emulator: stream the simulated vehicles' true poses as NatNet (or replay a capture)."""
    try:
        main(
            shared.config,
            shared.bus,
            host=shared.host,
            natnet_version=natnet_version,
            replay=replay,
            speed=speed,
            rate=rate,
            vehicles=vehicle or (),
            occlusions=[parse_occlusion(o) for o in occlude or ()],
        )
    except CaptureError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


if __name__ == "__main__":
    typer.run(cli)
