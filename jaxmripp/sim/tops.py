"""Building tops (`jaxmripp.spec.view`): per robot and column, 1 + the highest z its map
holds OCCUPIED and the lowest z it holds FREE, kept as casts and bumps write the map (its
codes are the truth, so a FREE voxel stays FREE and a kept lowest stays the lowest), the
box tops those two give (`sensor.gain_tops=boxes`), and the facade tops
(`sensor.gain_facade`) that mark which unknown voxels the view gain counts as facade.
The NumPy side is in `jaxmripp.runtime.view`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import SensorConfig
from jaxmripp.sim.geometry import FREE, OCCUPIED
from jaxmripp.sim.sensing import CastResult, scatter_max, scatter_min


def empty_tops(size: int) -> jax.Array:
    """(G, G) int8 building tops of an empty map: no column has a known building."""
    return jnp.zeros((size, size), jnp.int8)


def empty_lowest_free(size: int) -> jax.Array:
    """(G, G) int8 lowest FREE z of an empty map: G, no column has a known FREE voxel."""
    return jnp.full((size, size), size, jnp.int8)


def raise_tops(top: jax.Array, voxels: jax.Array, values: jax.Array) -> jax.Array:
    """(G, G) int8 tops after writing codes `values` at flat voxel indices `voxels` (G**3
    and beyond: nothing written): a voxel written OCCUPIED raises its column to z + 1."""
    size = top.shape[0]
    voxels, values = jnp.atleast_1d(voxels), jnp.atleast_1d(values)
    written = (voxels < size**3) & (values == OCCUPIED)
    column = jnp.where(written, voxels // size, size * size)
    height = ((voxels % size) + 1).astype(jnp.int8)
    return scatter_max(top.reshape(-1), column, height).reshape(top.shape)


def raise_tops_from_cast(top: jax.Array, cast: CastResult) -> jax.Array:
    """`raise_tops` with a cast's observed voxels and codes."""
    return raise_tops(top, cast.voxels, cast.values)


def lower_free(lowest_free: jax.Array, voxels: jax.Array, values: jax.Array) -> jax.Array:
    """(G, G) int8 lowest FREE z after writing codes `values` at flat voxel indices `voxels`
    (G**3 and beyond: nothing written): a voxel written FREE lowers its column to z."""
    size = lowest_free.shape[0]
    voxels, values = jnp.atleast_1d(voxels), jnp.atleast_1d(values)
    written = (voxels < size**3) & (values == FREE)
    column = jnp.where(written, voxels // size, size * size)
    z = (voxels % size).astype(jnp.int8)
    return scatter_min(lowest_free.reshape(-1), column, z).reshape(lowest_free.shape)


def lower_free_from_cast(lowest_free: jax.Array, cast: CastResult) -> jax.Array:
    """`lower_free` with a cast's observed voxels and codes."""
    return lower_free(lowest_free, cast.voxels, cast.values)


def box_tops(top: jax.Array, lowest_free: jax.Array, side: int) -> jax.Array:
    """(G, G) int8 tops and lowest FREE z of a map -> (G, G) int8 its box tops
    (`jaxmripp.spec.view`) for boxes of `side` x `side` columns."""
    size = top.shape[0]
    zero, box = jnp.int8(0), (side, side)
    # Per box, indexed by its low corner: its highest top, and whether it is possible.
    box_top = jax.lax.reduce_window(top, zero, jax.lax.max, box, (1, 1), "VALID")
    box_free = jax.lax.reduce_window(lowest_free, jnp.int8(size), jax.lax.min, box, (1, 1),
                                     "VALID")
    possible = jnp.where((box_top > 0) & (box_free >= box_top), box_top, zero)
    # Per column, the largest over the boxes that hold it: those whose low corner lies
    # within side - 1 below it on both axes.
    spread = jax.lax.reduce_window(jnp.pad(possible, side - 1), zero, jax.lax.max, box,
                                   (1, 1), "VALID")
    return jnp.maximum(top, spread)


def _shifted_max(top: jax.Array, axis: int) -> jax.Array:
    """(G, G) -> (G, G) the largest of each column and its two neighbours along `axis`
    (outside the grid: 0)."""
    edge = jnp.zeros_like(jax.lax.slice_in_dim(top, 0, 1, axis=axis))
    up = jnp.concatenate([jax.lax.slice_in_dim(top, 1, None, axis=axis), edge], axis=axis)
    down = jnp.concatenate([edge, jax.lax.slice_in_dim(top, 0, -1, axis=axis)], axis=axis)
    return jnp.maximum(jnp.maximum(up, down), top)


def nearby_tops(top: jax.Array) -> jax.Array:
    """(G, G) -> (G, G) the largest top of each column and its four neighbours."""
    # Shifted copies in the tops' own int8: on XLA:CPU an int32 conversion of a batch of
    # tops (E, N, G, G) costs many times what the maxima cost.
    return jnp.maximum(_shifted_max(top, 0), _shifted_max(top, 1))


def around_tops(top: jax.Array) -> jax.Array:
    """(G, G) -> (G, G) the largest top of each column and its eight neighbours (the 3 x 3
    maximum, as a maximum along x, then along y)."""
    return _shifted_max(_shifted_max(top, 0), 1)


def facade_tops(top: jax.Array, sensor: SensorConfig) -> jax.Array:
    """(G, G) tops -> (G, G) the tops that mark facade voxels (`sensor.gain_facade`)."""
    if sensor.gain_facade == "nearby":
        return nearby_tops(top)
    if sensor.gain_facade == "around":
        return around_tops(top)
    return top
