"""What a privileged critic reads beside `Observation.global_state` (`ppo.privileged_critic`):
where the windows nobody has found yet are, from the true world. Only the critic of a
training run reads it, to estimate how much the team will still find; the actor never
does, so nothing a robot computes in flight depends on it.

Layout (`size(N)` = N * len(RADII) + 1 entries, float32):

    for each robot i (robot-major), for each radius r in RADII:
        share of the world's real windows that are undiscovered and whose voxel centre
        lies within r (unit-cube distance) of robot i
    share of the world's real windows that are undiscovered

One environment, no batch axes (callers vmap).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import EnvParams
from jaxmripp.sim.types import EnvState

# Unit-cube radii: about one flight (the candidate shell reaches 0.2 in the default world),
# two flights and a quarter of the city.
RADII = (0.1, 0.2, 0.4)


def size(robots: int) -> int:
    """Length of `features` for a team of `robots`."""
    return robots * len(RADII) + 1


def features(state: EnvState) -> jax.Array:
    """(size(N),) float32 the layout of the module docstring."""
    world = state.world
    grid = world.height.shape[0]
    remaining = world.target_valid & ~state.discovered  # (T,)
    total = jnp.maximum(world.target_valid.sum(), 1).astype(jnp.float32)
    centre = (world.target_voxel.astype(jnp.float32) + 0.5) / grid  # (T, 3)
    distance = jnp.linalg.norm(state.position[:, None, :] - centre[None], axis=-1)  # (N, T)
    near = distance[..., None] <= jnp.asarray(RADII, jnp.float32)  # (N, T, R)
    counts = jnp.sum(near & remaining[None, :, None], axis=1)  # (N, R)
    return jnp.concatenate([counts.reshape(-1), remaining.sum()[None]]).astype(
        jnp.float32) / total


def _extended(obs: Observation, extra: jax.Array) -> Observation:
    """obs with `extra` (broadcast to (..., P)) appended to its global_state (..., G)."""
    extra = jnp.broadcast_to(extra, (*obs.global_state.shape[:-1], extra.shape[-1]))
    return obs.replace(global_state=jnp.concatenate([obs.global_state, extra], axis=-1))


def appended(obs: Observation, env_state: EnvState) -> Observation:
    """obs (E, N, ...) of E environments with each environment's `features` appended to
    every robot's global_state: (E, N, N * S + 2) -> (E, N, N * S + 2 + size(N))."""
    return _extended(obs, jax.vmap(features)(env_state)[:, None])


def observation_zeros(params: EnvParams, privileged: bool) -> Observation:
    """One robot's all-zero observation as a critic with (or without) these inputs reads
    it: shapes for initialising a network."""
    obs = Observation.zeros(params)
    return _extended(obs, jnp.zeros((size(params.n_robots),), jnp.float32)) if privileged else obs


@dataclasses.dataclass(frozen=True)
class ZeroFilled:
    """A network whose critic was trained with these inputs, applied where nobody has them
    (evaluation sweeps): zeros stand in for them. Only the critic's value changes, which
    no planner reads; the actor's memory and logits are the network's own."""

    network: Any  # a flax module: apply(params, memory (W,), obs) of one robot
    robots: int

    def apply(self, params, memory, obs: Observation):
        zeros = jnp.zeros((size(self.robots),), jnp.float32)
        return self.network.apply(params, memory, _extended(obs, zeros))
