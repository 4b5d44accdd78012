"""Who holds a vehicle, and what orders the hand-overs: identities, never arrival times or wall clocks.

Setpoints and commands travel on two Zenoh keys and arrive in any order; the clocks of two hosts differ.
So a hand-over is decided by what the messages carry:

- every setpoint names its **stream** (an identity unique to one program's one stream) and its **number**
  within it (``seq``, from 1);
- authority over the vehicle passes **only by commands**, in the order the gateway executes them (a
  program's commands are answered one at a time, so its own are in the order it sent them):
  ``mode OFFBOARD`` with a stream's identity gives the vehicle to that stream; ``goto`` to the gateway's
  own hold; ``takeoff``, ``land``, ``hold``, another mode, ``kill`` and an estop to the autopilot;
- a command that takes the vehicle **ends** every stream the gateway has seen (the one holding it and
  those waiting): a setpoint of an ended stream, however late it arrives, is dropped and counted and
  never takes over; a setpoint numbered at or below its stream's newest is dropped and counted too;
- a stream that does not hold the vehicle is held back (counted) until a command engages it.

:class:`Ledger` remembers streams and their ends (bounded); :class:`Holder` names who holds the vehicle.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Literal

__all__ = ["MEMORY", "Holder", "Ledger"]

MEMORY = 1024  # streams remembered (their newest number, or their end); the oldest are forgotten first


@dataclass(frozen=True, slots=True)
class Holder:
    """Who holds the vehicle: a setpoint stream (``sid``) or the gateway's goto, and the source of the
    command that gave it."""

    kind: Literal["stream", "goto"]
    sid: str
    src: str

    def describe(self) -> str:
        """``stream 7f3a… (lab-pc/flight.py)`` or ``goto (lab-pc/flight.py)``."""
        if self.kind == "goto":
            return f"goto ({self.src or '?'})"
        return f"stream {self.sid} ({self.src or '?'})"


class Ledger:
    """Each stream's newest number and the streams that ended, remembered for the last ``memory`` streams."""

    def __init__(self, memory: int = MEMORY) -> None:
        self.memory = memory
        self._seq: collections.OrderedDict[str, int] = collections.OrderedDict()
        self._ended: collections.OrderedDict[str, str] = collections.OrderedDict()

    def ended(self, sid: str) -> str | None:
        """Why stream ``sid`` ended, or None while it may still take the vehicle."""
        return self._ended.get(sid)

    def end(self, sid: str, why: str) -> None:
        """Mark ``sid`` ended (its later setpoints are dropped); the first reason stays."""
        if sid not in self._ended:
            self._ended[sid] = why
            if len(self._ended) > self.memory:
                self._ended.popitem(last=False)

    def admit(self, sid: str, seq: int) -> str | None:
        """Why a setpoint numbered ``seq`` of stream ``sid`` is dropped (its stream ended, or it is not
        newer than the newest seen), else None (and ``seq`` is the newest now)."""
        why = self._ended.get(sid)
        if why is not None:
            return f"its stream {sid} ended ({why})"
        newest = self._seq.get(sid, 0)
        if seq <= newest:
            return f"number {seq} of stream {sid} arrived after number {newest}"
        self._seq[sid] = seq
        self._seq.move_to_end(sid)
        if len(self._seq) > self.memory:
            self._seq.popitem(last=False)
        return None

    def seen(self) -> list[str]:
        """The streams seen and not ended, oldest first."""
        return [sid for sid in self._seq if sid not in self._ended]
