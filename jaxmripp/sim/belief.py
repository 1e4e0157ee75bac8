"""The JAX implementation of `jaxmripp.spec.belief`: each robot's buildings, the windows
and facade it knows of them, their posterior window rates, and the quantised facade rates
that weigh the view gain's facade samples (`jaxmripp.sim.view`, `rates=`).

Also the same rates computed from the truth (`true_rates`: each building's real number of
windows the robot has not found, spread over the surface it has not seen), for the
`oracle_rate` reference, which knows how many windows are left on a building but not
where on it.

Shapes: G voxels per side, N robots, T window slots. One environment, no batch axes
(callers vmap); every function is traced once per static shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import SensorConfig, WorldConfig
from jaxmripp.sim import maps, view
from jaxmripp.sim.geometry import OCCUPIED, UNKNOWN
from jaxmripp.sim.types import EnvState
from jaxmripp.spec import belief as spec


def prior(world: WorldConfig) -> float:
    """m: the world generator's expected windows per window slot (`spec.prior_rate`)."""
    return spec.prior_rate(world.size, world.n_buildings, world.footprint,
                           world.footprint_min, world.height_range,
                           (world.target_min, world.target_capacity), world.target_placement)


def building_labels(building: jax.Array, footprint: int) -> jax.Array:
    """(G, G) bool building columns -> (G, G) int32 labels: the smallest flat column index
    x G + y of each column's 8-connected component, G * G for other columns. Components
    are spread by repeated neighbourhood minima until nothing changes (at most footprint^2
    rounds: a component lies inside one footprint)."""
    size = building.shape[0]
    none = size * size
    start = jnp.where(building, jnp.arange(none, dtype=jnp.int32).reshape(size, size), none)

    def spread(labels):
        padded = jnp.pad(labels, 1, constant_values=none)
        smallest = labels
        for dx in (0, 1, 2):
            for dy in (0, 1, 2):
                smallest = jnp.minimum(smallest, padded[dx:dx + size, dy:dy + size])
        return jnp.where(building, smallest, none)

    def cond(carry):
        labels, previous, rounds = carry
        return jnp.any(labels != previous) & (rounds < footprint * footprint)

    def body(carry):
        labels, _, rounds = carry
        return spread(labels), labels, rounds + 1

    labels, _, _ = jax.lax.while_loop(cond, body, (spread(start), start, jnp.int32(1)))
    return labels


def known_facade(team_map: jax.Array, n_robots: int) -> jax.Array:
    """(N, G, G) int32: per robot and column, the voxels its map holds OCCUPIED."""
    return jnp.sum(maps.robot_maps(team_map, n_robots) == OCCUPIED, axis=-1, dtype=jnp.int32)


def known_windows(team_map: jax.Array, target_voxel: jax.Array, target_valid: jax.Array,
                  n_robots: int) -> jax.Array:
    """(N, T) bool: the valid windows whose voxel each robot's map holds."""
    size = team_map.shape[-1]
    flat = (target_voxel[:, 0] * size + target_voxel[:, 1]) * size + target_voxel[:, 2]
    words = team_map.reshape(team_map.shape[0], -1)
    codes = maps.codes_at(words, jnp.arange(n_robots)[:, None], flat[None, :])
    return (codes != UNKNOWN) & target_valid[None, :]


def _per_building(labels: jax.Array, values: jax.Array, at: jax.Array | None = None):
    """Sums of `values` per label (G * G + 1,) float32: values per column (G, G), or per
    item at flat columns `at`."""
    size = labels.shape[0]
    flat = labels.reshape(-1)
    where = flat if at is None else flat[at]
    return jnp.zeros(size * size + 1, jnp.float32).at[where].add(
        values.reshape(-1).astype(jnp.float32))


def relative_rates(labels: jax.Array, facade_seen: jax.Array, window_column: jax.Array,
                   window_known: jax.Array, strength, prior_rate: float) -> jax.Array:
    """(G, G) float32 rho of each known building column's building (0 elsewhere), for
    labels (G, G), the OCCUPIED voxels known per column (G, G), the windows' flat columns
    (T,) and which of them are known (T,)."""
    found = _per_building(labels, window_known, window_column)
    seen = _per_building(labels, facade_seen)
    rho = spec.relative_rate(found, seen, strength, prior_rate, jnp)
    return jnp.where(labels < labels.size, rho[labels], 0.0)


def facade_rates(rates: jax.Array, sensor: SensorConfig) -> jax.Array:
    """(G, G) float32 column rates -> (G, G) int32 quantised facade rates: the largest q of
    the columns that make each column's facade top (`view.facade_tops`)."""
    return view.facade_tops(spec.quantised(rates, jnp), sensor)


def _window_columns(state: EnvState) -> jax.Array:
    size = state.world.height.shape[0]
    return state.world.target_voxel[:, 0] * size + state.world.target_voxel[:, 1]


def team_rates(state: EnvState, strength, sensor: SensorConfig, world: WorldConfig
               ) -> jax.Array:
    """(N, G, G) int32 every robot's facade rates from its own map, tops and the windows it
    knows (`jaxmripp.spec.belief`), prior strength `strength` (traced or static)."""
    n = state.position.shape[0]
    labels = jax.vmap(building_labels, in_axes=(0, None))(state.building_top > 0,
                                                         world.footprint)
    known = known_windows(state.team_map, state.world.target_voxel, state.world.target_valid, n)
    rates = jax.vmap(relative_rates, in_axes=(0, 0, None, 0, None, None))(
        labels, known_facade(state.team_map, n), _window_columns(state), known, strength,
        prior(world))
    return jax.vmap(facade_rates, in_axes=(0, None))(rates, sensor)


def surface(height: jax.Array) -> jax.Array:
    """(G, G) int32 the building voxels of each column with a face open to the air: the
    part of the column above its lowest horizontal neighbour (outside the grid: 0), and
    at least its roof voxel."""
    padded = jnp.pad(height, 1)
    lowest = jnp.minimum(jnp.minimum(padded[:-2, 1:-1], padded[2:, 1:-1]),
                         jnp.minimum(padded[1:-1, :-2], padded[1:-1, 2:]))
    return jnp.where(height > 0, jnp.maximum(height - lowest, 1), 0)


def true_rates(state: EnvState, sensor: SensorConfig, world: WorldConfig) -> jax.Array:
    """(N, G, G) int32 facade rates from the truth: for each real building (a connected
    footprint of the height map), the windows the robot's map does not hold over the
    surface voxels it does not hold (at least 1), relative to the prior m, quantised as
    `jaxmripp.spec.belief` quantises rho."""
    n = state.position.shape[0]
    labels = building_labels(state.world.height > 0, world.footprint)
    known = known_windows(state.team_map, state.world.target_voxel, state.world.target_valid, n)
    windows = _per_building(labels, state.world.target_valid, _window_columns(state))
    total = _per_building(labels, surface(state.world.height))
    m = prior(world)

    def one(known_i, seen_i):
        left = windows - _per_building(labels, known_i, _window_columns(state))
        unseen = jnp.maximum(total - _per_building(labels, seen_i), 1.0)
        rate = left / unseen / jnp.float32(m)
        return facade_rates(jnp.where(labels < labels.size, rate[labels], 0.0), sensor)

    return jax.vmap(one)(known, known_facade(state.team_map, n))
