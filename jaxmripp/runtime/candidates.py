"""NumPy port of `jaxmripp.sim.candidates.sample`: the same rules, a NumPy random source.

Draw 0 is the current position (turning in place); the other draws are uniform on the
shell [lo, hi] around the robot. A draw is kept when it lies in the unit cube, its straight
line of flight is known free (every voxel it traverses is FREE in the robot's map, the
traversal rule of `jaxmripp.spec.grid`) and the flight's closest approach to every robot
heard this round, hovering where it was heard, exceeds d_c (`jaxmripp.spec.flight`); a
pose (draw x heading) is feasible when its cost (distance + turn cost on a heading change)
fits the budget and it is not the current pose. Feasible draws fill the K slots in draw
order; padding sits at the current position and is marked invalid. Given the same uniforms
(`uniforms`, shape (K * oversample - 1, 3)) the output equals the JAX sampler's up to
float32 rounding of the trigonometry.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxmripp.runtime import flight
from jaxmripp.runtime.mapping import N_HEADINGS, OccupancyMap, inside_world
from jaxmripp.runtime.weights import RuntimeSpec

F32 = np.float32


class Candidates(NamedTuple):
    """L = 4 K poses; index = slot * 4 + heading (jaxmripp.sim.candidates.Candidates)."""

    position: np.ndarray  # (L, 3) float32
    heading: np.ndarray  # (L,) int32
    cost: np.ndarray  # (L,) float32
    valid: np.ndarray  # (L,) bool


def pose_cost(position, heading, targets, target_headings, turn_cost) -> np.ndarray:
    """(L,) float32 budget charged: Euclidean distance + turn cost on a heading change."""
    distance = np.linalg.norm(np.asarray(targets, F32) - position, axis=-1).astype(F32)
    return distance + F32(turn_cost) * (np.asarray(target_headings) != heading).astype(F32)


def sample(
    uniforms: np.ndarray,
    position: np.ndarray,
    heading: int,
    budget_left: float,
    occupancy: OccupancyMap,
    others: np.ndarray,
    spec: RuntimeSpec,
    stats: dict | None = None,
) -> Candidates:
    """uniforms (K * oversample - 1, 3) in [0, 1) float32 -> this robot's candidates.

    `stats`, if given, receives how many of the draws each rule rejected (for messages)."""
    position = np.asarray(position, F32)
    k = spec.positions
    n_draws = k * spec.oversample
    u = np.asarray(uniforms, F32).reshape(n_draws - 1, 3)
    lo, hi = spec.shell
    z = F32(2.0) * u[:, 0] - F32(1.0)
    azimuth = F32(2.0 * np.pi) * u[:, 1]
    rho = np.sqrt(np.maximum(F32(0.0), F32(1.0) - z * z))
    direction = np.stack([rho * np.cos(azimuth), rho * np.sin(azimuth), z], axis=-1)
    offset = (F32(lo) + F32(hi - lo) * u[:, 2:3]) * direction
    drawn = position + np.concatenate([np.zeros((1, 3), F32), offset])
    distance = np.linalg.norm(drawn - position, axis=-1).astype(F32)

    inside = inside_world(drawn)
    free = inside.copy()  # draws outside the world are rejected anyway: not traversed
    free[inside] = occupancy.known_free(position, drawn[inside], max_length=hi)
    apart = free.copy()
    apart[free] = flight.clear_of_robots(position, drawn[free], others,
                                         spec.collision_distance)
    place_ok = inside & free & apart

    headings = np.arange(N_HEADINGS, dtype=np.int32)
    turns = headings != heading
    cost = distance[:, None] + F32(spec.turn_cost) * turns.astype(F32)
    is_current = (np.arange(n_draws) == 0)[:, None] & ~turns
    pose_ok = place_ok[:, None] & (cost <= F32(budget_left)) & ~is_current
    keep = np.any(pose_ok, axis=-1)
    if stats is not None:
        stats.update(draws=n_draws, outside=int((~inside).sum()),
                     blocked=int((inside & ~free).sum()),
                     crowded=int((inside & free & ~apart).sum()),
                     over_budget=int((place_ok & ~keep).sum()))

    slot = np.argsort(~keep, kind="stable")[:k]
    kept = keep[slot]
    slot_position = np.where(kept[:, None], drawn[slot], position)
    slot_cost = np.where(kept[:, None], cost[slot], cost[0])
    slot_valid = pose_ok[slot] & kept[:, None]
    return Candidates(
        position=np.repeat(slot_position, N_HEADINGS, axis=0).astype(F32),
        heading=np.tile(headings, k),
        cost=slot_cost.reshape(-1).astype(F32),
        valid=slot_valid.reshape(-1),
    )
