"""Shared maps: what robots in radio range tell each other about the world.

With `radio.share_maps` (the default world's setting; the paper's robots share only their
waypoints), a robot's map holds what it and its team have seen, as far as the radio
carried it:

- Each round, after sensing, every robot's map is merged with the maps of the robots it
  hears (single hop: each neighbour's map as it stood after the neighbour's own sensing
  this round; with `radio.relay`: every map in its connected component, in the same
  round). The merge rule, per voxel: UNKNOWN in the receiver's map takes the sender's
  code; FREE becomes OCCUPIED where the sender holds it OCCUPIED; OCCUPIED stays, whatever
  the sender holds. So no message ever frees a voxel: one the receiver mapped OCCUPIED
  (seen itself, or heard) stays OCCUPIED, and OCCUPIED from any peer wins over FREE.
  Building tops (`jaxmripp.spec.view`) merge by maximum.
- In the simulator maps copy codes from the truth, so senders never disagree and the rule
  is the union of what the robots know (`jaxmripp.sim.maps.merge`). Onboard, maps come
  from real sensors (depth images: `jaxmripp.runtime.depth`) and from peers, which may
  disagree or lie; the runtime applies the rule in full (`OccupancyMap.merge`) and counts
  the voxels where a merged delta disagreed (`MapSharing.conflicts`). The parity tests
  check that the count stays 0 in the simulator's worlds, where the two sides' merges
  must agree voxel for voxel.
- The merged map is what the robot's candidates (the known-free flight rule), its view
  gain features and everything after this round read.

On the wire (`jaxmripp.spec.protocol`, message type MAP_MESSAGE_TYPE) a robot sends each
robot it heard this round only the voxels it learned since their last contact: the ones
it sensed after sending its previous map message to that robot, and the ones it merged in
at that contact or later (the receiver already has everything else of the sender's map,
since it merged it then); voxels it merged in from that same robot are left out too (the
receiver sent them and maps only grow). Where the maps agree (always, in the simulator),
merging a delta is merging the sender's map: the receiver ends with the same map as the
environment's merge. The JAX environment merges whole maps
(`jaxmripp.sim.comms.share_maps`); the runtime exchanges deltas
(`jaxmripp.runtime.sharing`); a parity test keeps the two equal on random episodes.
"""
