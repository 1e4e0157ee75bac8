"""The GP feeding rule: which poses enter a robot's two GPs, and in which order.

This is the one written statement of the rule. The JAX env
(`jaxmripp.sim.feeding.feed_gps`, all robots at once with fixed shapes) and the onboard
runtime (`jaxmripp.runtime.feeding`, one robot with plain lists) implement it in
different forms; they must agree on what enters which GP in which order, because a GP's
posterior depends on its points' order (a full GP evicts first in, first out, and float32
rounding follows the order of the updates).

Every robot keeps two GPs over poses (x, y, z, heading angle): the utility GP (targets:
windows seen from a pose / reward.utility_norm) and the communication GP (targets: the
constant COMM_VALUE at every pose a peer reported, so its mean says "a peer has been
here"). Robot i knows the first know[i, j] entries of robot j's history of visited poses
(its own by visiting, a peer's by radio) and has fed the first fed[i, j] of them; an entry
is pending while fed[i, j] < know[i, j]. Once per planning round, after the round's
sensing and radio exchange and before the candidates are scored, robot i:

1. Own pose first. If its own history has a pending entry (at most OWN_PER_ROUND: the
   pose it just reached), its oldest pending own entry enters the utility GP. Own poses
   never enter the communication GP.
2. Then exactly R = N - 1 + gp.catchup_rounds peer rounds (`peer_rounds` below; R = 0 for
   a lone robot). In each round it picks the peer with
   the largest backlog know[i, j] - fed[i, j]; ties go to the nearest peer offset, i.e.
   peers are ranked (i + 1) mod N, (i + 2) mod N, ..., (i + N - 1) mod N and the first
   maximum in that ranking wins. If the picked peer has a pending entry, its oldest
   pending entry enters the utility GP (with the peer's value) and then the
   communication GP (with COMM_VALUE), and fed[i, j] grows by one; otherwise (no backlog
   anywhere) the round adds nothing.

Why a fixed R: JAX needs static shapes, so every round does the same work; N - 1 rounds
keep up with a steady exchange (each peer brings one pose per round) and the extra
catch-up rounds drain the backlog a radio silence left behind.

Points enter each GP in the order above. How a side batches them (the env inserts a
round's points as blocks, `jaxmripp.sim.gp.add_block`) is free as long as the order is
kept. Where the two sides differ on purpose: with gp.shared_utility (a training-time
option) the env pools every robot's poses in one utility GP; a robot has only its own.

This module imports nothing but the standard library.
"""

COMM_VALUE = 1.0  # target of every peer pose in the communication GP
OWN_PER_ROUND = 1  # own history entries fed per round (one pose is reached per round)


def peer_rounds(team_size: int, catchup_rounds: int) -> int:
    """R = N - 1 + catchup_rounds, none for a lone robot (nobody to feed)."""
    return team_size - 1 + catchup_rounds if team_size > 1 else 0
