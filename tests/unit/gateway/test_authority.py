"""Who holds a vehicle, decided by identities and commands, never by arrival (gateway.authority and the
forwarder's rules): the setpoint forwarder driven with explicit times, its MAVLink output recorded."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import pytest

from arena_common.core import config as config_mod
from arena_common.core import wire
from arena_common.gateway.authority import Ledger
from arena_common.gateway.events import EventSink
from arena_common.gateway.setpoints import SetpointForwarder
from tests.helpers import write_config
from tests.unit.gateway.test_gateway_safety import _Link


class _Fwd:
    def __init__(self, tmp_path: Path, grounded: str | None = None) -> None:
        cfg = config_mod.load(write_config(tmp_path, "tcp/127.0.0.1:7447", n_vehicles=1))
        self.events = EventSink(None, logging.getLogger("test"))
        self.link = _Link()
        self.grounded = grounded
        self.fwd = SetpointForwarder(
            self.link,  # type: ignore[arg-type]
            1,
            cfg.arena,
            self.events,
            position=lambda: (0.0, 0.0, -1.0),
            grounded=lambda: self.grounded,
        )
        self.seqs: dict[str, itertools.count[int]] = {}
        self.t = 100.0

    def sp(self, stream: str, north: float, seq: int | None = None, src: str = "prog") -> wire.Setpoint:
        n = seq if seq is not None else next(self.seqs.setdefault(stream, itertools.count(1)))
        return wire.Setpoint(t=1, p=(north, 0.0, -1.0), lease=0.5, src=src, stream=stream, seq=n)

    def offer(self, sp: wire.Setpoint) -> str | None:
        self.t += 0.05
        return self.fwd.offer(sp, self.t)

    def sent_north(self) -> list[float]:
        return [m.x for m in self.link.sent if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]  # type: ignore[attr-defined]

    def texts(self, kind: str) -> list[str]:
        return [e.text for e in self.events.recent if e.kind == kind]


def test_a_late_setpoint_of_a_stream_handed_to_goto_never_takes_over(tmp_path: Path) -> None:
    """Issue 32's follow(): the stream's last setpoint, sent before the hand-over, arrives after it."""
    f = _Fwd(tmp_path)
    late = f.sp("follow-1", 0.5)  # numbered before the hand-over
    f.offer(f.sp("follow-1", 0.1))
    assert f.fwd.engage("follow-1", "prog", f.t) is None
    f.offer(f.sp("follow-1", 0.2))
    f.fwd.start_goto((0.3, 0.0, -1.0), 0.0, f.t, src="prog")  # the hand-over
    before = len(f.sent_north())
    assert f.offer(late) is not None  # arrives after it: dropped
    assert f.fwd.holder == "goto (prog)" and f.fwd.dropped == 1
    f.fwd.tick(f.t + 0.1)
    assert f.sent_north()[before:] and all(abs(x - 0.5) > 1e-9 for x in f.sent_north()[before:])
    assert any(
        "goto from prog takes the vehicle from stream follow-1 (prog)" in t for t in f.texts("authority")
    )
    assert any("setpoint dropped: its stream follow-1 ended" in t for t in f.texts("authority"))


def test_setpoints_out_of_order_are_dropped_and_counted(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    assert f.fwd.engage("s", "prog", f.t) is None
    assert f.offer(f.sp("s", 0.1, seq=1)) is None
    assert f.offer(f.sp("s", 0.3, seq=3)) is None
    assert f.offer(f.sp("s", 0.2, seq=2)) == "number 2 of stream s arrived after number 3"
    assert f.offer(f.sp("s", 0.3, seq=3)) is not None  # a duplicate too
    assert f.fwd.dropped == 2 and f.sent_north()[-1] == 0.3


def test_a_stream_waits_for_its_engage_and_a_take_over_names_both(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    f.fwd.start_goto((0.0, 0.0, -1.0), 0.0, f.t, src="cli")
    for _ in range(5):  # a second program streams while the goto holds: held back, never sent
        assert f.offer(f.sp("b", 0.4, src="other")) is None
        f.fwd.tick(f.t)
    assert 0.4 not in f.sent_north() and f.fwd.held == 5 and f.fwd.holder == "goto (cli)"
    assert f.fwd.engage("b", "other", f.t) is None  # its mode OFFBOARD
    assert f.sent_north()[-1] == 0.4 and f.fwd.holder == "stream b (other)"
    assert "stream b (other) takes the vehicle from goto (cli)" in f.texts("authority")
    # A third stream engaged by its own command ends b: b's setpoints are dropped from then on.
    f.offer(f.sp("c", 0.6, src="third"))
    assert f.fwd.engage("c", "third", f.t) is None
    assert f.offer(f.sp("b", 0.45, src="other")) is not None
    assert f.sent_north()[-1] == 0.6
    assert f.fwd.engage("b", "other", f.t) is not None  # an ended stream cannot come back


def test_a_command_ends_every_stream_seen_before_it(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    f.offer(f.sp("a", 0.1))
    f.offer(f.sp("waiting", 0.2))
    assert f.fwd.engage("a", "prog", f.t) is None
    f.fwd.supersede("hold from prog")
    f.fwd.latch("the vehicle switched to AUTO.LOITER")
    assert f.fwd.holder == ""
    for sid in ("a", "waiting"):
        assert f.offer(f.sp(sid, 0.3)) is not None
        assert (
            f.fwd.engage(sid, "prog", f.t)
            == f"stream {sid} has ended (superseded by hold from prog): start a new one"
        )
    assert f.fwd.dropped == 2
    # A stream begun after the command is a new one: it may be engaged.
    f.offer(f.sp("after", 0.4))
    assert f.fwd.engage("after", "prog", f.t) is None and f.sent_north()[-1] == 0.4


def test_mode_offboard_without_a_stream_engages_the_newest_live_one(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    assert f.fwd.engage(None, "cli", f.t) is not None  # nothing streams
    f.offer(f.sp("old", 0.1))
    f.offer(f.sp("new", 0.2))
    assert f.fwd.engage(None, "cli", f.t) is None and f.fwd.holder == "stream new (cli)"
    f.t += 5.0  # leases lapse: nothing live any more
    f.fwd.tick(f.t)
    f.fwd.latch("left")
    assert f.fwd.engage(None, "cli", f.t) is not None


@pytest.mark.parametrize("why", ["disarmed", "on the ground", "landing"])
def test_nothing_flies_from_the_floor(tmp_path: Path, why: str) -> None:
    f = _Fwd(tmp_path, grounded=why)
    assert f.offer(f.sp("s", 0.1)) == f"{why}: take off first"
    assert f.fwd.refused == 1 and f.sent_north() == []
    assert f"setpoint refused: {why}: take off first" in f.texts("safety")


def test_a_setpoint_without_a_stream_identity_is_refused(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    reason = f.offer(wire.Setpoint(t=1, p=(0.0, 0.0, -1.0)))
    assert reason is not None and "no stream identity" in reason and f.fwd.refused == 1


def test_a_lapsed_lease_ends_the_stream_holding_the_vehicle(tmp_path: Path) -> None:
    f = _Fwd(tmp_path)
    f.offer(f.sp("dies", 0.1))
    assert f.fwd.engage("dies", "prog", f.t) is None
    f.fwd.tick(f.t + 1.0)  # the program died: its lease lapsed
    assert f.fwd.holder == "" and any("lease expired" in t for t in f.texts("safety"))
    assert f.offer(f.sp("dies", 0.2)) == "its stream dies ended (its lease lapsed)"


def test_the_ledger_forgets_the_oldest_streams_first() -> None:
    ledger = Ledger(memory=3)
    for k in range(5):
        assert ledger.admit(f"s{k}", 1) is None
        ledger.end(f"s{k}", "done")
    assert ledger.ended("s0") is None and ledger.ended("s4") == "done"
    assert ledger.admit("s4", 2) == "its stream s4 ended (done)"
