"""One robot's GP feeding, in NumPy: the rule written in `jaxmripp.spec.feeding`.

The rule (own pending pose first, then R = N - 1 + catchup_rounds peer rounds taking the oldest pending pose of the peer with the largest backlog, ties to the
nearest offset) is stated once, in that module; this is its single-robot implementation, as
`jaxmripp.sim.feeding.feed_gps` is its JAX one. The histories themselves stay with
the planner (they are also what its radio sends); this class only remembers how much of
each has gone into the GPs.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from jaxmripp.runtime.gp import GaussianProcess
from jaxmripp.spec.feeding import COMM_VALUE, OWN_PER_ROUND, peer_rounds

F32 = np.float32


def peer_order(robot_id: int, team_size: int) -> list[int]:
    """Peers ranked by offset (i + 1) mod N, (i + 2) mod N, ...: the tie order."""
    return [(robot_id + offset) % team_size for offset in range(1, team_size)]


class FeedSchedule:
    """How many entries of each history robot `robot_id` has fed into its GPs."""

    def __init__(self, robot_id: int, team_size: int, catchup_rounds: int):
        self.order = peer_order(robot_id, team_size)
        self.rounds = peer_rounds(team_size, catchup_rounds)
        self.own_fed = 0
        self.peer_fed: dict[int, int] = {j: 0 for j in self.order}

    def feed(self, utility_gp: GaussianProcess, comm_gp: GaussianProcess,
             own_poses: Sequence[np.ndarray], own_values: Sequence[np.float32],
             peer_poses: Mapping[int, Sequence[np.ndarray]],
             peer_values: Mapping[int, Sequence[np.float32]]) -> None:
        """One round of the rule: own pending pose(s), then the fixed peer rounds."""
        for _ in range(OWN_PER_ROUND):
            if self.own_fed < len(own_poses):
                utility_gp.add(own_poses[self.own_fed], own_values[self.own_fed])
                self.own_fed += 1
        for _ in range(self.rounds):
            j = self._largest_backlog(peer_values)
            index = self.peer_fed[j]
            if index < len(peer_values[j]):
                utility_gp.add(peer_poses[j][index], peer_values[j][index])
                comm_gp.add(peer_poses[j][index], F32(COMM_VALUE))
                self.peer_fed[j] = index + 1

    def _largest_backlog(self, peer_values: Mapping[int, Sequence]) -> int:
        # max() keeps the first maximum in `order`, as argmax does over the env's offsets.
        return max(self.order, key=lambda peer: len(peer_values[peer]) - self.peer_fed[peer])
