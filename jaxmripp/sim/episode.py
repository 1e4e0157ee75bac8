"""Whole episodes with any planner: one `lax.scan` over T_max steps, vmap-able over keys."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.sim import env as envmod
from jaxmripp.sim.params import DynamicParams, EnvParams


class Planner(NamedTuple):
    """What an episode runs per robot team: `init(N)` gives the (N, M) memory, `act(key,
    memory, obs, state, dyn)` the new memory and (N,) candidate indices."""

    name: str
    init: Callable[[int], jax.Array]
    act: Callable[..., tuple[jax.Array, jax.Array]]


@struct.dataclass
class Trajectory:
    """T = T_max steps after the reset; N robots."""

    position: jax.Array  # (T + 1, N, 3) including the start
    heading: jax.Array  # (T + 1, N)
    active: jax.Array  # (T, N) bool: the robot acted at this step
    discovered_fraction: jax.Array  # (T + 1,)
    budget_used: jax.Array  # (T + 1,) fraction of the team budget spent
    reward: jax.Array  # (T, N)


@struct.dataclass
class EpisodeResult:
    discovered_fraction: jax.Array  # ()
    steps: jax.Array  # () steps until every robot was done
    obstacle_collisions: jax.Array  # () flights that entered a building (jaxmripp.spec.flight)
    blocked: jax.Array  # () flights cut short where the map stops being known free
    held: jax.Array  # () flights given up for a lower-id robot's intent
    robot_collisions_in_range: jax.Array  # () pairs closer than d_c that heard each other
    robot_collisions_out_of_range: jax.Array  # () pairs closer than d_c out of radio range
    distance: jax.Array  # () team path length
    contacts: jax.Array  # ()
    found_at: jax.Array  # (T_targets,) int32 step each window was found: 0 at reset, -1 never
    final_state: envmod.EnvState
    trajectory: Trajectory


def run(key: jax.Array, params: EnvParams, dyn: DynamicParams, planner: Planner,
        world_key: jax.Array | None = None) -> EpisodeResult:
    """Resets a world and lets `planner` act until T_max steps have passed.

    The world (and budget, first candidates) come from `world_key` when given, so several
    trials can share one world; otherwise both world and trial are drawn from `key`.
    `dyn` may be traced: vmapping over it runs several settings in one compilation.
    """
    if world_key is None:
        world_key, key = jax.random.split(key)
    key_reset, key_run = world_key, key
    obs, state = envmod.reset(key_reset, params, dyn)
    memory = planner.init(params.n_robots)
    team_budget = state.budget_initial * params.n_robots

    def spent(s):
        return 1.0 - s.budget_left.sum() / team_budget

    def body(carry, key):
        obs, state, memory = carry
        key_act, key_step = jax.random.split(key)
        memory, actions = planner.act(key_act, memory, obs, state, dyn)
        obs, state, reward, _, info = envmod.step(key_step, state, actions, params, dyn)
        out = (state.position, state.heading, info.acted, info.discovered_fraction,
               spent(state), reward, state.discovered)
        return (obs, state, memory), out

    keys = jax.random.split(key_run, params.max_steps)
    (_, final, _), (pos, head, acted, frac, used, reward, found) = jax.lax.scan(
        body, (obs, state, memory), keys)
    trajectory = Trajectory(
        position=jnp.concatenate([state.position[None], pos]),
        heading=jnp.concatenate([state.heading[None], head]),
        active=acted,
        discovered_fraction=jnp.concatenate([envmod.discovered_fraction(state)[None], frac]),
        budget_used=jnp.concatenate([spent(state)[None], used]),
        reward=reward,
    )
    m = final.metrics
    first = jnp.argmax(found, axis=0) + 1
    found_at = jnp.where(state.discovered, 0, jnp.where(final.discovered, first, -1))
    return EpisodeResult(
        discovered_fraction=envmod.discovered_fraction(final),
        steps=jnp.any(acted, axis=1).sum(),
        obstacle_collisions=m.obstacle_collisions.sum(),
        blocked=m.blocked.sum(),
        held=m.held.sum(),
        robot_collisions_in_range=m.robot_collisions_in_range,
        robot_collisions_out_of_range=m.robot_collisions_out_of_range,
        distance=m.distance.sum(),
        contacts=m.contacts,
        found_at=found_at.astype(jnp.int32),
        final_state=final,
        trajectory=trajectory,
    )
