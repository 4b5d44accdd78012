"""Per-publisher sequence numbers, so that every subscriber counts what the bus lost.

Real-time streams drop rather than wait (:class:`~arena_common.bus.session.Lane`): a congested link or a
full queue sheds samples, and Zenoh says nothing of it.  So every :class:`~arena_common.bus.session.Publisher`
numbers what it publishes, in the sample's Zenoh *attachment*: 16 bytes, the publisher's random 64-bit id
and the sample's number from 1, both unsigned little-endian (:data:`STAMP`).  A subscriber keeps, per key
and publisher, the last number seen; a jump of more than one is a loss of that many samples
(:class:`GapCounter`).  A publisher seen for the first time (a late subscriber, a restarted publisher:
a new id) starts a new count; a number at or below the last one is counted as *late*, not as a loss undone.

Samples with no attachment of this shape (a replay of a recording, another program) are counted as
*unnumbered*: nobody can tell what was lost among them.
"""

from __future__ import annotations

import os
import struct
import threading
from dataclasses import dataclass

#: The attachment: publisher id (u64 LE), then the sample's number (u64 LE, from 1).
STAMP = struct.Struct("<QQ")


def new_publisher_id() -> int:
    """A random 64-bit publisher id (two publishers of a bus never share one in practice)."""
    return int.from_bytes(os.urandom(8), "little")


@dataclass(slots=True)
class KeyLoss:
    """What one subscriber saw on one key: samples received, lost (gaps), late, unnumbered."""

    received: int = 0
    lost: int = 0
    late: int = 0
    unnumbered: int = 0


class GapCounter:
    """Counts, per key, the samples that never arrived: gaps in each publisher's sequence.

    Called from Zenoh's threads (one per subscription); a lock keeps concurrent callbacks exact.
    """

    def __init__(self) -> None:
        self.keys: dict[str, KeyLoss] = {}
        self._last: dict[tuple[str, int], int] = {}
        self._lock = threading.Lock()

    def observe(self, key: str, attachment: bytes | None) -> int:
        """Account one sample of ``key``; returns how many were lost just before it."""
        with self._lock:
            loss = self.keys.get(key)
            if loss is None:
                loss = self.keys[key] = KeyLoss()
            loss.received += 1
            if attachment is None or len(attachment) != STAMP.size:
                loss.unnumbered += 1
                return 0
            pub, seq = STAMP.unpack(attachment)
            last = self._last.get((key, pub))
            if last is None:
                self._last[(key, pub)] = seq
                return 0
            if seq <= last:
                loss.late += 1
                return 0
            self._last[(key, pub)] = seq
            gap = seq - last - 1
            loss.lost += gap
            return gap

    def lost(self) -> dict[str, int]:
        """Samples lost so far, per key (keys with none left out)."""
        with self._lock:
            return {k: v.lost for k, v in self.keys.items() if v.lost}
