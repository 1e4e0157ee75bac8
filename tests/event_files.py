"""Reading TensorBoard event files back without TensorBoard or TensorFlow: the TFRecord
framing parsed here, the `Event` messages with tensorboardX's own protobuf classes."""

from __future__ import annotations

import struct
from pathlib import Path

from tensorboardX.proto import event_pb2
from tensorboardX.proto.event_pb2 import SessionLog


def events(path: Path) -> list[event_pb2.Event]:
    """Every event of one file. A TFRecord is a little-endian uint64 length, a uint32
    checksum of it, the data and a uint32 checksum of the data."""
    data, out, at = path.read_bytes(), [], 0
    while at < len(data):
        (length,) = struct.unpack("<Q", data[at:at + 8])
        at += 12
        out.append(event_pb2.Event.FromString(data[at:at + length]))
        at += length + 4
    return out


def scalars(directory: Path) -> dict[tuple[str, int], list[float]]:
    """{(tag, step): values} over the folder's event files in name order, as TensorBoard
    shows them: a session start at step s (a writer's purge step) hides the earlier
    files' events at steps >= s."""
    out: dict[tuple[str, int], list[float]] = {}
    for path in sorted(directory.glob("events.out.tfevents.*")):
        for event in events(path):
            if event.HasField("session_log") and event.session_log.status == SessionLog.START:
                out = {key: values for key, values in out.items() if key[1] < event.step}
            for value in event.summary.value:
                out.setdefault((value.tag, event.step), []).append(value.simple_value)
    return out
