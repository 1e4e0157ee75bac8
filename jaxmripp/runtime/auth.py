"""Authenticated team radio: the tags and sequence numbers of `jaxmripp.spec.protocol`.

A team that shares a secret key signs every message it sends (HMAC-SHA256 over the
message's bytes, its sender id and its sequence number) and takes only messages that
carry a valid tag, each sender's in increasing sequence: a radio without the key can
neither speak for a robot (claim id 0 and go first in every hold, or send map deltas) nor
replay what a robot said before. Without a key nothing is checked, as before keys.
What a team member holding the key can still do is in docs/safety.md.

The standard library's `hmac`, `hashlib` and `os` only: the runtime stays NumPy-only.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os

from jaxmripp.runtime.errors import MessageError, TeamKeyError
from jaxmripp.runtime.messages import Envelope
from jaxmripp.spec.protocol import TAG_CHARS, TAG_DOMAIN, TAG_FIELD, TEAM_KEY_MIN_BYTES

# Why a receiver refused a message: not a valid message, another protocol version, no tag
# (with a key), a tag that does not verify, a sequence number not above the last taken.
REASONS = ("malformed", "version", "unsigned", "forged", "stale")
_PREFIX = b'{"' + TAG_FIELD.encode() + b'":"'


def team_key(seed: int | None = None) -> bytes:
    """A 32-byte team key: from the operating system's random source (seed None: what a
    real team uses, drawn once and loaded onto every robot), or derived from `seed` (a
    simulated team: reproducible, and no secret at all)."""
    if seed is None:
        return os.urandom(32)
    return hashlib.sha256(b"jaxmripp simulated team key\x00" + str(int(seed)).encode()).digest()


def checked_key(key) -> bytes | None:
    """`key` as bytes, or None; anything but bytes of TEAM_KEY_MIN_BYTES or more is
    refused (TeamKeyError)."""
    if key is None:
        return None
    if not isinstance(key, (bytes, bytearray)) or len(key) < TEAM_KEY_MIN_BYTES:
        got = f"{len(key)} bytes" if isinstance(key, (bytes, bytearray)) else \
            type(key).__name__
        raise TeamKeyError(f"team_key: got {got}; allowed: None or bytes of at least "
                           f"{TEAM_KEY_MIN_BYTES} (e.g. jaxmripp.runtime.auth.team_key())")
    return bytes(key)


def tag(key: bytes, sender: int, seq: int, signed: bytes) -> bytes:
    """The tag (base64, TAG_CHARS characters) of the signed bytes of a message."""
    mac = hmac.new(key, TAG_DOMAIN + int(sender).to_bytes(8, "big")
                   + int(seq).to_bytes(8, "big") + signed, hashlib.sha256)
    return base64.b64encode(mac.digest())


def sign(body: bytes, key: bytes, sender: int, seq: int) -> bytes:
    """An encoded message (a JSON object without a tag) with its tag as first member."""
    return _PREFIX + tag(key, sender, seq, body) + b'",' + body[1:]


def split(data: bytes) -> tuple[bytes, bytes] | None:
    """(tag, signed bytes) of a message that starts with a tag member as the protocol
    writes it, else None."""
    head = len(_PREFIX) + TAG_CHARS
    if not data.startswith(_PREFIX) or data[head:head + 2] != b'",':
        return None
    return data[len(_PREFIX):head], b"{" + data[head + 2:]


class RadioAuth:
    """One robot's side of the team radio: its sequence numbers, the last one it took
    from each sender, and how many messages it refused, by reason (`rejected`)."""

    def __init__(self, key: bytes | None, robot_id: int):
        self.key = checked_key(key)
        self.id = int(robot_id)
        self.sequence = 0  # the last one sent
        self.accepted: dict[int, int] = {}  # sender -> the last seq taken from it
        self.rejected = dict.fromkeys(REASONS, 0)  # counted by the planner's receptions

    def next_sequence(self) -> int:
        self.sequence += 1
        return self.sequence

    def seal(self, body: bytes, seq: int) -> bytes:
        """The message to broadcast: signed with the team key, or as encoded."""
        return body if self.key is None else sign(body, self.key, self.id, seq)

    def object_allowed(self, kind: str) -> None:
        """A decoded message object carries no tag: with a key only bytes are taken."""
        if self.key is not None:
            raise MessageError(f"{kind}: this team signs its radio; pass the "
                                          "message's bytes as received (an object has no tag)", "unsigned")

    def check(self, envelope: Envelope) -> None:
        """With a key: refuses (MessageError with its `reason`) an unsigned, forged,
        replayed or out-of-order message. Nothing is recorded: `accept` does that."""
        if self.key is None:
            return
        where = f"radio message from robot {envelope.sender} (seq {envelope.seq})"
        if TAG_FIELD not in envelope.record:
            raise MessageError(f"{where} is not signed; this team signs every message "
                               "with its key", "unsigned")
        parts = split(envelope.data)
        if parts is None:
            raise MessageError(f"{where}: its tag is malformed or not the first member",
                               "forged")
        given, signed = parts
        if not hmac.compare_digest(given, tag(self.key, envelope.sender, envelope.seq,
                                              signed)):
            raise MessageError(f"{where}: its tag does not verify with this team's key "
                               "(forged, altered, or signed with another key)", "forged")
        last = self.accepted.get(envelope.sender)
        if last is not None and envelope.seq <= last:
            raise MessageError(f"{where}: seq {last} was already taken from it (a "
                               "replayed or out-of-order message)", "stale")

    def accept(self, envelope: Envelope) -> None:
        """Records a message taken: the sender's later messages must have a larger seq."""
        if self.key is not None:
            self.accepted[envelope.sender] = envelope.seq
