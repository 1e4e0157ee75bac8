"""The JAX implementation of `jaxmripp.spec.belief`: each robot's buildings, the windows
and facade it knows of them, their posterior window rates, and the quantised facade rates
that weigh the view gain's facade samples (`jaxmripp.sim.view`, `rates=`).

Also the same rates computed from the truth (`true_rates`: each building's real number of
windows the robot has not found, spread over the surface it has not seen), for the
`oracle_rate` reference, which knows how many windows are left on a building but not
where on it.

Where the work goes: a robot's known building columns are always columns of real
buildings, and with `world.clearance` >= 1 no two real buildings touch, so the rule's
8-connected components never leave one real building's footprint box. The simulator
therefore computes everything on the B boxes of footprint^2 columns that hold the real
buildings (`building_boxes`, from the world's height map) instead of on the whole G x G
ground: the same labels and counts (the other columns hold nothing the rule counts), for
a tenth of the reads. The truth only says where to look, never what a robot knows.

Shapes: G voxels per side, N robots, T window slots, B buildings, F = footprint, C = B F^2
box columns. One environment, no batch axes (callers vmap); traced once per shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import SensorConfig, WorldConfig
from jaxmripp.sim import maps, tops
from jaxmripp.sim.geometry import OCCUPIED, UNKNOWN
from jaxmripp.sim.types import EnvState
from jaxmripp.spec import belief as spec


def prior(world: WorldConfig) -> float:
    """m: the world generator's expected windows per window slot (`spec.prior_rate`)."""
    return spec.prior_rate(world.size, world.n_buildings, world.footprint,
                           world.footprint_min, world.height_range,
                           (world.target_min, world.target_capacity), world.target_placement)


def building_boxes(height: jax.Array, world: WorldConfig) -> jax.Array:
    """(B, F * F) int32 flat column indices of each real building's footprint box (its
    columns, row-major from its low corner), G * G where the box column is not a building
    column. A building's low corner is its only column with no building at x - 1 or
    y - 1 (footprints are rectangles at least `clearance` apart)."""
    size, side = world.size, world.footprint
    padded = jnp.pad(height, ((1, 0), (1, 0)))
    corner = (height > 0) & (padded[:-1, 1:] == 0) & (padded[1:, :-1] == 0)
    (origin,) = jnp.nonzero(corner.reshape(-1), size=world.n_buildings,
                            fill_value=size * size)
    dx, dy = (d.reshape(-1) for d in jnp.meshgrid(jnp.arange(side), jnp.arange(side),
                                                  indexing="ij"))
    x, y = origin[:, None] // size + dx[None], origin[:, None] % size + dy[None]
    inside = (origin[:, None] < size * size) & (x < size) & (y < size)
    cell = jnp.where(inside, x * size + y, 0)
    return jnp.where(inside & (height.reshape(-1)[cell] > 0), cell, size * size)


def box_labels(known: jax.Array, cells: jax.Array, footprint: int, size: int) -> jax.Array:
    """(B, F * F) bool known building columns of the boxes `cells` (B, F * F) -> their
    labels (`jaxmripp.spec.belief`: the smallest flat column index of the 8-connected
    component), G * G for the others. F^2 - 1 rounds of neighbourhood minima reach across
    any component of a box."""
    none = size * size
    shape = (cells.shape[0], footprint, footprint)
    known = known.reshape(shape)

    def spread(_, labels):
        # The 3 x 3 minimum as a minimum along x, then along y (min is separable).
        padded = jnp.pad(labels, ((0, 0), (1, 1), (0, 0)), constant_values=none)
        rows = jnp.minimum(jnp.minimum(padded[:, :-2], padded[:, 1:-1]), padded[:, 2:])
        padded = jnp.pad(rows, ((0, 0), (0, 0), (1, 1)), constant_values=none)
        least = jnp.minimum(jnp.minimum(padded[..., :-2], padded[..., 1:-1]), padded[..., 2:])
        return jnp.where(known, least, none)

    start = jnp.where(known, cells.reshape(shape), none)
    return jax.lax.fori_loop(0, footprint * footprint - 1, spread, start).reshape(
        cells.shape)


def known_facade(team_map: jax.Array, cells: jax.Array, n_robots: int) -> jax.Array:
    """(N, C) int32: per robot and box column (C,), the voxels its map holds OCCUPIED (0 for
    the columns G * G)."""
    size = team_map.shape[-1]
    # Whole columns at once (G bytes each, contiguous), decoded as a thin team map.
    rows = team_map.reshape(team_map.shape[0], size * size, size)[
        :, jnp.minimum(cells, size * size - 1)]
    codes = maps.robot_maps(rows[..., None], n_robots)  # (N, C, G, 1)
    count = jnp.sum(codes == OCCUPIED, axis=(-2, -1), dtype=jnp.int32)
    return jnp.where(cells[None, :] < size * size, count, 0)


def known_windows(team_map: jax.Array, target_voxel: jax.Array, target_valid: jax.Array,
                  n_robots: int) -> jax.Array:
    """(N, T) bool: the valid windows whose voxel each robot's map holds."""
    size = team_map.shape[-1]
    flat = (target_voxel[:, 0] * size + target_voxel[:, 1]) * size + target_voxel[:, 2]
    words = team_map.reshape(team_map.shape[0], -1)
    codes = maps.codes_at(words, jnp.arange(n_robots)[:, None], flat[None, :])
    return (codes != UNKNOWN) & target_valid[None, :]


def _sums(labels: jax.Array, values: jax.Array, size: int) -> jax.Array:
    """(G * G + 1,) float32 sums of `values` per label (both (M,); label G * G: none)."""
    return jnp.zeros(size * size + 1, jnp.float32).at[labels].add(values.astype(jnp.float32))


def _window_labels(labels: jax.Array, cells: jax.Array, target_voxel: jax.Array,
                   size: int) -> jax.Array:
    """(T,) the label of each window's column (G * G outside every known building)."""
    grid = jnp.full(size * size + 1, size * size, jnp.int32).at[cells].set(labels)
    return grid[target_voxel[:, 0] * size + target_voxel[:, 1]]


def _rate_grid(per_label: jax.Array, labels: jax.Array, cells: jax.Array,
               size: int) -> jax.Array:
    """(G, G) float32: each box column takes its label's value (label G * G: 0), every
    other column 0."""
    values = jnp.where(labels < size * size, per_label[labels], 0.0)
    return jnp.zeros(size * size, jnp.float32).at[cells].set(values, mode="drop").reshape(
        size, size)


def facade_rates(rates: jax.Array, sensor: SensorConfig) -> jax.Array:
    """(G, G) float32 column rates -> (G, G) int32 quantised facade rates: the largest q of
    the columns that make each column's facade top (`tops.facade_tops`)."""
    return tops.facade_tops(spec.quantised(rates, jnp), sensor)


def robot_rates(top: jax.Array, seen: jax.Array, window_known: jax.Array, cells: jax.Array,
                target_voxel: jax.Array, strength, world: WorldConfig,
                sensor: SensorConfig) -> jax.Array:
    """(G, G) int32 one robot's facade rates from its tops (G, G), the OCCUPIED voxels it
    knows per box column (C,) and the windows it knows (T,) (`jaxmripp.spec.belief`)."""
    size = world.size
    cells = cells.reshape(-1)
    known = (cells < size * size) & (top.reshape(-1)[jnp.minimum(cells, size * size - 1)] > 0)
    labels = box_labels(known.reshape(-1, world.footprint**2), cells.reshape(
        -1, world.footprint**2), world.footprint, size).reshape(-1)
    found = _sums(_window_labels(labels, cells, target_voxel, size), window_known, size)
    rho = spec.relative_rate(found, _sums(labels, seen, size), strength, prior(world), jnp)
    return facade_rates(_rate_grid(rho, labels, cells, size), sensor)


def team_rates(state: EnvState, strength, sensor: SensorConfig, world: WorldConfig
               ) -> jax.Array:
    """(N, G, G) int32 every robot's facade rates from its own map, tops and the windows it
    knows, prior strength `strength` (traced or static)."""
    n = state.position.shape[0]
    cells = building_boxes(state.world.height, world)
    known = known_windows(state.team_map, state.world.target_voxel, state.world.target_valid, n)
    seen = known_facade(state.team_map, cells.reshape(-1), n)
    return jax.vmap(robot_rates, in_axes=(0, 0, 0, None, None, None, None, None))(
        state.building_top, seen, known, cells, state.world.target_voxel, strength, world,
        sensor)


def _lowest_neighbour(height: jax.Array) -> jax.Array:
    """(G, G) the lowest of each column's four horizontal neighbours (outside the grid: 0)."""
    padded = jnp.pad(height, 1)
    return jnp.minimum(jnp.minimum(padded[:-2, 1:-1], padded[2:, 1:-1]),
                       jnp.minimum(padded[1:-1, :-2], padded[1:-1, 2:]))


def surface(height: jax.Array) -> jax.Array:
    """(G, G) int32 the building voxels of each column with a face open to the air: the
    part of the column above its lowest horizontal neighbour (outside the grid: 0), and
    at least its roof voxel."""
    return jnp.where(height > 0, jnp.maximum(height - _lowest_neighbour(height), 1), 0)


def window_voxels(height: jax.Array, world: WorldConfig) -> jax.Array:
    """(G, G, G) bool the building voxels that can hold a window: with facade windows
    (`world.target_placement`) those with a side face open to the air, i.e. above their
    column's lowest horizontal neighbour (the roofs of `surface` left out); with windows
    inside footprints every building voxel."""
    z = jnp.arange(height.shape[0])
    solid = z < height[..., None]
    if world.target_placement != "facade":
        return solid
    return solid & (z >= _lowest_neighbour(height)[..., None])


def true_rates(state: EnvState, sensor: SensorConfig, world: WorldConfig) -> jax.Array:
    """(N, G, G) int32 facade rates from the truth: for each real building, the windows the
    robot's map does not hold over the surface voxels it does not hold (at least 1),
    relative to the prior m, quantised as `jaxmripp.spec.belief` quantises rho."""
    n, size = state.position.shape[0], world.size
    cells = building_boxes(state.world.height, world)
    flat = cells.reshape(-1)
    # A real building's label: its box's smallest building column.
    labels = jnp.broadcast_to(jnp.min(cells, axis=1, keepdims=True), cells.shape).reshape(-1)
    labels = jnp.where(flat < size * size, labels, size * size)
    window_labels = _window_labels(labels, flat, state.world.target_voxel, size)
    windows = _sums(window_labels, state.world.target_valid, size)
    outside = jnp.append(surface(state.world.height).reshape(-1), 0)[flat]
    total = _sums(labels, outside, size)
    known = known_windows(state.team_map, state.world.target_voxel, state.world.target_valid, n)

    def one(known_i, seen_i):
        left = windows - _sums(window_labels, known_i, size)
        unseen = jnp.maximum(total - _sums(labels, seen_i, size), 1.0)
        return facade_rates(_rate_grid(left / unseen / jnp.float32(prior(world)), labels,
                                       flat, size), sensor)

    return jax.vmap(one)(known, known_facade(state.team_map, flat, n))


def rates_for(source: str, strength, sensor: SensorConfig, world: WorldConfig):
    """state -> (N, G, G) the facade rates a belief-weighted lookahead weighs by: the
    robot's own posterior (`source` = "belief", `team_rates` at prior strength `strength`)
    or the truth's (`source` = "truth", `true_rates`: privileged, references only)."""
    if source == "belief":
        return lambda state: team_rates(state, strength, sensor, world)
    if source == "truth":
        return lambda state: true_rates(state, sensor, world)
    raise ValueError(f"rates source {source!r}; allowed: belief, truth")
