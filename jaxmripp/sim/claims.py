"""Robots deciding in turn, each seeing the views its peers have just claimed.

Within one step the robots of a team choose in index order. Before robot i chooses, the
VIEW columns of its observation (`jaxmripp.spec.layout`) are recomputed on its map with
the voxels that the robots j < i it hears will look at (the unknown samples of their
chosen poses, `view.unknown_in_view`) counted as seen, so a view a peer has taken is no
longer a gain. Robot 0, and a robot that hears nobody who chose before it, sees the
observation `observe` wrote. This is the sequential allocation of the `nbv_team` baseline
and of the lookahead rules (`jaxmripp.sim.lookahead`), for any decision rule.

One environment, no batch axes: callers `vmap` over environments.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from jaxmripp.config import SensorConfig
from jaxmripp.sim import comms, geometry, view
from jaxmripp.sim.observation import VIEW_COLUMNS, Observation, view_columns
from jaxmripp.sim.types import EnvState

# decide(i, robot i's observation, robot i's map (G, G, G) with its peers' claims counted
# as seen: what the observation's VIEW columns were computed on) -> (action () int32,
# anything else to stack over robots)
Decide = Callable[[jax.Array, Observation, jax.Array], tuple[jax.Array, Any]]


def in_turn(decide: Decide, obs: Observation, state: EnvState, sensor: SensorConfig,
            shell_outer: float, relay: bool = False) -> tuple[Observation, jax.Array, Any]:
    """Runs `decide` robot by robot on observations (N, ...) of `state`; returns the
    observations the robots decided on (N, ...), their actions (N,) and the stacked
    extra outputs (N, ...). A robot hears the choices of the robots in radio range this
    round, or with `relay` of its whole connected component (`comms.links`)."""
    n, size = obs.mask.shape[0], state.occupancy.shape[-1]
    c = state.candidates
    outside = size**3  # an index past the map: scatters drop it
    hears = comms.links(state.heard, relay)

    def choose(claimed, i):
        heard = jnp.where(hears[i][:, None], claimed, outside).reshape(-1)
        occupancy = state.occupancy[i].reshape(-1).at[heard].set(
            geometry.FREE, mode="drop").reshape(state.occupancy.shape[1:])
        columns = view_columns(occupancy, state.building_top[i], c.position[i], c.cost[i],
                               sensor, size, shell_outer)
        mine = jax.tree.map(lambda x: x[i], obs)
        mine = mine.replace(features=mine.features.at[:, VIEW_COLUMNS].set(columns))
        action, extra = decide(i, mine, occupancy)
        seen = view.unknown_in_view(occupancy, state.building_top[i], c.position[i, action],
                                    c.heading[i, action], sensor, size)
        seen = jnp.where(jnp.any(mine.mask), seen, outside)
        return claimed.at[i].set(seen), (mine, action, extra)

    samples = view.samples_per_pose(sensor, size)
    init = jnp.full((n, samples), outside, jnp.int32)
    _, (decided, actions, extra) = jax.lax.scan(choose, init, jnp.arange(n))
    return decided, actions, extra
