"""Mocap sources other than the NatNet client: Motive CSV takes and the ``motioncapture`` package.

The CSV reader and replay are tested on ``tests/data/motive_take.csv`` (Motive's export layout: 24 frames at
120 Hz, bodies d1 (id 1, moving, yawing) and d2 (id 2, untracked in frames 10–12), plus rigid-body-marker
and unlabeled-marker columns to ignore) and on broken variants of it. The motioncapture source runs the
real library in its child process against the test's NatNet server on loopback.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from arena_common.core import config as config_mod
from arena_common.mocap.client import MocapError, NatNetClient, TimedFrame
from arena_common.mocap.sources import (
    CsvTakeError,
    CsvTakeSource,
    MotionCaptureSource,
    motioncapture_params,
    open_source,
    read_csv_take,
    resolve_csv,
)
from tests.helpers import TESTS
from tests.unit.mocap.test_natnet_client import Body, FakeMotive, Rejects, fake_motive  # noqa: F401

TAKE = TESTS / "data" / "motive_take.csv"


def test_reads_the_take() -> None:
    take = read_csv_take(TAKE)
    assert take.bodies == ((1, "d1"), (2, "d2"))
    assert take.frame_rate == 120.0
    assert take.metadata["Take Name"] == "arena_take"
    assert len(take.frames) == 24
    number, seconds, bodies = take.frames[5]
    assert (number, seconds) == (5, pytest.approx(5 / 120, abs=1e-6))
    d1, d2 = bodies
    assert d1.id == 1 and d1.tracking_valid
    assert d1.pos == pytest.approx((0.05, 1.0, -0.5))
    assert d1.quat_xyzw == pytest.approx((0.0, math.sin(0.125), 0.0, math.cos(0.125)), abs=1e-6)
    assert d1.mean_error == pytest.approx(0.000213)
    assert d2.pos == pytest.approx((1.0, 0.8, 1.0)) and d2.tracking_valid
    untracked = [n for n, _, b in take.frames if not b[1].tracking_valid]
    assert untracked == [10, 11, 12]
    assert all(b[0].tracking_valid for _, _, b in take.frames)


def _variant(tmp_path: Path, edit: Callable[[list[str]], None]) -> Path:
    lines = TAKE.read_text().splitlines()
    edit(lines)
    path = tmp_path / "take.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def _cell(line: str, index: int, value: str) -> str:
    cells = line.split(",")
    cells[index] = value
    return ",".join(cells)


def test_millimetres_are_scaled(tmp_path: Path) -> None:
    def to_mm(lines: list[str]) -> None:
        lines[0] = lines[0].replace("Length Units,Meters", "Length Units,Millimeters")

    take = read_csv_take(_variant(tmp_path, to_mm))
    assert take.frames[5][2][0].pos == pytest.approx((0.00005, 0.001, -0.0005))


def test_takes_without_metadata_or_blank_line(tmp_path: Path) -> None:
    def strip(lines: list[str]) -> None:
        del lines[0:2]

    take = read_csv_take(_variant(tmp_path, strip))
    assert len(take.frames) == 24 and take.frame_rate is None


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda ls: ls.__setitem__(0, ls[0].replace("Quaternion", "XYZ")), "Rotation Type is 'XYZ'"),
        (lambda ls: ls.__setitem__(0, ls[0].replace("Meters", "Inches")), "Length Units 'Inches'"),
        (
            lambda ls: ls.__setitem__(8, _cell(ls[8], 6, "abc")),
            "row 9, column 7: expected a number, got 'abc'",
        ),
        (lambda ls: ls.__setitem__(8, "x" + ls[8]), "row 9: frame number"),
        (lambda ls: ls.__setitem__(6, ls[6].replace("Time (Seconds)", "Time")), "Frame,Time (Seconds)"),
        (lambda ls: ls.__setitem__(2, ls[2].replace("Rigid Body,", "Bone,")), "no rigid body columns"),
        (lambda ls: ls.__setitem__(6, ls[6].replace(",W,", ",Q,", 1)), "'d1': no RW column"),
        (lambda ls: ls.__delitem__(slice(7, None)), "no frames"),
        (lambda ls: ls.__delitem__(slice(2, 5)), "not a Motive CSV export"),
    ],
)
def test_malformed_takes_are_refused_clearly(
    tmp_path: Path, edit: Callable[[list[str]], None], message: str
) -> None:
    path = _variant(tmp_path, edit)
    with pytest.raises(CsvTakeError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        read_csv_take(path)
    assert str(path) in str(info.value)


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(CsvTakeError, match="cannot read"):
        read_csv_take(tmp_path / "missing.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(CsvTakeError, match="empty file"):
        read_csv_take(tmp_path / "empty.csv")
    (tmp_path / "binary.csv").write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(CsvTakeError):
        read_csv_take(tmp_path / "binary.csv")


def _replay(source: CsvTakeSource, limit: float = 10.0) -> list[tuple[float, TimedFrame]]:
    got: list[tuple[float, TimedFrame]] = []
    deadline = time.monotonic() + limit
    while not source.finished:
        assert time.monotonic() < deadline, "replay did not finish"
        frame = source.poll(0.05)
        if frame is not None:
            got.append((time.monotonic(), frame))
    return got


def test_replay_keeps_the_take_timing() -> None:
    counts: dict[str, int] = {}
    source = CsvTakeSource(TAKE, on_count=lambda k, n: counts.__setitem__(k, counts.get(k, 0) + n)).open()
    start = time.monotonic()
    got = _replay(source)
    assert [f.frame_number for _, f in got] == list(range(24))
    for when, frame in got:
        assert when - start >= frame.mts - 0.001  # never early
    # Never early (above); late only by what a busy machine adds (0.05 s seen idle at most, 2 s allowed).
    assert 23 / 120 - 0.001 <= got[-1][0] - start < 23 / 120 + 2.0
    steps = [(b.t - a.t) / 1e9 for (_, a), (_, b) in itertools.pairwise(got)]
    assert steps == pytest.approx([1 / 120] * 23, abs=2e-6)  # t follows the take exactly
    first = got[0][1]
    assert first.tsrc == "arrival" and first.lat == -1 and first.names == {1: "d1", 2: "d2"}
    assert counts["frames"] == 24
    assert source.poll(0.01) is None


def test_replay_faster_and_in_a_loop() -> None:
    source = CsvTakeSource(TAKE, speed=4.0, loop=True).open()
    numbers: list[int] = []
    start = time.monotonic()
    while len(numbers) < 30:
        assert time.monotonic() - start < 5
        frame = source.poll(0.05)
        if frame is not None:
            numbers.append(frame.frame_number)
    assert numbers[:24] == list(range(24)) and numbers[24:] == list(range(6))
    assert time.monotonic() - start >= 29 / 120 / 4 - 0.01  # never faster than 4× (the bound above: 5 s)
    with pytest.raises(MocapError, match="speed"):
        CsvTakeSource(TAKE, speed=0)


def test_sources_from_the_config(tmp_path: Path) -> None:
    path = tmp_path / "arena.toml"
    path.write_text(
        '[mocap]\nsource = "csv"\ncsv_file = "take.csv"\n'
        '[vehicles.d1]\nrigid_body = "d1"\nmavlink = "udpin:127.0.0.1:14540"\nsystem_id = 1\n'
    )
    (tmp_path / "take.csv").write_text(TAKE.read_text())
    cfg = config_mod.load(path)
    assert resolve_csv(cfg) == tmp_path / "take.csv"  # beside the config file
    source = open_source(cfg)
    assert isinstance(source, CsvTakeSource)
    cfg = cfg.replace(mocap=config_mod.MocapSpec(source="natnet", server="127.0.0.1", multicast=False))
    assert isinstance(open_source(cfg), NatNetClient)
    spec = config_mod.MocapSpec(
        source="motioncapture", motioncapture_type="optitrack", server="10.0.0.5", interface="10.0.0.9"
    )
    assert motioncapture_params(spec) == (
        "optitrack",
        {"hostname": "10.0.0.5", "port_command": "1510", "interface_ip": "10.0.0.9"},
    )
    assert motioncapture_params(config_mod.MocapSpec(server="h")) == ("vrpn", {"hostname": "h"})
    assert isinstance(open_source(cfg.replace(mocap=spec)), MotionCaptureSource)
    with pytest.raises(MocapError, match="csv_file"):
        resolve_csv(cfg.replace(mocap=config_mod.MocapSpec(source="csv")))


# ------------------------------------------------------------------------------------------------------------
# motioncapture (libmotioncapture) in its child process
# ------------------------------------------------------------------------------------------------------------


def _optitrack(
    server: FakeMotive,
    rejects: Rejects,
    loss_timeout: float = 1.0,
    restart_after: float = 5.0,
    max_backoff: float = 5.0,
) -> MotionCaptureSource:
    params = {"hostname": "127.0.0.1", "port_command": str(server.command_port), "interface_ip": "127.0.0.1"}
    return MotionCaptureSource(
        "optitrack",
        params,
        on_reject=rejects,
        loss_timeout=loss_timeout,
        restart_after=restart_after,
        max_backoff=max_backoff,
    )


def _frames_until(
    server: FakeMotive | None, source: MotionCaptureSource, pred: Callable[[TimedFrame], bool], timeout: float
) -> TimedFrame:
    deadline = time.monotonic() + timeout
    while True:
        assert time.monotonic() < deadline, "timed out waiting for a frame from the motioncapture child"
        if server is not None:
            server.send_frame()
        frame = source.poll(0.02)
        if frame is not None and pred(frame):
            return frame


def test_motioncapture_optitrack_against_a_natnet_server(fake_motive: Callable[..., FakeMotive]) -> None:  # noqa: F811
    pytest.importorskip("motioncapture")
    server = fake_motive("3.1", bodies=[Body(1, "d1", (0.4, 1.1, -0.2), (0.0, 0.6, 0.0, 0.8)), Body(5, "b5")])
    rejects = Rejects()
    # Silence is not under test here: a busy machine may take seconds to start the child and connect.
    source = _optitrack(server, rejects, loss_timeout=60.0, restart_after=120.0).open()
    try:
        frame = _frames_until(server, source, lambda f: len(f.bodies) == 2, timeout=20)
        by_name = {frame.names[b.id]: b for b in frame.bodies}
        d1 = by_name["d1"]
        assert d1.id < 0 and d1.tracking_valid  # the library gives names only: stable negative ids
        assert d1.pos == pytest.approx((0.4, 1.1, -0.2), abs=1e-6)
        assert d1.quat_xyzw == pytest.approx((0.0, 0.6, 0.0, 0.8), abs=1e-6)
        assert frame.tsrc == "arrival" and frame.t == frame.arrival
        # The library drops untracked bodies from its frames: a body seen before is reported untracked.
        server.bodies[1].tracked = False
        frame = _frames_until(
            server, source, lambda f: not all(b.tracking_valid for b in f.bodies), timeout=10
        )
        lost = [frame.names[b.id] for b in frame.bodies if not b.tracking_valid]
        assert lost == ["b5"]
    finally:
        source.close()
    assert source.proc is None
    assert rejects.items == []


def test_motioncapture_silence_restarts_the_child(fake_motive: Callable[..., FakeMotive]) -> None:  # noqa: F811
    pytest.importorskip("motioncapture")
    server = fake_motive("3.0", answer_connect=False)  # the library's connect blocks forever
    rejects = Rejects()
    source = _optitrack(server, rejects, loss_timeout=0.3, restart_after=1.0, max_backoff=0.5).open()
    try:
        deadline = time.monotonic() + 15
        while source.starts < 2:
            assert time.monotonic() < deadline, f"no restart; rejects {rejects.items}"
            assert source.poll(0.1) is None
        assert "no_data" in rejects.reasons() and "worker_restart" in rejects.reasons()
        # The server comes back: frames flow.  A child now gets longer than one second to start and connect
        # (a busy machine may need that), else it could be restarted again before its first frame.
        source.restart_after = 30.0
        server.answer_connect = True
        _frames_until(server, source, lambda f: len(f.bodies) == 2, timeout=20)
    finally:
        source.close()


def test_motioncapture_bad_type_is_reported_and_retried() -> None:
    pytest.importorskip("motioncapture")
    rejects = Rejects()
    source = MotionCaptureSource("no-such-system", {}, on_reject=rejects, max_backoff=0.2).open()
    try:
        deadline = time.monotonic() + 20
        while rejects.reasons().count("worker_exit") < 2:
            assert time.monotonic() < deadline, "the child's failure was not reported"
            source.poll(0.1)
    finally:
        source.close()
    assert "Unknown motion capture type" in dict(rejects.items)["worker_exit"]
