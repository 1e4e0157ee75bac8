"""Shared maps onboard: the rule of `jaxmripp.spec.sharing`, sent as deltas.

A robot's map grows by its own sensing and by the deltas it merges. Per voxel it keeps the
round the voxel was learned in, whether it was merged (and from whom) or sensed, and per
peer the round it last sent that peer a map message. The delta for a peer is then what
the spec says the peer may lack: the voxels sensed after that round, the ones merged in
that round or later, and, at a first contact, the whole map.

One refinement: a voxel merged from the receiver itself is left out. The receiver sent
it, and maps only grow, so it holds it still; without this a pair in steady contact would
send every voxel back to the robot that just sent it, about doubling the traffic. The
receiver ends with the same map as the spec's (the environment's) merge either way.

With the target belief (`windows`) a voxel's window bit travels with it (the delta's
window bits, `jaxmripp.spec.protocol`), and a bit learned after its voxel counts as
learning the voxel again, so the voxel goes out once more with its bit.

Links are taken to be symmetric, as the environment's are: a robot that hears a peer
assumes the peer hears its map message. Where a message is lost, the voxels it carried
reach that peer only once relearned or forwarded by another robot.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from jaxmripp.runtime.messages import MapDelta, MapMessage

OWN = -1  # `source` of a voxel the robot sensed itself


class MapSharing:
    """One robot's bookkeeping of what it learned when, over its `OccupancyMap`."""

    def __init__(self, robot_id: int, occupancy: OccupancyMap, windows: bool = False):
        """windows: the deltas carry window bits (an export with the target belief)."""
        cells = occupancy.size ** 3
        self.id = int(robot_id)
        self.map = occupancy
        self.windows = bool(windows)
        self.learned = np.full(cells, -1, np.int32)  # round the voxel's code was last set
        self.source = np.full(cells, OWN, np.int32)  # the peer it came from, or OWN
        self.last_sent: dict[int, int] = {}  # peer -> round of the last map message to it
        # Voxels a merged delta held otherwise than this map (FREE against OCCUPIED): none
        # while every map is true to the world, as in the simulator.
        self.conflicts = 0
        self._noted = occupancy.codes.copy()  # codes as of the last bookkeeping
        self._noted_windows = occupancy.window.copy()  # window bits, likewise

    def note_sensed(self, round_: int) -> None:
        """Records every voxel whose code (or, with `windows`, window bit) changed since
        the last call as sensed this round (the map was written by the robot's own camera
        or a blocked move)."""
        changed = self.map.codes != self._noted
        if self.windows:
            changed |= self.map.window != self._noted_windows
        changed = np.flatnonzero(changed)
        self.learned[changed] = round_
        self.source[changed] = OWN
        self._noted[changed] = self.map.codes[changed]
        self._noted_windows[changed] = self.map.window[changed]

    def delta(self, peer: int) -> np.ndarray:
        """Flat indices (increasing) of the known voxels `peer` may lack."""
        known = self.map.codes != UNKNOWN
        if peer in self.last_sent:
            since = self.last_sent[peer]
            merged = self.source != OWN
            known &= np.where(merged, self.learned >= since, self.learned > since)
        return np.flatnonzero(known & (self.source != peer))

    def message(self, receivers, round_: int) -> MapMessage:
        """The map message to `receivers` (robots heard this round); they count as
        contacted in `round_` from now on."""
        deltas = []
        for peer in sorted(set(int(r) for r in receivers) - {self.id}):
            voxels = self.delta(peer)
            deltas.append(MapDelta(peer, voxels, self.map.codes[voxels] == OCCUPIED,
                                   self.map.window[voxels] if self.windows else None))
        for delta in deltas:
            self.last_sent[delta.receiver] = round_
        return MapMessage(self.id, self.map.size, tuple(deltas))

    def merge(self, delta: MapDelta, sender: int, round_: int) -> int:
        """Merges a delta from `sender` (`OccupancyMap.merge`: OCCUPIED is never freed, and
        with `windows` its window bits, which mark OCCUPIED voxels only); returns the
        number of voxels whose code or window bit it changed."""
        values = np.where(delta.occupied, OCCUPIED, FREE).astype(np.int8)
        fresh, disagreed = self.map.merge(delta.voxels, values)
        if self.windows and delta.windows is not None:
            # The sender's OCCUPIED voxels are OCCUPIED here after the merge.
            marked = self.map.mark_windows(delta.voxels[delta.windows & delta.occupied])
            fresh = np.union1d(fresh, marked)
            self._noted_windows[fresh] = self.map.window[fresh]
        self.conflicts += disagreed
        self.learned[fresh] = round_
        self.source[fresh] = int(sender)
        self._noted[fresh] = self.map.codes[fresh]
        return len(fresh)
