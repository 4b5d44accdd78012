"""MAVLink 2 message signing between a gateway and its vehicle: key files, signing and verification.

A vehicle's config may name a key file (``vehicles.<name>.signing_key_file``): the 32-byte secret as 64
hex digits, readable by its owner only.  :func:`generate_key_file` writes one (``arena px4 keygen FILE``),
:func:`load_key` reads one and :func:`vehicle_key` finds a vehicle's (a relative path is relative to the
config file's directory).  The key travels as a :class:`SigningKey`, whose ``repr`` shows a fingerprint
only: the secret itself is never logged, published or put in an exception.

:class:`LinkSigning` signs one link's output and verifies its input as the MAVLink signing spec says
(https://mavlink.io/en/guide/message_signing.html):

- a signed frame carries 13 more bytes — link id (1), timestamp (6, little-endian, 10 µs units since
  2015-01-01 00:00 UTC) and the first 6 bytes of SHA-256(secret + header + payload + CRC + link id +
  timestamp) — and has bit 0x01 of its incompatibility flags set;
- each stream (link id, system id, component id) must carry increasing timestamps: a frame whose
  timestamp is not above the last accepted one of its stream is a replay and is dropped; a stream not seen
  before is accepted if its timestamp is at most one minute behind ours;
- our own timestamp is the wall clock, at least one more than the last one sent, and never below the
  newest timestamp accepted from the other side.

The signature is checked before the timestamp is recorded, so a forged frame cannot move a stream's
timestamp ahead and lock the real sender out (pymavlink's own check records it first).

Unsigned frames are dropped except the message ids in ``allow_unsigned``.  The gateway lets only
RADIO_STATUS through unsigned (:data:`GATEWAY_UNSIGNED`: telemetry radios inject it and hold no key, as
the spec suggests); a simulated PX4 lets through what PX4 with ``MAV_SIGN_CFG`` = 2 does
(:data:`PX4_UNSIGNED`: RADIO_STATUS, ADSB_VEHICLE, COLLISION).  HEARTBEAT is not among them: an unsigned
heartbeat could fake a live link and a mode.  A frame let through unsigned is data, never proof of who sent
it (:meth:`LinkSigning.verify` tells the two apart): only a verified one may move a link to a new address.
"""

from __future__ import annotations

import collections
import hashlib
import hmac
import logging
import os
import secrets
import stat
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.mavlink import px4

__all__ = [
    "GATEWAY_UNSIGNED",
    "KEY_BYTES",
    "PX4_UNSIGNED",
    "LinkSigning",
    "SigningError",
    "SigningKey",
    "generate_key_file",
    "key_path",
    "load_key",
    "parse_key",
    "setup_signing",
    "signing_timestamp",
    "vehicle_key",
    "write_px4_secret",
]

log = logging.getLogger("arena.signing")

KEY_BYTES = 32
EPOCH_2015 = 1420070400  # 2015-01-01 00:00:00 UTC in Unix seconds
TICKS_PER_SECOND = 100_000  # timestamp unit: 10 µs
NEW_STREAM_WINDOW = 60 * TICKS_PER_SECOND  # a new stream may lag our timestamp by one minute
SIGNATURE_BYTES = 13
_IFLAG_SIGNED = 0x01
_MAGIC_V2 = 0xFD

#: Message ids the gateway accepts unsigned from its vehicle (RADIO_STATUS: radios cannot sign).
GATEWAY_UNSIGNED: frozenset[int] = frozenset({px4.MAVLINK_MSG_ID_RADIO_STATUS})
#: Message ids PX4 accepts unsigned when signing is required (``MavlinkSignControl::accept_unsigned``).
PX4_UNSIGNED: frozenset[int] = frozenset(
    {px4.MAVLINK_MSG_ID_RADIO_STATUS, px4.MAVLINK_MSG_ID_ADSB_VEHICLE, px4.MAVLINK_MSG_ID_COLLISION}
)


class SigningError(ConfigError):
    """A signing key file that cannot be used (missing, unreadable, wrong length, not hexadecimal)."""


class SigningKey:
    """A 32-byte MAVLink signing secret.  ``str``/``repr`` show its fingerprint, never the secret."""

    __slots__ = ("_secret", "fingerprint")

    def __init__(self, secret: bytes) -> None:
        if not isinstance(secret, (bytes, bytearray)) or len(secret) != KEY_BYTES:
            raise SigningError(f"a signing key is {KEY_BYTES} bytes")
        if not any(secret):
            raise SigningError("a signing key of all zeros means 'no signing' to PX4: generate a real key")
        self._secret = bytes(secret)
        #: 8 hex digits identifying the key (a hash, safe to log): equal on both ends when the keys match.
        self.fingerprint = hashlib.sha256(b"arena signing key id\0" + self._secret).hexdigest()[:8]

    @property
    def secret(self) -> bytes:
        """The raw 32 bytes (give them to MAVLink only)."""
        return self._secret

    def __repr__(self) -> str:
        return f"SigningKey(id={self.fingerprint})"

    __str__ = __repr__

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SigningKey) and hmac.compare_digest(self._secret, other._secret)

    def __hash__(self) -> int:
        return hash(self.fingerprint)

    def __reduce__(self) -> Any:
        raise TypeError("a SigningKey is not serialisable")


# ------------------------------------------------------------------------------------------ key files
def parse_key(text: str, source: str = "signing key") -> SigningKey:
    """A key from its text: 64 hex digits, surrounding whitespace ignored.  Errors never echo the text."""
    digits = "".join(text.split())
    if len(digits) != 2 * KEY_BYTES:
        raise SigningError(
            f"{source}: expected {2 * KEY_BYTES} hex digits (a {KEY_BYTES}-byte key), found {len(digits)} "
            "characters"
        )
    bad = next((i for i, c in enumerate(digits) if c not in "0123456789abcdefABCDEF"), None)
    if bad is not None:
        raise SigningError(f"{source}: not hexadecimal (character {bad + 1} of {len(digits)} is not 0-9a-f)")
    try:
        return SigningKey(bytes.fromhex(digits))
    except SigningError as exc:
        raise SigningError(f"{source}: {exc}") from None


def load_key(path: str | Path) -> SigningKey:
    """Read a key file: :class:`SigningError` naming the file and the problem; a warning (log) when other
    users may read it."""
    p = Path(path).expanduser()
    try:
        st = p.stat()
    except FileNotFoundError:
        raise SigningError(
            f"{p}: signing key file does not exist (create one with `arena px4 keygen {p}`)"
        ) from None
    except OSError as exc:
        raise SigningError(f"{p}: cannot read the signing key file: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise SigningError(f"{p}: the signing key file is not a regular file")
    if st.st_size > 4096:
        raise SigningError(f"{p}: {st.st_size} bytes is too long for a signing key file (64 hex digits)")
    try:
        text = p.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise SigningError(f"{p}: not a text file of 64 hex digits") from None
    except OSError as exc:
        raise SigningError(f"{p}: cannot read the signing key file: {exc.strerror or exc}") from None
    key = parse_key(text, str(p))
    if st.st_mode & 0o077:
        log.warning(
            "%s: signing key file is accessible to other users (mode %03o): chmod 600 %s",
            p,
            stat.S_IMODE(st.st_mode),
            p,
        )
    return key


def generate_key_file(path: str | Path, *, overwrite: bool = False) -> SigningKey:
    """Write a new random key to ``path`` (mode 600); :class:`SigningError` if it exists (unless
    ``overwrite``) or cannot be written."""
    p = Path(path).expanduser()
    key = SigningKey(secrets.token_bytes(KEY_BYTES))
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
    try:
        fd = os.open(p, flags, 0o600)
    except FileExistsError:
        raise SigningError(f"{p}: exists already (keep it, or overwrite it deliberately)") from None
    except OSError as exc:
        raise SigningError(f"{p}: cannot write the signing key file: {exc.strerror or exc}") from None
    try:
        os.fchmod(fd, 0o600)  # an existing file keeps its mode with O_TRUNC
        os.write(fd, (key.secret.hex() + "\n").encode("ascii"))
    finally:
        os.close(fd)
    return key


def write_px4_secret(path: str | Path, key: SigningKey, timestamp: int | None = None) -> None:
    """Write ``key`` in PX4's own format (``/fs/microsd/mavlink/.secret``: 32 bytes, then u64 timestamp)."""
    p = Path(path).expanduser()
    ts = signing_timestamp() if timestamp is None else int(timestamp)
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    except OSError as exc:
        raise SigningError(f"{p}: cannot write: {exc.strerror or exc}") from None
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, key.secret + ts.to_bytes(8, "little"))
    finally:
        os.close(fd)


def key_path(cfg: ArenaConfig, vehicle: str) -> Path | None:
    """The vehicle's key file (relative paths from the config file's directory), None without signing."""
    name = cfg.vehicle(vehicle).signing_key_file
    return cfg.file(name) if name else None


def vehicle_key(cfg: ArenaConfig, vehicle: str) -> SigningKey | None:
    """The vehicle's signing key, or None when its config has no ``signing_key_file``."""
    p = key_path(cfg, vehicle)
    if p is None:
        return None
    try:
        return load_key(p)
    except SigningError as exc:
        raise SigningError(f"vehicles.{vehicle}.signing_key_file: {exc}") from None


# ---------------------------------------------------------------------------------------- timestamps
def signing_timestamp(unix_seconds: float | None = None) -> int:
    """A signing timestamp: 10 µs units since 2015-01-01 UTC (now by default)."""
    t = time.time() if unix_seconds is None else unix_seconds
    return max(0, int((t - EPOCH_2015) * TICKS_PER_SECOND))


# -------------------------------------------------------------------------------------------- links
class LinkSigning:
    """Signing state of one MAVLink link: signs what a pymavlink ``MAVLink`` object sends, checks frames.

    :meth:`attach` makes the object sign every frame it packs (pymavlink adds the 13 bytes and counts the
    timestamp up); call :meth:`refresh` just before packing (under the link's send lock) to keep the
    timestamp on the wall clock.  :meth:`check` verifies one raw received frame and says why it is
    refused (``None`` when accepted), :meth:`verify` also says whether its signature verified (a frame let
    through unsigned did not); :attr:`rejected` counts the reasons.  The object must decode with
    its own key unused: :meth:`attach` tells pymavlink to accept everything, :meth:`check` decides.
    """

    def __init__(
        self,
        key: SigningKey,
        *,
        link_id: int = 0,
        allow_unsigned: Collection[int] = GATEWAY_UNSIGNED,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if not isinstance(key, SigningKey):
            raise SigningError("LinkSigning needs a SigningKey")
        if not 0 <= int(link_id) <= 255:
            raise SigningError(f"a signing link id is within 0..255, got {link_id}")
        self.key = key
        self.link_id = int(link_id)
        self.allow_unsigned = frozenset(int(m) for m in allow_unsigned)
        self.clock = clock
        self._mav: Any = None
        self._own_ts = signing_timestamp(clock())
        self._seen_max = 0
        self._streams: dict[tuple[int, int, int], int] = {}
        self.accepted = 0
        self.accepted_unsigned = 0
        self.rejected: collections.Counter[str] = collections.Counter()

    def __repr__(self) -> str:
        return f"LinkSigning(key={self.key!r}, link_id={self.link_id})"

    # -- output ------------------------------------------------------------------------------------
    def attach(self, mav: Any) -> None:
        """Make a pymavlink ``MAVLink`` object sign everything it sends with this key and link id."""
        s = mav.signing
        s.secret_key = self.key.secret
        s.sign_outgoing = True
        s.link_id = self.link_id
        s.timestamp = max(int(s.timestamp or 0), self.timestamp)
        s.allow_unsigned_callback = _accept_all  # pymavlink decodes; check() is the judge
        self._mav = mav
        self.refresh()

    def refresh(self) -> None:
        """Bring the outgoing timestamp up to the wall clock and the newest accepted input (call under the
        send lock, before packing)."""
        now = max(signing_timestamp(self.clock()), self._seen_max)
        mav = self._mav
        if mav is None:
            self._own_ts = max(self._own_ts, now)
        elif mav.signing.timestamp < now:
            mav.signing.timestamp = now

    @property
    def timestamp(self) -> int:
        """Our current timestamp (the next frame we sign carries at least this)."""
        mav = self._mav
        ts = int(mav.signing.timestamp) if mav is not None else self._own_ts
        return max(ts, self._seen_max)

    # -- input ----------------------------------------------------------------------------------------
    def check(self, raw: bytes | bytearray, msgid: int, sysid: int, compid: int) -> str | None:
        """Why the frame ``raw`` must be dropped (``"unsigned"``, ``"bad signature"``, ``"replayed"``,
        ``"stale timestamp"``), or None when it is accepted."""
        return self.verify(raw, msgid, sysid, compid)[0]

    def verify(self, raw: bytes | bytearray, msgid: int, sysid: int, compid: int) -> tuple[str | None, bool]:
        """As :meth:`check`, and whether the frame's signature verified: ``(None, True)`` for a frame
        signed with our key and fresh, ``(None, False)`` for one let through unsigned (``allow_unsigned``:
        take it as data, never as proof of who sent it), ``(reason, False)`` for one to drop."""
        if len(raw) < 12 or raw[0] != _MAGIC_V2 or not raw[2] & _IFLAG_SIGNED:
            return self._unsigned(msgid, "unsigned"), False
        if len(raw) < 12 + SIGNATURE_BYTES:
            return self._unsigned(msgid, "malformed"), False
        digest = hashlib.sha256(self.key.secret + bytes(raw[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(raw[-6:])):
            return self._unsigned(msgid, "bad signature"), False
        link_id = raw[-13]
        ts = int.from_bytes(raw[-12:-6], "little")
        stream = (link_id, sysid, compid)
        last = self._streams.get(stream)
        if last is not None:
            if ts <= last:
                return self._unsigned(msgid, "replayed"), False
        elif ts + NEW_STREAM_WINDOW < self.timestamp:
            return self._unsigned(msgid, "stale timestamp"), False
        self._streams[stream] = ts
        if ts > self._seen_max:
            self._seen_max = ts
        self.accepted += 1
        return None, True

    def _unsigned(self, msgid: int, reason: str) -> str | None:
        if msgid in self.allow_unsigned:
            self.accepted_unsigned += 1
            return None
        self.rejected[reason] += 1
        return reason

    def forget_streams(self) -> None:
        """Forget the streams seen (a reboot: the timestamps seen lived in RAM); ours carries on."""
        self._streams.clear()

    def stream_timestamps(self) -> dict[tuple[int, int, int], int]:
        """Last accepted timestamp per (link id, system id, component id)."""
        return dict(self._streams)


def _accept_all(mav: Any, msgid: int) -> bool:
    return True


def setup_signing(
    conn: Any,
    key: SigningKey,
    *,
    link_id: int = 0,
    allow_unsigned: Collection[int] = GATEWAY_UNSIGNED,
    initial_timestamp: int | None = None,
) -> None:
    """pymavlink's own signing on a ``mavutil`` connection (a user script, a test client): sign
    everything sent, drop unsigned input except ``allow_unsigned``, timestamps from the wall clock."""
    allowed = frozenset(int(m) for m in allow_unsigned)
    conn.setup_signing(
        key.secret,
        sign_outgoing=True,
        allow_unsigned_callback=lambda mav, msgid: msgid in allowed,
        initial_timestamp=signing_timestamp() if initial_timestamp is None else int(initial_timestamp),
        link_id=int(link_id),
    )
