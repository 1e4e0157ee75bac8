"""Safe flight between robots, in JAX: the rules of `jaxmripp.spec.flight`.

Closest approach of flights flown at one common speed, the candidate rule against robots
heard, the intent (hold) rule, robot collisions and the take-off pads.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jaxmripp.spec.flight import takes_no_closer


def closest_approach(a0: jax.Array, a1: jax.Array, b0: jax.Array, b1: jax.Array) -> jax.Array:
    """(..., 3) x 4 -> (...,) the least distance between robots flying a0 -> a1 and
    b0 -> b1 at one common speed from the same moment (the shorter flight hovers at its end).
    """
    la = jnp.linalg.norm(a1 - a0, axis=-1, keepdims=True)
    lb = jnp.linalg.norm(b1 - b0, axis=-1, keepdims=True)
    ua = jnp.where(la > 0, (a1 - a0) / jnp.where(la > 0, la, 1.0), 0.0)
    ub = jnp.where(lb > 0, (b1 - b0) / jnp.where(lb > 0, lb, 1.0), 0.0)
    short, long = jnp.minimum(la, lb), jnp.maximum(la, lb)
    # Phase 1, t in [0, short]: both fly.  Phase 2, t in [short, long]: the longer one flies
    # on while the other hovers at its end; the gap there is r(short) + w2 (t - short).
    r0 = a0 - b0
    w1 = ua - ub
    w2 = jnp.where(la > lb, ua, -ub)
    gap1 = _least_gap(r0, w1, 0.0, short)
    gap2 = _least_gap(r0 + w1 * short, w2, 0.0, long - short)
    return jnp.minimum(gap1, gap2)


def _least_gap(r0, w, lo, hi):
    """min over t in [lo, hi] of |r0 + w t|; shapes (..., 3), (..., 3), (..., 1)."""
    ww = jnp.sum(w * w, axis=-1, keepdims=True)
    t = jnp.clip(-jnp.sum(r0 * w, axis=-1, keepdims=True) / jnp.where(ww > 0, ww, 1.0), lo, hi)
    return jnp.linalg.norm(r0 + w * t, axis=-1)


def clear_of_robots(start: jax.Array, ends: jax.Array, others: jax.Array, heard: jax.Array,
                    collision_distance, escape: bool = False) -> jax.Array:
    """(3,), (M, 3), (N, 3), (N,) -> (M,) True where the flight start -> end keeps more than
    d_c from every robot heard, hovering where it was heard; with `escape` (static) also
    where it takes the robot no closer to it (`jaxmripp.spec.flight`)."""
    m, n = ends.shape[0], others.shape[0]
    a0 = jnp.broadcast_to(start, (m, n, 3))
    a1 = jnp.broadcast_to(ends[:, None, :], (m, n, 3))
    b = jnp.broadcast_to(others[None], (m, n, 3))
    clear = closest_approach(a0, a1, b, b) > collision_distance
    if escape:
        clear = clear | takes_no_closer(a0, a1, b)
    return jnp.all(~heard[None, :] | clear, axis=-1)


def pairwise_approach(start: jax.Array, end: jax.Array) -> jax.Array:
    """(N, 3), (N, 3) flights -> (N, N) closest approach of every pair."""
    n = start.shape[0]
    grid = lambda x, axis: jnp.broadcast_to(jnp.expand_dims(x, axis), (n, n, 3))
    return closest_approach(grid(start, 1), grid(end, 1), grid(start, 0), grid(end, 0))


def ranks_above(budget_left: jax.Array, priority: str) -> jax.Array:
    """(N,) -> (N, N) bool: [i, j] True when robot j goes before robot i."""
    n = budget_left.shape[0]
    ids = jnp.arange(n)
    lower_id = ids[None, :] < ids[:, None]
    if priority == "id":
        return lower_id
    more = budget_left[None, :] > budget_left[:, None]
    same = budget_left[None, :] == budget_left[:, None]
    return more | (same & lower_id)


def holds(start: jax.Array, target: jax.Array, flying: jax.Array, heard: jax.Array,
          budget_left: jax.Array, collision_distance, priority: str) -> jax.Array:
    """(N,) bool: flying robots whose flight comes within d_c of the announced flight of a
    higher-priority flying robot they hear."""
    gap = pairwise_approach(start, target)
    conflict = heard & flying[None, :] & ranks_above(budget_left, priority) \
        & (gap <= collision_distance)
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
