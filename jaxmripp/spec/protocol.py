"""The radio message format: its type tag, version and size limit.

A robot broadcasts what the paper's single-hop radio exchanges: its own visited waypoints
(poses, in order, with the normalised number of windows seen from each) and its current
position, plus what the safe-flight rules of `jaxmripp.spec.flight` need: its remaining
budget (the `budget` priority) and, in the second broadcast of a round, its intent -- the
target of the flight it has chosen. Histories only grow, so a message carries them from
some index `start` on and a receiver appends what it does not have yet.

Wire format (UTF-8 JSON object):
    {"type": MESSAGE_TYPE, "protocol": PROTOCOL_VERSION, "sender": 2,
     "position": [x, y, z], "heading": 1, "start": 0,
     "poses": [[x, y, z, angle], ...], "utilities": [u, ...],
     "budget_left": b, "intent": null | [x, y, z]}
budget_left is the sender's remaining budget (float32, >= 0). intent is null in the first
broadcast of a round and when the sender hovers; otherwise the target position of its
chosen flight, which starts at `position` (the intent broadcast may carry no poses).
Floats are float32 values written as the shortest decimal that reads back to the same
double, so a pose survives the round trip bit for bit. A receiver refuses any other
protocol version and malformed records. `jaxmripp.runtime.messages` encodes and decodes.

Version history: 1 -- waypoints and position; 2 -- adds budget_left and intent.
"""

PROTOCOL_VERSION = 2
MESSAGE_TYPE = "jaxmripp.waypoints"
MAX_BYTES = 1 << 20  # a history of thousands of poses is still far below this
