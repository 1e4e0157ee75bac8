"""Building tops (`jaxmripp.spec.view`): per robot and column, 1 + the highest z its map
holds OCCUPIED, and the facade tops they give (`sensor.gain_facade`) that mark which
unknown voxels the view gain counts as facade. The NumPy side is in
`jaxmripp.runtime.view`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import SensorConfig
from jaxmripp.sim.geometry import OCCUPIED
from jaxmripp.sim.sensing import CastResult, scatter_max


def empty_tops(size: int) -> jax.Array:
    """(G, G) int8 building tops of an empty map: no column has a known building."""
    return jnp.zeros((size, size), jnp.int8)


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
