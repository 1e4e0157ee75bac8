"""The JAX implementation of `jaxmripp.spec.view`: building tops, the view gain of
candidate poses on a robot's map and the distance to the robots heard.

Per robot and step the gain costs K * 4 * R * S two-table lookups (K candidate positions,
4 headings, R rays, S samples), all from one static table; the four headings of a
position share its voxel. Layouts keep the sample axis leading so that the clear-line
test runs as S whole-array steps instead of a scan over a trailing axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.config import SensorConfig
from jaxmripp.sim import geometry
from jaxmripp.sim.geometry import OCCUPIED, UNKNOWN
from jaxmripp.sim.sensing import CastResult, take_flat
from jaxmripp.spec import view as spec


def samples_per_pose(sensor: SensorConfig, size: int) -> int:
    """R * S: the gain samples of one pose."""
    return spec.RAYS_PER_SIDE**2 * spec.samples_per_ray(sensor.range, size)


def empty_tops(size: int) -> jax.Array:
    """(G, G) int8 building tops of an empty map: no column has a known building."""
    return jnp.zeros((size, size), jnp.int8)


def raise_tops(top: jax.Array, voxels: jax.Array, values: jax.Array) -> jax.Array:
    """(G, G) int8 tops after writing codes `values` at flat voxel indices `voxels` (G**3
    and beyond: nothing written): a voxel written OCCUPIED raises its column to z + 1."""
    size = top.shape[0]
    written = (voxels < size**3) & (values == OCCUPIED)
    column = jnp.where(written, voxels // size, size * size)
    height = ((voxels % size) + 1).astype(jnp.int8)
    return top.reshape(-1).at[column].max(height, mode="drop").reshape(top.shape)


def raise_tops_from_cast(top: jax.Array, cast: CastResult) -> jax.Array:
    return raise_tops(top, cast.voxels, cast.values)


def nearby_tops(top: jax.Array) -> jax.Array:
    """(G, G) -> (G, G) the largest top of each column and its four neighbours."""
    padded = jnp.pad(top, 1)
    return jnp.maximum(
        jnp.maximum(padded[1:-1, 1:-1], jnp.maximum(padded[:-2, 1:-1], padded[2:, 1:-1])),
        jnp.maximum(padded[1:-1, :-2], padded[1:-1, 2:]))


def _march(occupancy: jax.Array, top: jax.Array, position: jax.Array,
           sensor: SensorConfig, size: int):
    """Every sample of every ray of every heading from positions (K, 3): flat voxel index,
    unknown and facade flags, each (S, K, 4, R), and the weights (S,) of `gain_table`."""
    offsets, weights = spec.gain_table(sensor.fov_deg, sensor.range, size)
    # (S, 4, R) per axis: the sample axis leads (module doc).
    ox, oy, oz = (np.ascontiguousarray(np.moveaxis(offsets[..., a], 2, 0)) for a in range(3))
    camera = geometry.voxel_of(position, size)
    cx, cy, cz = (camera[:, a, None, None] for a in range(3))  # (K, 1, 1)
    codes = occupancy.reshape(-1)
    near = nearby_tops(top).reshape(-1).astype(jnp.int32)
    clear = jnp.ones((position.shape[0], *ox.shape[1:]), bool)  # (K, 4, R)
    flats, unknowns, facades = [], [], []
    for s in range(ox.shape[0]):
        x, y, z = cx + ox[s], cy + oy[s], cz + oz[s]
        inside = ((x >= 0) & (x < size) & (y >= 0) & (y < size) & (z >= 0) & (z < size))
        column = jnp.clip(x, 0, size - 1) * size + jnp.clip(y, 0, size - 1)
        flat = column * size + jnp.clip(z, 0, size - 1)
        code = take_flat(codes, flat)
        unknown = clear & inside & (code == UNKNOWN)
        column_top = take_flat(near, column)
        flats.append(flat)
        unknowns.append(unknown)
        facades.append(unknown & (column_top > 0) & (z <= column_top))
        clear = clear & inside & (code != OCCUPIED)
    return jnp.stack(flats), jnp.stack(unknowns), jnp.stack(facades), weights


def _weighted_share(flags: jax.Array, weights: np.ndarray) -> jax.Array:
    """(S, K, 4, R) flags -> (K, 4) float32: their weight over the table's whole weight."""
    scale = np.float32(1) / np.float32(flags.shape[-1] * int(weights.sum()))
    summed = jnp.zeros(flags.shape[1:], jnp.int32)
    for s in range(flags.shape[0]):  # integer sums: exact, in any order
        summed = summed + int(weights[s]) * flags[s]
    return summed.sum(-1).astype(jnp.float32) * scale


def view_gain(occupancy: jax.Array, top: jax.Array, position: jax.Array,
              sensor: SensorConfig, size: int) -> tuple[jax.Array, jax.Array]:
    """One robot's map (G, G, G) int8 and building tops (G, G) int8, positions (K, 3) ->
    (view_unknown, view_facade), each (K, 4) float32 per position and heading."""
    _, unknown, facade, weights = _march(occupancy, top, position, sensor, size)
    return _weighted_share(unknown, weights), _weighted_share(facade, weights)


def unknown_in_view(occupancy: jax.Array, top: jax.Array, position: jax.Array,
                    heading: jax.Array, sensor: SensorConfig, size: int) -> jax.Array:
    """The flat indices of the unknown samples of one pose ((3,), () int32) -> (R * S,)
    int32, G**3 for the other samples: the part of the map that pose would reveal."""
    flat, unknown, _, _ = _march(occupancy, top, position[None], sensor, size)
    flat = jnp.take(flat[:, 0], heading, axis=1)  # (S, R)
    return jnp.where(jnp.take(unknown[:, 0], heading, axis=1), flat, size**3).reshape(-1)


def per_cost(gain: jax.Array, cost: jax.Array, shell_outer: float) -> jax.Array:
    """gain * (shell[1] / max(cost, COST_FLOOR)), elementwise."""
    return gain * (jnp.float32(shell_outer) / jnp.maximum(cost, jnp.float32(spec.COST_FLOOR)))


def peer_distance(position: jax.Array, others: jax.Array, heard: jax.Array,
                  shell_outer: float) -> jax.Array:
    """Candidate positions (L, 3), all robots' positions (N, 3), heard (N,) bool -> (L,)
    min(PEER_CAP, distance to the nearest robot heard / shell[1])."""
    gap = position[:, None, :] - others[None, :, :]
    distance = jnp.sqrt(jnp.sum(gap * gap, axis=-1)) * (np.float32(1) / np.float32(shell_outer))
    distance = jnp.where(heard[None, :], distance, jnp.float32(spec.PEER_CAP))
    return jnp.minimum(jnp.min(distance, axis=-1), jnp.float32(spec.PEER_CAP))
