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
from jaxmripp.runtime.mapping import (N_HEADINGS, OccupancyMap, PaddedMaps, inside_world,
                                      known_free)
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
    many = sample_many(np.asarray(uniforms, F32)[None], np.asarray(position, F32)[None],
                       np.asarray([heading]), np.asarray([budget_left], F32),
                       occupancy.codes, occupancy.size, others, spec, stats)
    return Candidates(*(field[0] for field in many))


def sample_many(
    uniforms: np.ndarray,
    position: np.ndarray,
    heading: np.ndarray,
    budget_left: np.ndarray,
    codes: np.ndarray | PaddedMaps,
    size: int,
    others: np.ndarray,
    spec: RuntimeSpec,
    stats: dict | None = None,
) -> Candidates:
    """`sample` for B poses at once: uniforms (B, K * oversample - 1, 3), positions (B, 3),
    headings (B,), budgets left (B,), flat codes (G^3,) of one map or (B, G^3) (or
    `PaddedMaps`) of one map per pose -> Candidates with fields (B, L, ...). `stats` sums
    over the poses."""
    position = np.asarray(position, F32)[:, None, :]  # (B, 1, 3)
    heading = np.asarray(heading)[:, None, None]
    budget_left = np.asarray(budget_left, F32)[:, None, None]
    k = spec.positions
    n_draws = k * spec.oversample
    u = np.asarray(uniforms, F32).reshape(len(position), n_draws - 1, 3)
    lo, hi = spec.shell
    z = F32(2.0) * u[..., 0] - F32(1.0)
    azimuth = F32(2.0 * np.pi) * u[..., 1]
    rho = np.sqrt(np.maximum(F32(0.0), F32(1.0) - z * z))
    direction = np.stack([rho * np.cos(azimuth), rho * np.sin(azimuth), z], axis=-1)
    offset = (F32(lo) + F32(hi - lo) * u[..., 2:3]) * direction
    drawn = position + np.concatenate([np.zeros((len(u), 1, 3), F32), offset], axis=1)
    distance = np.linalg.norm(drawn - position, axis=-1).astype(F32)  # (B, D)

    # Each rule is judged on the draws the previous ones kept: outside draws are not
    # traversed, blocked ones not checked against the robots.
    inside = inside_world(drawn)
    free = inside.copy()
    free[inside] = known_free(codes, np.broadcast_to(position, drawn.shape)[inside],
                              drawn[inside], size, hi, rows=np.nonzero(inside)[0])
    apart = free.copy()
    apart[free] = flight.clear_of_robots(np.broadcast_to(position, drawn.shape)[free],
                                         drawn[free], others, spec.collision_distance,
                                         spec.escape)
    place_ok = inside & free & apart

    headings = np.arange(N_HEADINGS, dtype=np.int32)
    turns = headings != heading  # (B, 1, 4)
    cost = distance[..., None] + F32(spec.turn_cost) * turns.astype(F32)  # (B, D, 4)
    is_current = (np.arange(n_draws) == 0)[:, None] & ~turns
    pose_ok = place_ok[..., None] & (cost <= budget_left) & ~is_current
    keep = np.any(pose_ok, axis=-1)
    if stats is not None:
        stats.update(draws=keep.size, outside=int((~inside).sum()),
                     blocked=int((inside & ~free).sum()),
                     crowded=int((inside & free & ~apart).sum()),
                     over_budget=int((place_ok & ~keep).sum()))

    slot = np.argsort(~keep, axis=-1, kind="stable")[:, :k]  # (B, K)
    kept = np.take_along_axis(keep, slot, axis=-1)[..., None]
    take = lambda x: np.take_along_axis(x, slot[..., None], axis=1)  # noqa: E731
    slot_position = np.where(kept, take(drawn), position)
    slot_cost = np.where(kept, take(cost), cost[:, :1])
    slot_valid = take(pose_ok) & kept
    b = len(u)
    return Candidates(
        position=np.repeat(slot_position, N_HEADINGS, axis=1).astype(F32),
        heading=np.tile(headings, (b, k)),
        cost=slot_cost.reshape(b, -1).astype(F32),
        valid=slot_valid.reshape(b, -1),
    )
