"""Captured Motive sessions to replay (the Motive emulator's other frame source): pcap/pcapng captures kept
byte for byte, or decoded frames as JSON lines, with their timing and what their server said."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from arena_common.mocap import natnet
from arena_common.mocap.capture import CaptureError, iter_udp, read_frames_jsonl
from arena_common.mocap.natnet import Frame, MessageId, ModelDefs, ServerInfo, Version
from arena_common.sim.natnet_motive import TICK_FREQUENCY, NatNetServerError, served_version

__all__ = ["Recording", "iter_schedule", "load_recording"]

log = logging.getLogger("arena.natnet_server")


# ------------------------------------------------------------------------------------------------------------
# Recordings
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """A captured Motive session: its frames with their capture times, and what its server said.

    From a pcap/pcapng capture the frames are kept byte for byte (``raw``) and decoded in full, with the
    capture's SERVERINFO and MODELDEF. From JSON lines (decoded frames) only rigid bodies and timing exist;
    the clock frequency, which such files do not hold, is estimated from the tick stamps and capture times
    unless given.
    """

    path: str
    times: tuple[float, ...]
    frames: tuple[Frame, ...]
    version: Version | None = None
    raw: tuple[bytes, ...] = ()
    server_info: ServerInfo | None = None
    models: ModelDefs | None = None
    clock_frequency: int = TICK_FREQUENCY

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return self.times[-1] - self.times[0] if self.times else 0.0

    @property
    def frame_rate(self) -> float:
        """The median frame rate (Hz), from frame numbers and capture times."""
        if len(self.times) < 2:
            return 0.0
        steps = sorted(
            (t1 - t0) / (f1.frame_number - f0.frame_number)
            for t0, t1, f0, f1 in zip(self.times, self.times[1:], self.frames, self.frames[1:], strict=False)
            if f1.frame_number > f0.frame_number and t1 > t0
        )
        return 1.0 / steps[len(steps) // 2] if steps else 0.0

    def datagram(self, index: int, version: Version) -> bytes:
        """Frame ``index`` as a datagram for ``version``: as captured when the version is the recorded one."""
        if self.raw and version == self.version:
            return self.raw[index]
        try:
            return natnet.encode_frame(self.frames[index], version)
        except natnet.NatNetError as exc:
            raise NatNetServerError(
                f"{self.path}: frame {index} cannot be sent as NatNet {version}: {exc}"
            ) from None


def load_recording(
    path: str | Path, *, version: str | Version | None = None, clock_frequency: int | None = None
) -> Recording:
    """Load a capture to replay: pcap/pcapng (recognised by content) or JSON lines of decoded frames.

    ``version`` decodes a capture whose SERVERINFO is missing; ``clock_frequency`` overrides the recorded
    (or estimated) tick frequency. Raises :class:`NatNetServerError` (no frames, undecodable frames) or
    :class:`~arena_common.mocap.capture.CaptureError` (malformed file).
    """
    p = Path(path)
    try:
        with open(p, "rb") as stream:
            head = stream.read(4)
    except OSError as exc:
        raise NatNetServerError(f"cannot read {p}: {exc.strerror or exc}") from None
    forced = served_version(version) if version is not None else None
    # pcap (either byte order, µs or ns) and pcapng magics; anything else is read as JSON lines.
    is_capture = head in (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
    rec = _load_pcap(p, forced) if is_capture or head == b"\x0a\x0d\x0d\x0a" else _load_jsonl(p, forced)
    if not rec.frames:
        raise NatNetServerError(f"{p}: no NatNet frames to replay")
    if clock_frequency is not None:
        if clock_frequency <= 0:
            raise NatNetServerError(f"clock frequency must be positive, got {clock_frequency}")
        rec = replace(rec, clock_frequency=int(clock_frequency))
    return rec


def _load_pcap(path: Path, forced: Version | None) -> Recording:
    info: ServerInfo | None = None
    server: str | None = None
    modeldef: bytes | None = None
    captured: list[tuple[float, str, bytes]] = []
    with open(path, "rb") as stream:
        for dg in iter_udp(stream):
            try:
                message_id, payload = natnet.split_packet(dg.payload)
            except natnet.NatNetError:
                continue
            if message_id == MessageId.SERVERINFO and info is None:
                try:
                    info = natnet.decode_server_info(payload)
                except natnet.NatNetError:
                    continue
                server = dg.src[0]
            elif message_id == MessageId.MODELDEF:
                modeldef = payload
            elif message_id == MessageId.FRAMEOFDATA:
                captured.append((dg.timestamp, dg.src[0], dg.payload))
    version = forced or (info.natnet_version if info else None)
    if version is None:
        raise NatNetServerError(
            f"{path}: the capture has no SERVERINFO; give the NatNet version to decode it"
        )
    times, frames, raw = [], [], []
    for t, src, datagram in captured:
        if server is not None and src != server:
            continue
        try:
            frames.append(natnet.decode_frame(natnet.split_packet(datagram)[1], version, full=True))
        except natnet.NatNetError as exc:
            raise NatNetServerError(f"{path}: frame at capture time {t:.6f}: {exc}") from None
        times.append(t)
        raw.append(datagram)
    models = None
    if modeldef is not None:
        try:
            models = natnet.decode_model_defs(modeldef, version)
        except natnet.NatNetError as exc:
            log.warning("%s: MODELDEF not decoded, serving none: %s", path, exc)
    clock = info.clock_frequency if info and info.clock_frequency else _estimate_clock(times, frames)
    return Recording(str(path), tuple(times), tuple(frames), version, tuple(raw), info, models, clock)


def _load_jsonl(path: Path, forced: Version | None) -> Recording:
    times, frames = [], []
    try:
        for recorded in read_frames_jsonl(path):
            # Only rigid bodies and timing are recorded: the other sections' counts cannot be re-encoded.
            frame = replace(
                recorded.frame,
                n_marker_sets=0,
                n_unlabeled_markers=0,
                n_skeletons=0,
                n_assets=0,
                n_labeled_markers=0,
                n_force_plates=0,
                n_devices=0,
            )
            times.append(recorded.receive_time)
            frames.append(frame)
    except CaptureError:
        raise
    except UnicodeDecodeError:
        raise CaptureError(f"{path}: neither a pcap/pcapng capture nor JSON lines") from None
    return Recording(
        str(path), tuple(times), tuple(frames), forced, (), None, None, _estimate_clock(times, frames)
    )


def _estimate_clock(times: Sequence[float], frames: Sequence[Frame]) -> int:
    """Ticks per second of a recording whose SERVERINFO is unknown.

    Motive's frame ``timestamp`` and the mid-exposure ticks both follow the camera clock, so their ratio
    is the tick frequency (within 0.01 % on the real capture); without timestamps, a least-squares fit of
    the transmit ticks against capture times (within 0.1 %).
    """
    stamped = [f for f in frames if f.timestamp is not None and f.cam_mid_exposure]
    if len(stamped) >= 2:
        first, last = stamped[0], stamped[-1]
        assert first.timestamp is not None and last.timestamp is not None
        span = last.timestamp - first.timestamp
        ticks = (last.cam_mid_exposure or 0) - (first.cam_mid_exposure or 0)
        if span >= 0.05 and ticks > 0:
            return round(ticks / span)
    pairs = [(t, f.transmit) for t, f in zip(times, frames, strict=True) if f.transmit]
    if len(pairs) < 2 or pairs[-1][0] - pairs[0][0] < 0.05:
        return TICK_FREQUENCY
    mt = sum(t for t, _ in pairs) / len(pairs)
    mk = sum(k for _, k in pairs) / len(pairs)
    var = sum((t - mt) ** 2 for t, _ in pairs)
    cov = sum((t - mt) * (k - mk) for t, k in pairs)
    slope = cov / var if var > 0 else 0.0
    return round(slope) if slope >= 1 else TICK_FREQUENCY


def iter_schedule(times: Sequence[float], start_ns: int, speed: float = 1.0) -> Iterator[tuple[int, int]]:
    """``(index, deadline_ns)`` for each capture time, relative to the first, at ``speed`` × real time."""
    if not speed > 0:
        raise NatNetServerError(f"replay speed must be positive, got {speed}")
    if not times:
        return
    t0 = times[0]
    for index, t in enumerate(times):
        yield index, start_ns + round((t - t0) / speed * 1e9)
