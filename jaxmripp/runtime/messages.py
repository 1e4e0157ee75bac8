"""Radio messages between robots: encoding and validation of the formats that
`jaxmripp.spec.protocol` defines (type tags, version, numbers, fields, map masks).

Receiving is total: whatever bytes or text arrive, `parse` and the field checks either
return a valid message or raise `ProtocolVersionError` (naming both versions) or
`MessageError`, with one-line messages. `parse` reads the envelope (type, version,
sender, seq) that authentication (`jaxmripp.runtime.auth`) needs before the fields are
checked; `decode` and `decode_map` do both.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import math
import zlib

import numpy as np

from jaxmripp.runtime.errors import MessageError, ProtocolVersionError
from jaxmripp.spec.grid import N_HEADINGS
from jaxmripp.spec.protocol import (MAP_MESSAGE_TYPE, MAX_BYTES, MAX_INT_DIGITS, MAX_SEQUENCE,
                                    MESSAGE_TYPE, PROTOCOL_VERSION)

F32_MAX = float(np.finfo(np.float32).max)


@dataclasses.dataclass(frozen=True)
class Message:
    sender: int
    position: np.ndarray  # (3,) float32 current position
    heading: int  # current heading index
    start: int  # index of poses[0] in the sender's history
    poses: np.ndarray  # (K, 4) float32 history poses (x, y, z, heading angle)
    utilities: np.ndarray  # (K,) float32 windows seen from each pose / utility_norm
    budget_left: float  # float32, the sender's remaining budget
    intent: np.ndarray | None = None  # (3,) float32 target of the chosen flight, or None
    protocol: int = PROTOCOL_VERSION
    seq: int = 0  # the sender's sequence number

    @property
    def end(self) -> int:
        """History length the message brings its receiver up to."""
        return self.start + len(self.utilities)


@dataclasses.dataclass(frozen=True)
class Envelope:
    """One received message, parsed but its fields not yet checked."""

    data: bytes  # the message as received, UTF-8
    record: dict  # its JSON object
    sender: int
    seq: int


def _floats(values) -> list:
    return [float(v) for v in np.asarray(values, np.float32).reshape(-1)]


def _dumps(record: dict) -> bytes:
    return json.dumps(record, separators=(",", ":"), allow_nan=False).encode()


def encode(message: Message) -> bytes:
    poses = np.asarray(message.poses, np.float32).reshape(-1, 4)
    return _dumps({
        "type": MESSAGE_TYPE,
        "protocol": int(message.protocol),
        "sender": int(message.sender),
        "seq": int(message.seq),
        "position": _floats(message.position),
        "heading": int(message.heading),
        "start": int(message.start),
        "poses": [_floats(p) for p in poses],
        "utilities": _floats(message.utilities),
        "budget_left": float(np.float32(message.budget_left)),
        "intent": None if message.intent is None else _floats(message.intent),
    })


def decode(data: bytes | str) -> Message:
    """Parses and validates one message; raises MessageError / ProtocolVersionError."""
    return read_message(parse(data, MESSAGE_TYPE))


def read_message(envelope: Envelope) -> Message:
    """The waypoint (or intent) message in a parsed envelope, its fields checked."""
    record, sender = envelope.record, envelope.sender
    where = f"radio message from robot {sender}"
    position = _vector(record.get("position"), 3, f"{where}: position")
    heading = record.get("heading")
    if not _is_int(heading) or not 0 <= heading < N_HEADINGS:
        raise MessageError(f"{where}: heading {_shown(heading)} is not in "
                           f"0..{N_HEADINGS - 1}")
    start = record.get("start")
    if not _is_int(start) or start < 0:
        raise MessageError(f"{where}: start {_shown(start)} is not a non-negative integer")
    raw_poses, raw_utilities = record.get("poses"), record.get("utilities")
    if not isinstance(raw_poses, list) or not isinstance(raw_utilities, list) \
            or len(raw_poses) != len(raw_utilities):
        raise MessageError(f"{where}: poses and utilities must be lists of equal length")
    poses = np.asarray([_vector(p, 4, f"{where}: pose {start + k}")
                        for k, p in enumerate(raw_poses)], np.float32).reshape(-1, 4)
    utilities = _vector(raw_utilities, len(raw_utilities), f"{where}: utilities")
    if np.any(utilities < 0):
        raise MessageError(f"{where}: utilities must be non-negative")
    budget_left = record.get("budget_left")
    if not _is_float32(budget_left) or budget_left < 0:
        raise MessageError(f"{where}: budget_left {_shown(budget_left)} is not a "
                           "non-negative float32 number")
    raw_intent = record.get("intent", "missing")
    intent = None if raw_intent is None else _vector(raw_intent, 3, f"{where}: intent")
    if not (np.all(inside(position)) and np.all(inside(poses[:, :3]))
            and (intent is None or inside(intent))):
        raise MessageError(f"{where}: a position lies outside the unit cube")
    return Message(sender, position, heading, start, poses, utilities,
                   np.float32(budget_left), intent, record["protocol"], envelope.seq)


def parse(data: bytes | str, kind: str) -> Envelope:
    """The envelope of one message of type `kind`: its record (JSON, by the number rules
    of `jaxmripp.spec.protocol`), version checked, sender and seq."""
    raw = _utf8(data)
    try:
        record = json.loads(raw.decode("utf-8"), parse_int=_int, parse_float=_float,
                            parse_constant=_constant)
    except MessageError:
        raise
    except RecursionError:
        raise MessageError("radio message is nested too deeply") from None
    except json.JSONDecodeError as err:
        raise MessageError(f"radio message is not valid JSON ({err.msg} at {err.pos})") from None
    except ValueError as err:  # what else the parser may meet (a bad escape, ...)
        raise MessageError(f"radio message is not valid JSON ({err})") from None
    if not isinstance(record, dict) or record.get("type") != kind:
        raise MessageError(f"radio message is not a {kind} record")
    protocol = record.get("protocol")
    if not _is_int(protocol) or protocol < 1:
        raise MessageError(f"radio message has no valid protocol version ({_shown(protocol)})")
    sender = record.get("sender")
    if protocol != PROTOCOL_VERSION:
        update = "this robot" if protocol > PROTOCOL_VERSION else f"robot {_shown(sender)}"
        raise ProtocolVersionError(
            f"radio message from robot {_shown(sender)} uses protocol {protocol}; this "
            f"runtime speaks protocol {PROTOCOL_VERSION} only (update the runtime on "
            f"{update})")
    if not _is_int(sender) or sender < 0:
        raise MessageError(f"radio message has an invalid sender id ({_shown(sender)})")
    seq = record.get("seq")
    if not _is_int(seq) or not 0 <= seq <= MAX_SEQUENCE:
        raise MessageError(f"radio message from robot {sender}: seq {_shown(seq)} is not "
                           f"an integer 0 .. 2^63 - 1")
    return Envelope(raw, record, sender, seq)


def _utf8(data) -> bytes:
    """The message's bytes: bytes as they are, text as its UTF-8; at most MAX_BYTES."""
    if isinstance(data, str):
        if len(data) > MAX_BYTES:  # every character is at least one byte
            raise MessageError(f"radio message of {len(data)} characters exceeds "
                               f"{MAX_BYTES} bytes")
        try:
            data = data.encode("utf-8")
        except UnicodeEncodeError:
            raise MessageError("radio message text cannot be written as UTF-8") from None
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(f"radio message must be bytes or str, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > MAX_BYTES:
        raise MessageError(f"radio message of {len(data)} bytes exceeds {MAX_BYTES}")
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        raise MessageError("radio message is not UTF-8 text") from None
    return data


def _int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise MessageError(f"radio message holds an integer of {len(text.lstrip('-'))} "
                           f"digits; at most {MAX_INT_DIGITS} are allowed")
    return int(text)


def _float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise MessageError(f"radio message holds a number beyond the double range "
                           f"({_shown(text)})")
    return value


def _constant(name: str):
    raise MessageError(f"radio message holds {name}; only finite numbers are allowed")


def _shown(value) -> str:
    """A value for an error message: numbers and short text as written, else its kind
    (a message may hold anything, nested deep or a megabyte long)."""
    if value is None or isinstance(value, (bool, int, float)):
        return repr(value)
    if isinstance(value, str):
        return repr(value) if len(value) <= 40 else repr(value[:37]) + "..."
    return f"a {type(value).__name__}"


def inside(positions: np.ndarray) -> np.ndarray:
    return np.all((positions >= 0.0) & (positions <= 1.0), axis=-1)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_float32(value) -> bool:
    """A JSON number whose float32 is finite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value) and abs(value) <= F32_MAX


def _vector(value, length: int, name: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != length \
            or not all(_is_float32(v) for v in value):
        raise MessageError(f"{name} must be a list of {length} finite float32 numbers")
    return np.asarray(value, np.float32)

# ---------------------------------------------------------------------------------------
# The map message


@dataclasses.dataclass(frozen=True)
class MapDelta:
    """The voxels one receiver may lack (`jaxmripp.spec.sharing`)."""

    receiver: int
    voxels: np.ndarray  # (n,) int64 flat voxel indices, increasing
    occupied: np.ndarray  # (n,) bool: OCCUPIED, else FREE
    # (n,) bool: a known window (OCCUPIED voxels only), or None where the team's export has
    # no target belief (`jaxmripp.spec.protocol`: the delta then has no windows field)
    windows: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class MapMessage:
    sender: int
    size: int  # G of the sender's map
    deltas: tuple[MapDelta, ...]
    protocol: int = PROTOCOL_VERSION
    seq: int = 0  # the sender's sequence number

    def delta_for(self, receiver: int) -> MapDelta | None:
        return next((d for d in self.deltas if d.receiver == receiver), None)


def encode_map(message: MapMessage) -> bytes:
    cells = int(message.size) ** 3
    deltas = []
    for delta in message.deltas:
        voxels = np.asarray(delta.voxels, np.int64).reshape(-1)
        order = np.argsort(voxels, kind="stable")
        mask = np.zeros(cells, bool)
        mask[voxels] = True
        occupied = np.asarray(delta.occupied, bool).reshape(-1)[order]
        entry = {
            "receiver": int(delta.receiver),
            "count": int(len(voxels)),
            "voxels": _pack(mask),
            "occupied": _pack(occupied),
        }
        if delta.windows is not None:  # one bit per OCCUPIED voxel, in flat order
            entry["windows"] = _pack(np.asarray(delta.windows, bool).reshape(-1)[order][occupied])
        deltas.append(entry)
    return _dumps({"type": MAP_MESSAGE_TYPE, "protocol": int(message.protocol),
                   "sender": int(message.sender), "seq": int(message.seq),
                   "size": int(message.size), "deltas": deltas})


def decode_map(data: bytes | str, size: int, windows: bool = False) -> MapMessage:
    """Parses and validates one map message for a receiver whose map has G = `size` (and,
    with `windows`, whose export has the target belief: every delta holds window bits);
    raises MessageError / ProtocolVersionError."""
    return read_map(parse(data, MAP_MESSAGE_TYPE), size, windows)


def read_map(envelope: Envelope, size: int, windows: bool = False) -> MapMessage:
    """The map message in a parsed envelope, its fields checked against G = `size` and
    whether the receiver reads window bits (`windows`, `jaxmripp.spec.protocol`)."""
    record, sender = envelope.record, envelope.sender
    where = f"map message from robot {sender}"
    if not _is_int(record.get("size")) or record.get("size") != size:
        raise MessageError(f"{where}: its map has size {_shown(record.get('size'))}, this "
                           f"robot's {size}")
    raw = record.get("deltas")
    if not isinstance(raw, list) or not all(isinstance(d, dict) for d in raw):
        raise MessageError(f"{where}: deltas must be a list of records")
    deltas, seen = [], set()
    for entry in raw:
        receiver, count = entry.get("receiver"), entry.get("count")
        if not _is_int(receiver) or receiver < 0 or receiver in seen:
            raise MessageError(f"{where}: receiver {_shown(receiver)} is not a robot id, or "
                               "repeats one")
        seen.add(receiver)
        name = f"{where}: delta for robot {receiver}"
        if not _is_int(count) or not 0 <= count <= size ** 3:
            raise MessageError(f"{name}: count {_shown(count)} is not a voxel count")
        mask = _unpack(entry.get("voxels"), size ** 3, f"{name}: voxels")
        voxels = np.flatnonzero(mask)
        if len(voxels) != count:
            raise MessageError(f"{name}: the mask holds {len(voxels)} voxels, count says "
                               f"{count}")
        occupied = _unpack(entry.get("occupied"), count, f"{name}: occupied")
        deltas.append(MapDelta(receiver, voxels.astype(np.int64), occupied,
                               _windows(entry, occupied, windows, name)))
    return MapMessage(sender, size, tuple(deltas), record["protocol"], envelope.seq)


def _windows(entry: dict, occupied: np.ndarray, expected: bool, name: str
             ) -> np.ndarray | None:
    """A delta's window bits over its voxels (n,) bool, or None for a receiver without the
    target belief; the field must be present exactly when the receiver reads it."""
    if ("windows" in entry) != expected:
        held = "holds" if "windows" in entry else "has no"
        wanted = "reads them" if expected else "has no target belief"
        raise MessageError(f"{name} {held} window bits; this robot's export {wanted} "
                           "(policy.belief_features; a team flies one export)")
    if not expected:
        return None
    bits = np.zeros(len(occupied), bool)
    bits[occupied] = _unpack(entry["windows"], int(occupied.sum()), f"{name}: windows")
    return bits


def _pack(bits: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(np.packbits(bits).tobytes(), 9)).decode("ascii")


def _unpack(text, bits: int, name: str) -> np.ndarray:
    """(bits,) bool from a packed, compressed, base64 mask of exactly that many bits."""
    if not isinstance(text, str):
        raise MessageError(f"{name} must be a base64 string")
    try:
        raw = base64.b64decode(text.encode("ascii"), validate=True)
    except (UnicodeEncodeError, binascii.Error, ValueError):
        raise MessageError(f"{name} is not valid base64") from None
    expected = (bits + 7) // 8
    inflate = zlib.decompressobj()
    try:
        # Never inflates past what a valid mask holds: a crafted stream cannot balloon.
        packed = inflate.decompress(raw, expected + 1)
    except zlib.error:
        raise MessageError(f"{name} is not a zlib stream") from None
    if len(packed) != expected or not inflate.eof or inflate.unused_data:
        raise MessageError(f"{name} does not hold exactly {expected} bytes of mask")
    mask = np.unpackbits(np.frombuffer(packed, np.uint8))
    if mask[bits:].any():
        raise MessageError(f"{name}: padding bits are set")
    return mask[:bits].astype(bool)
