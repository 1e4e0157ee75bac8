"""The radio message formats: type tags, version and size limit.

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

Map message (with `radio.share_maps`; what it carries is the rule of
`jaxmripp.spec.sharing`). After the first broadcast of a round a robot broadcasts one
record holding, for every robot it heard in that broadcast, the voxels of its map that
robot may lack (the delta since their last contact):
    {"type": MAP_MESSAGE_TYPE, "protocol": PROTOCOL_VERSION, "sender": 2, "size": G,
     "deltas": [{"receiver": 0, "count": n, "voxels": V, "occupied": O}, ...]}
size is the sender's G (a receiver with another G refuses the message). voxels is a bit
mask over the G^3 voxels in flat C order (index (x G + y) G + z), bit k set when voxel k
is in the delta; occupied has one bit per voxel of the delta, in increasing flat index,
set when the sender maps it OCCUPIED and clear when FREE (UNKNOWN voxels are never in a
delta). Both masks are packed eight bits to a byte, the first bit in the most significant
position and the last byte padded with zero bits (G^3 / 8 and n / 8 bytes, rounded up),
then zlib-compressed and written as standard padded base64. count is n, the number of
bits set in voxels. At most one entry per receiver; a robot reads the entry addressed to
it and ignores the others. A receiver refuses, changing nothing, a record whose masks do
not decode to exactly those lengths, whose padding bits are set, whose count disagrees
with the mask, or whose receivers repeat.

Every message carries the version; a receiver refuses any other version, whatever the
type. Version history: 1 -- waypoints and position; 2 -- adds budget_left and intent;
3 -- adds the map message.
"""

PROTOCOL_VERSION = 3
MESSAGE_TYPE = "jaxmripp.waypoints"
MAP_MESSAGE_TYPE = "jaxmripp.map"
MAX_BYTES = 1 << 20  # a history of thousands of poses, or a whole map at G = 100, fits
