"""Radio messages between robots: encoding and validation of the formats that
`jaxmripp.spec.protocol` defines (type tags, version, fields, float rule, map masks).

Receivers refuse any other protocol version (`ProtocolVersionError`, naming both
versions) and malformed records (`MessageError`), with one-line messages.
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
from jaxmripp.spec.protocol import MAP_MESSAGE_TYPE, MAX_BYTES, MESSAGE_TYPE, PROTOCOL_VERSION


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

    @property
    def end(self) -> int:
        """History length the message brings its receiver up to."""
        return self.start + len(self.utilities)


def _floats(values) -> list:
    return [float(v) for v in np.asarray(values, np.float32).reshape(-1)]


def encode(message: Message) -> bytes:
    poses = np.asarray(message.poses, np.float32).reshape(-1, 4)
    record = {
        "type": MESSAGE_TYPE,
        "protocol": int(message.protocol),
        "sender": int(message.sender),
        "position": _floats(message.position),
        "heading": int(message.heading),
        "start": int(message.start),
        "poses": [_floats(p) for p in poses],
        "utilities": _floats(message.utilities),
        "budget_left": float(np.float32(message.budget_left)),
        "intent": None if message.intent is None else _floats(message.intent),
    }
    return json.dumps(record, separators=(",", ":"), allow_nan=False).encode()


def decode(data: bytes | str) -> Message:
    """Parses and validates one message; raises MessageError / ProtocolVersionError."""
    record, sender = _record(data, MESSAGE_TYPE)
    protocol = record["protocol"]
    where = f"radio message from robot {sender}"
    position = _vector(record.get("position"), 3, f"{where}: position")
    heading = record.get("heading")
    if not _is_int(heading) or not 0 <= heading < N_HEADINGS:
        raise MessageError(f"{where}: heading {heading!r} is not in 0..{N_HEADINGS - 1}")
    start = record.get("start")
    if not _is_int(start) or start < 0:
        raise MessageError(f"{where}: start {start!r} is not a non-negative integer")
    raw_poses, raw_utilities = record.get("poses"), record.get("utilities")
    if not isinstance(raw_poses, list) or not isinstance(raw_utilities, list) \
            or len(raw_poses) != len(raw_utilities):
        raise MessageError(f"{where}: poses and utilities must be lists of equal length")
    poses = np.asarray([_vector(p, 4, f"{where}: pose {start + i}")
                        for i, p in enumerate(raw_poses)], np.float32).reshape(-1, 4)
    utilities = _vector(raw_utilities, len(raw_utilities), f"{where}: utilities")
    if np.any(utilities < 0):
        raise MessageError(f"{where}: utilities must be non-negative")
    budget_left = record.get("budget_left")
    if isinstance(budget_left, bool) or not isinstance(budget_left, (int, float)) \
            or not math.isfinite(budget_left) or budget_left < 0:
        raise MessageError(f"{where}: budget_left {budget_left!r} is not a non-negative "
                           "number")
    raw_intent = record.get("intent", "missing")
    intent = None if raw_intent is None else _vector(raw_intent, 3, f"{where}: intent")
    if not (np.all(inside(position)) and np.all(inside(poses[:, :3]))
            and (intent is None or inside(intent))):
        raise MessageError(f"{where}: a position lies outside the unit cube")
    return Message(sender, position, heading, start, poses, utilities,
                   np.float32(budget_left), intent, protocol)


def _record(data: bytes | str, kind: str) -> tuple[dict, int]:
    """The JSON record of one message of type `kind`, its version checked, and its sender."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        if len(data) > MAX_BYTES:
            raise MessageError(f"radio message of {len(data)} bytes exceeds {MAX_BYTES}")
        try:
            data = bytes(data).decode("utf-8")
        except UnicodeDecodeError:
            raise MessageError("radio message is not UTF-8 text") from None
    if not isinstance(data, str):
        raise MessageError(f"radio message must be bytes or str, got {type(data).__name__}")
    try:
        record = json.loads(data)
    except json.JSONDecodeError as err:
        raise MessageError(f"radio message is not valid JSON ({err.msg} at {err.pos})") from None
    except RecursionError:
        raise MessageError("radio message is nested too deeply") from None
    if not isinstance(record, dict) or record.get("type") != kind:
        raise MessageError(f"radio message is not a {kind} record")
    protocol = record.get("protocol")
    if not _is_int(protocol) or protocol < 1:
        raise MessageError(f"radio message has no valid protocol version ({protocol!r})")
    sender = record.get("sender")
    if protocol != PROTOCOL_VERSION:
        update = "this robot" if protocol > PROTOCOL_VERSION else f"robot {sender!r}"
        raise ProtocolVersionError(
            f"radio message from robot {sender!r} uses protocol {protocol}; this runtime "
            f"speaks protocol {PROTOCOL_VERSION} only (update the runtime on {update})")
    if not _is_int(sender) or sender < 0:
        raise MessageError(f"radio message has an invalid sender id ({sender!r})")
    return record, sender


def inside(positions: np.ndarray) -> np.ndarray:
    return np.all((positions >= 0.0) & (positions <= 1.0), axis=-1)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _vector(value, length: int, name: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != length or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            for v in value):
        raise MessageError(f"{name} must be a list of {length} finite numbers")
    return np.asarray(value, np.float32)


# ---------------------------------------------------------------------------------------
# The map message


@dataclasses.dataclass(frozen=True)
class MapDelta:
    """The voxels one receiver may lack (`jaxmripp.spec.sharing`)."""

    receiver: int
    voxels: np.ndarray  # (n,) int64 flat voxel indices, increasing
    occupied: np.ndarray  # (n,) bool: OCCUPIED, else FREE


@dataclasses.dataclass(frozen=True)
class MapMessage:
    sender: int
    size: int  # G of the sender's map
    deltas: tuple[MapDelta, ...]
    protocol: int = PROTOCOL_VERSION

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
        deltas.append({
            "receiver": int(delta.receiver),
            "count": int(len(voxels)),
            "voxels": _pack(mask),
            "occupied": _pack(np.asarray(delta.occupied, bool).reshape(-1)[order]),
        })
    record = {"type": MAP_MESSAGE_TYPE, "protocol": int(message.protocol),
              "sender": int(message.sender), "size": int(message.size), "deltas": deltas}
    return json.dumps(record, separators=(",", ":")).encode()


def decode_map(data: bytes | str, size: int) -> MapMessage:
    """Parses and validates one map message for a receiver whose map has G = `size`;
    raises MessageError / ProtocolVersionError."""
    record, sender = _record(data, MAP_MESSAGE_TYPE)
    where = f"map message from robot {sender}"
    if record.get("size") != size or not _is_int(record.get("size")):
        raise MessageError(f"{where}: its map has size {record.get('size')!r}, this robot's "
                           f"{size}")
    raw = record.get("deltas")
    if not isinstance(raw, list) or not all(isinstance(d, dict) for d in raw):
        raise MessageError(f"{where}: deltas must be a list of records")
    deltas, seen = [], set()
    for entry in raw:
        receiver, count = entry.get("receiver"), entry.get("count")
        if not _is_int(receiver) or receiver < 0 or receiver in seen:
            raise MessageError(f"{where}: receiver {receiver!r} is not a robot id, or "
                               "repeats one")
        seen.add(receiver)
        name = f"{where}: delta for robot {receiver}"
        if not _is_int(count) or not 0 <= count <= size ** 3:
            raise MessageError(f"{name}: count {count!r} is not a voxel count")
        mask = _unpack(entry.get("voxels"), size ** 3, f"{name}: voxels")
        voxels = np.flatnonzero(mask)
        if len(voxels) != count:
            raise MessageError(f"{name}: the mask holds {len(voxels)} voxels, count says "
                               f"{count}")
        occupied = _unpack(entry.get("occupied"), count, f"{name}: occupied")
        deltas.append(MapDelta(receiver, voxels.astype(np.int64), occupied))
    return MapMessage(sender, size, tuple(deltas), record["protocol"])


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
