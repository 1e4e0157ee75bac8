"""Candidate actions: the L = 4 K poses a robot may fly to next.

Positions are drawn on a thin spherical shell around the robot (docs/design.md section 1),
filtered by what the robot itself knows -- its own occupancy map (the flight rules of
`jaxmripp.spec.flight`), the robots it can hear and its remaining budget -- and compacted into a fixed number of slots, each expanded into
the four headings. Everything is a pure function of its inputs and an explicit PRNG key,
with static shapes, so `sample` can be jitted and vmapped over robots and environments;
the turn cost and collision distance may be traced (sweeps vmap over them).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.sim import flight, geometry
from jaxmripp.config import CandidateConfig, SafetyConfig


@struct.dataclass
class Candidates:
    """One robot's candidate poses; pose index = position slot * 4 + heading.

    position: (L, 3) float32  slot k's position, repeated for its 4 headings
    heading:  (L,) int32      heading index into geometry.HEADING_ANGLES
    cost:     (L,) float32    budget charged: Euclidean distance + turn cost on a heading change
    valid:    (L,) bool       feasible; invalid entries are padding and must be masked out
    """

    position: jax.Array
    heading: jax.Array
    cost: jax.Array
    valid: jax.Array


def sample(
    key: jax.Array,
    position: jax.Array,
    heading: jax.Array,
    budget_left: jax.Array,
    occupancy: geometry.Map,
    others: jax.Array,
    others_known: jax.Array,
    cand: CandidateConfig,
    safety: SafetyConfig,
    turn_cost: float | jax.Array,
    collision_distance: float | jax.Array,
    size: int,
) -> Candidates:
    """Samples one robot's candidate poses for the next step.

    Args:
      key: PRNG key for this robot and step.
      position: (3,) the robot's position.
      heading: () int32 its heading index.
      budget_left: () float32 its remaining path budget.
      occupancy: its own map, (G, G, G) int8 codes (geometry.FREE/UNKNOWN/OCCUPIED) or a
        `geometry.CodeReader` such as `sim.maps.RobotMap`.
      others: (N, 3) positions of all robots (the caller's own row is ignored if masked).
      others_known: (N,) bool robots this one can hear (within radio range); False for self.
      cand: static configuration (shapes: K positions, oversampling, shell).
      safety: static rules of jaxmripp.spec.flight: `flight` (known_free offers only
        flights through voxels mapped FREE; truncate and optimistic only avoid voxels
        mapped OCCUPIED) and `escape` (flights that take the robot no closer to a robot
        heard are clear of it).
      turn_cost: () charged on a heading change.
      collision_distance: () d_c; flights that come within it of a robot heard (hovering
        where it is) are rejected.
      size: G, voxels per side.

    Returns:
      `Candidates` with L = 4 * cand.positions poses. Slot 0 holds the current position
      (turning in place) whenever that is feasible; the other slots hold the first feasible
      draws in draw order; the rest is padding at the current position, marked invalid.
    """
    position = jnp.asarray(position, jnp.float32)
    heading = jnp.asarray(heading, jnp.int32)
    budget_left = jnp.asarray(budget_left, jnp.float32)
    n_robots = others.shape[0]
    chex.assert_shape(position, (3,))
    chex.assert_shape([heading, budget_left], ())
    if not isinstance(occupancy, geometry.CodeReader):
        chex.assert_shape(occupancy, (size, size, size))
    chex.assert_shape(others, (n_robots, 3))
    chex.assert_shape(others_known, (n_robots,))
    n_draws = cand.positions * cand.oversample

    # Draw 0 is the current position, so turning in place is always on offer; the rest
    # are uniform in direction (z uniform in [-1, 1] and azimuth uniform gives the uniform
    # measure on the sphere, with no normalisation to divide by zero) and uniform in
    # distance across the shell.
    lo, hi = cand.shell
    u = jax.random.uniform(key, (n_draws - 1, 3), jnp.float32)
    z = 2.0 * u[:, 0] - 1.0
    azimuth = 2.0 * jnp.pi * u[:, 1]
    rho = jnp.sqrt(jnp.maximum(0.0, 1.0 - z * z))
    direction = jnp.stack([rho * jnp.cos(azimuth), rho * jnp.sin(azimuth), z], axis=-1)
    offset = (lo + (hi - lo) * u[:, 2:3]) * direction
    drawn = position + jnp.concatenate([jnp.zeros((1, 3), jnp.float32), offset])
    # Charged distance as flown between the float32 endpoints (exactly 0 for draw 0).
    distance = jnp.linalg.norm(drawn - position, axis=-1)

    line_ok = geometry.line_rule(safety.flight)
    place_ok = (
        geometry.inside_world(drawn)
        & line_ok(position, drawn, occupancy, size, hi)
        & flight.clear_of_robots(position, drawn, others, others_known, collision_distance,
                                 safety.escape)
    )

    # Per pose: pay the distance, plus the turn cost when the heading changes. The
    # current pose itself (draw 0, same heading) would be a no-op step, so it is excluded
    # and every executed action makes progress.
    headings = jnp.arange(geometry.N_HEADINGS, dtype=jnp.int32)
    turns = headings != heading
    cost = distance[:, None] + turn_cost * turns.astype(jnp.float32)
    is_current = (jnp.arange(n_draws) == 0)[:, None] & ~turns
    pose_ok = place_ok[:, None] & (cost <= budget_left) & ~is_current
    keep = jnp.any(pose_ok, axis=-1)  # the cheapest remaining pose fits the budget

    # Compact: slot r takes the r-th feasible draw in draw order, so slot 0 stays the
    # current position whenever turning in place is feasible. A rank match over (slots,
    # draws) instead of a stable argsort, which XLA:CPU runs as a slow per-row sort.
    rank = jnp.cumsum(keep) - 1
    match = keep[None, :] & (rank[None, :] == jnp.arange(cand.positions)[:, None])
    slot = jnp.argmax(match, axis=1)
    kept = jnp.any(match, axis=1)
    # Padding sits at the current position (finite, inside the world) so that downstream
    # features never see the rejected draws; its cost is then exactly the turn cost.
    slot_position = jnp.where(kept[:, None], drawn[slot], position)
    slot_cost = jnp.where(kept[:, None], cost[slot], cost[0])
    slot_valid = pose_ok[slot] & kept[:, None]

    return Candidates(
        position=jnp.repeat(slot_position, geometry.N_HEADINGS, axis=0),
        heading=jnp.tile(headings, cand.positions),
        cost=slot_cost.reshape(cand.count),
        valid=slot_valid.reshape(cand.count),
    )
