"""The ground-truth choice: robots in turn take the view that reveals the most windows
nobody has found yet. It reads the true world (`EnvState.world`, `discovered`), so it is
an upper reference (the `oracle` baseline) and a privileged teacher (`ppo.teacher =
oracle`), never something a robot could compute.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.sim import sensing
from jaxmripp.sim.params import EnvParams
from jaxmripp.sim.types import EnvState
from jaxmripp.spec import layout


def choose_in_turn(mask: jax.Array, state: EnvState, params: EnvParams,
                   tie: jax.Array) -> jax.Array:
    """The team's choices (N,) int32. mask (N, L) the feasible candidates, tie (N, L) the
    tie-break scores, each below 0.5 in magnitude so that one window outweighs them. Robot
    i (index order) casts the sensor on the true world from each of its candidates and
    takes the one with the most windows neither discovered nor seen from the poses robots
    j < i chose this step. One environment: callers vmap."""
    c = state.candidates
    cast = jax.vmap(lambda p, h: sensing.cast(state.world, p, h, params.sensor,
                                              params.size).seen)

    def choose(covered, i):
        seen = cast(c.position[i], c.heading[i])  # (L, T)
        fresh = jnp.sum(seen & ~covered[None], axis=-1).astype(jnp.float32)
        a = layout.masked_argmax(fresh + tie[i], mask[i], jnp)
        covered = covered | (seen[a] & jnp.any(mask[i]))
        return covered, a

    _, actions = jax.lax.scan(choose, state.discovered, jnp.arange(mask.shape[0]))
    return actions
