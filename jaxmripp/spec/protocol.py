"""The radio message formats: type tags, version, size limit and authentication.

A robot broadcasts what the paper's single-hop radio exchanges: its own visited waypoints
(poses, in order, with the normalised number of windows seen from each) and its current
position, its remaining budget and, for the safe-flight rules of `jaxmripp.spec.flight`,
in the second broadcast of a round its intent -- the target of the flight it has chosen.
Histories only grow, so a message carries them from some index `start` on and a receiver
appends what it does not have yet.

Wire format (UTF-8 JSON object):
    {"type": MESSAGE_TYPE, "protocol": PROTOCOL_VERSION, "sender": 2, "seq": 17,
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
    {"type": MAP_MESSAGE_TYPE, "protocol": PROTOCOL_VERSION, "sender": 2, "seq": 18,
     "size": G, "deltas": [{"receiver": 0, "count": n, "voxels": V, "occupied": O}, ...]}
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

Windows (an export with the target belief, `policy.belief_features`; the rule is
`jaxmripp.spec.belief`). Each delta then also holds
    "windows": W
one bit per OCCUPIED voxel of the delta (the set bits of `occupied`, in increasing flat
index), set when the sender knows that voxel to be a window -- its own classifier's or a
peer's report, merged with the map as the voxel's code is. W is packed, compressed and
written as the masks above. A voxel whose window bit the sender learned after sending
the voxel itself travels again in the next delta, so the windows a receiver knows are
those of the map it merged. A receiver whose export has the belief refuses a delta
without the field, one whose export has none refuses a delta with it (a team flies one
export), and a mask of another length or with padding bits set is refused as above.

Numbers, for every type: integers are written with at most MAX_INT_DIGITS digits; NaN,
Infinity and decimals beyond the double range are refused, and so is any float field
whose value is not a finite float32.

Sequence and authentication, for every type. seq is the sender's sequence number, an
integer 0 <= seq <= MAX_SEQUENCE that grows with every message the sender sends, whatever
its type (a receiver may miss some: gaps are allowed). A team that shares a secret key
(TEAM_KEY_MIN_BYTES bytes or more) signs every message: the record then starts with a tag
member, written exactly as
    {"tag":"<TAG_CHARS characters>",<the rest of the record>
and the signed bytes are the message without that member: "{" followed by everything
after the comma that ends it. The tag is the standard padded base64 of
    HMAC-SHA256(key, TAG_DOMAIN + sender (8 bytes, big-endian) + seq (8 bytes, big-endian)
                     + signed bytes),
so it covers the message's bytes, the sender id and the sequence number. A receiver that
holds the key refuses, and counts, a message without a tag (unsigned), one whose tag is
malformed, misplaced or does not verify (forged), and one whose seq is not above the
last seq it accepted from that sender (replayed or out of order). A receiver without a
key reads tag and seq but checks neither. `jaxmripp.runtime.auth` signs and verifies.

Every message carries the version; a receiver refuses any other version, whatever the
type. Version history: 1 -- waypoints and position; 2 -- adds budget_left and intent;
3 -- adds the map message; 4 -- adds seq and the tag of a team with a key; 5 -- adds the
window bits of the map deltas (with the target belief).
"""

PROTOCOL_VERSION = 5
MESSAGE_TYPE = "jaxmripp.waypoints"
MAP_MESSAGE_TYPE = "jaxmripp.map"
MAX_BYTES = 1 << 20  # a history of thousands of poses, or a whole map at G = 100, fits
MAX_INT_DIGITS = 19  # every id, count, index and seq is below 10^19
MAX_SEQUENCE = (1 << 63) - 1
TAG_FIELD = "tag"
TAG_CHARS = 44  # base64 of the 32 bytes of HMAC-SHA256
TAG_DOMAIN = b"jaxmripp.radio\x00"  # keeps these tags apart from any other use of the key
TEAM_KEY_MIN_BYTES = 16
