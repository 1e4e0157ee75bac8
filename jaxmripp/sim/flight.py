"""Safe flight between robots, in JAX: the rules of `jaxmripp.spec.flight`.

Closest approach of flights flown at one common speed, the candidate rule against robots
heard, the intent (hold) rule, robot collisions and the take-off pads.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxmripp.spec import flight as spec


def closest_approach(a0: jax.Array, a1: jax.Array, b0: jax.Array, b1: jax.Array) -> jax.Array:
    """(..., 3) x 4, broadcasting -> (...,) `jaxmripp.spec.flight.closest_approach`."""
    return spec.closest_approach(a0, a1, b0, b1, jnp)


def clear_of_robots(start: jax.Array, ends: jax.Array, others: jax.Array, heard: jax.Array,
                    collision_distance, escape: bool = False) -> jax.Array:
    """(3,), (M, 3), (N, 3), (N,) -> (M,) True where the flight start -> end keeps more than
    d_c from every robot heard, hovering where it was heard; with `escape` (static) also
    where it takes the robot no closer to it (`jaxmripp.spec.flight`)."""
    a0, a1, b = start[None, None, :], ends[:, None, :], others[None, :, :]
    clear = closest_approach(a0, a1, b, b) > collision_distance  # (M, N)
    if escape:
        clear = clear | spec.takes_no_closer(a0, a1, b)
    return jnp.all(~heard[None, :] | clear, axis=-1)


def pairwise_approach(start: jax.Array, end: jax.Array) -> jax.Array:
    """(N, 3), (N, 3) flights -> (N, N) closest approach of every pair."""
    return closest_approach(start[:, None], end[:, None], start[None], end[None])


def holds(start: jax.Array, target: jax.Array, flying: jax.Array, heard: jax.Array,
          collision_distance) -> jax.Array:
    """(N,) bool: flying robots whose flight comes within d_c of the announced flight of a
    lower-id flying robot they hear."""
    gap = pairwise_approach(start, target)
    ids = jnp.arange(start.shape[0])
    lower_id = ids[None, :] < ids[:, None]  # [i, j]: robot j goes before robot i
    conflict = heard & flying[None, :] & lower_id & (gap <= collision_distance)
    return flying & jnp.any(conflict, axis=1)


def robot_collisions(start: jax.Array, stop: jax.Array, flew: jax.Array, heard: jax.Array,
                     collision_distance) -> tuple[jax.Array, jax.Array]:
    """Pairs, at least one flying, whose actual flights come closer than d_c from at least
    d_c apart: () int32 counts (in radio range at the decision, out of range), each pair
    once. A pair already closer than d_c was counted when it came so close (with
    `safety.escape` it may part: that is no new collision)."""
    n = start.shape[0]
    close = pairwise_approach(start, stop) < collision_distance
    apart = jnp.linalg.norm(start[:, None] - start[None], axis=-1) >= collision_distance
    upper = jnp.triu(jnp.ones((n, n), bool), k=1)
    counted = close & apart & upper & (flew[:, None] | flew[None, :])
    in_range = jnp.sum(counted & heard).astype(jnp.int32)
    return in_range, jnp.sum(counted & ~heard).astype(jnp.int32)


def pads(start: jax.Array, count: int, spacing) -> jax.Array:
    """(3,) -> (N, 3) take-off pads: start + spacing (i mod m, 0, i div m), m = ceil(sqrt N)."""
    side = math.ceil(math.sqrt(count))
    i = jnp.arange(count)
    offset = jnp.stack([i % side, jnp.zeros_like(i), i // side], axis=-1).astype(jnp.float32)
    return start + spacing * offset
