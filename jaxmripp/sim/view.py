"""The JAX implementation of `jaxmripp.spec.view`: building tops, the view gain of
candidate poses on a robot's map and the distance to the robots heard.

Per robot and step the gain costs K * 4 * R * S lookups (K candidate positions, 4
headings, R rays, S samples) in the map with facade marked, at static offsets from the
candidate's voxel; the four headings of a position share its voxel. The clear-line test
runs over the S distances as S whole-array steps instead of a scan over a trailing axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.config import SensorConfig
from jaxmripp.sim import geometry
from jaxmripp.sim.geometry import FREE, OCCUPIED, UNKNOWN
from jaxmripp.sim.sensing import CastResult, scatter_max, take_flat
from jaxmripp.spec import vectors
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
    voxels, values = jnp.atleast_1d(voxels), jnp.atleast_1d(values)
    written = (voxels < size**3) & (values == OCCUPIED)
    column = jnp.where(written, voxels // size, size * size)
    height = ((voxels % size) + 1).astype(jnp.int8)
    return scatter_max(top.reshape(-1), column, height).reshape(top.shape)


def raise_tops_from_cast(top: jax.Array, cast: CastResult) -> jax.Array:
    return raise_tops(top, cast.voxels, cast.values)


def nearby_tops(top: jax.Array) -> jax.Array:
    """(G, G) -> (G, G) the largest top of each column and its four neighbours."""
    padded = jnp.pad(top, 1)
    return jnp.maximum(
        jnp.maximum(padded[1:-1, 1:-1], jnp.maximum(padded[:-2, 1:-1], padded[2:, 1:-1])),
        jnp.maximum(padded[1:-1, :-2], padded[1:-1, 2:]))


def facade_tops(top: jax.Array, sensor: SensorConfig) -> jax.Array:
    """(G, G) tops -> (G, G) the tops that mark facade voxels (`sensor.gain_facade`)."""
    return nearby_tops(top) if sensor.gain_facade == "nearby" else top


FACADE = 3  # the gain's own code for an UNKNOWN voxel that is facade (jaxmripp.spec.view)


def _marked_map(occupancy: jax.Array, top: jax.Array, sensor: SensorConfig,
                size: int) -> jax.Array:
    """The map as the gain reads it, flat (G**3,) int8: FACADE for unknown facade voxels
    and, without occlusion, known buildings marked FREE (then only leaving the grid,
    coded OCCUPIED by `_codes`, stops a ray). XLA fuses it into the reads of `_codes`:
    each sample reads its voxel's code and its column's facade top."""
    near = facade_tops(top, sensor)[:, :, None]
    height = jnp.arange(size, dtype=jnp.int8)[None, None, :]
    known = occupancy if sensor.gain_occlusion else \
        jnp.where(occupancy == OCCUPIED, jnp.int8(FREE), occupancy)
    return jnp.where((occupancy == UNKNOWN) & (near > 0) & (height <= near),
                     jnp.int8(FACADE), known).reshape(-1)


def _sample_major(sensor: SensorConfig, size: int) -> tuple[np.ndarray, np.ndarray]:
    """`spec.gain_table` with the sample axis before the rays: offsets (4, S, R, 3) and
    weights (S,), so that the clear-line test steps over leading sample slices."""
    offsets, weights = spec.gain_table(sensor.fov_deg, sensor.range, size)
    return np.moveaxis(offsets, 2, 1), weights


def _codes(marked: jax.Array, camera: jax.Array, offsets: jax.Array,
           size: int) -> tuple[jax.Array, jax.Array]:
    """Camera voxels (..., 3) plus voxel offsets (..., 3) (broadcast) -> the samples' flat
    voxel indices and codes from `_marked_map`, OCCUPIED outside the grid."""
    x, y, z = (camera[..., a] + offsets[..., a] for a in range(3))
    inside = (x >= 0) & (x < size) & (y >= 0) & (y < size) & (z >= 0) & (z < size)
    flat = geometry.linear_index(jnp.stack([jnp.clip(v, 0, size - 1) for v in (x, y, z)], -1),
                                 size)
    return flat, jnp.where(inside, take_flat(marked, flat), jnp.int8(OCCUPIED))


def view_gain(occupancy: jax.Array, top: jax.Array, position: jax.Array,
              sensor: SensorConfig, size: int) -> tuple[jax.Array, jax.Array]:
    """One robot's map (G, G, G) int8 and building tops (G, G) int8, positions (K, 3) ->
    (view_unknown, view_facade), each (K, 4) float32 per position and heading."""
    offsets, weights = _sample_major(sensor, size)
    rays = spec.RAYS_PER_SIDE**2
    # Samples (K, 4 * R) at one distance at a time, their voxels computed where they are
    # read: XLA then fuses the whole sum into one pass, where (S, K * 4 * R) coordinate
    # arrays would be written to memory and read back.
    per_distance = np.moveaxis(offsets, 1, 0).reshape(len(weights), 1, -1, 3)
    marked = _marked_map(occupancy, top, sensor, size)
    camera = geometry.voxel_of(position, size)[:, None, :]
    total = rays * int(weights.sum())
    scale = np.float32(1) / np.float32(total)
    # Integer sums, exact in any order. While both totals fit 15 bits (ranges up to about
    # 75 voxels) they share one int32, unknown weight in the low 16 bits and facade weight
    # above, so each sample costs one accumulation instead of two.
    packed = total < 1 << 15
    unknown_sum = jnp.zeros((position.shape[0], 4 * rays), jnp.int32)
    facade_sum = jnp.zeros_like(unknown_sum)
    clear = jnp.ones(unknown_sum.shape, bool)
    for s, w in enumerate(weights.astype(int)):
        _, code = _codes(marked, camera, per_distance[s], size)
        unknown = clear & ((code == UNKNOWN) | (code == FACADE))
        facade = clear & (code == FACADE)
        if packed:
            unknown_sum = unknown_sum + jnp.where(unknown, jnp.int32(w), 0) \
                + jnp.where(facade, jnp.int32(w << 16), 0)
        else:
            unknown_sum = unknown_sum + jnp.where(unknown, jnp.int32(w), 0)
            facade_sum = facade_sum + jnp.where(facade, jnp.int32(w), 0)
        clear = clear & (code != OCCUPIED)
    unknown_sum = unknown_sum.reshape(position.shape[0], 4, rays).sum(-1)
    if packed:
        unknown_sum, facade_sum = unknown_sum & 0xFFFF, unknown_sum >> 16
    else:
        facade_sum = facade_sum.reshape(position.shape[0], 4, rays).sum(-1)
    return unknown_sum.astype(jnp.float32) * scale, facade_sum.astype(jnp.float32) * scale


def unknown_in_view(occupancy: jax.Array, top: jax.Array, position: jax.Array,
                    heading: jax.Array, sensor: SensorConfig, size: int) -> jax.Array:
    """The flat indices of the unknown samples of one pose ((3,), () int32) -> (R * S,)
    int32, G**3 for the other samples: the part of the map that pose would reveal."""
    offsets, _ = _sample_major(sensor, size)
    camera = geometry.voxel_of(position, size)
    flat, code = _codes(_marked_map(occupancy, top, sensor, size), camera,
                        jnp.asarray(offsets)[heading], size)  # (S, R)
    blocked = jnp.cumsum(code == OCCUPIED, axis=0) - (code == OCCUPIED) > 0
    unknown = ~blocked & ((code == UNKNOWN) | (code == FACADE))
    return jnp.where(unknown, flat, size**3).reshape(-1)


def per_cost(gain: jax.Array, cost: jax.Array, shell_outer: float) -> jax.Array:
    """gain * (shell[1] / max(cost, COST_FLOOR)), elementwise."""
    return gain * (jnp.float32(shell_outer) / jnp.maximum(cost, jnp.float32(spec.COST_FLOOR)))


def peer_distance(position: jax.Array, others: jax.Array, heard: jax.Array,
                  shell_outer: float) -> jax.Array:
    """Candidate positions (L, 3), all robots' positions (N, 3), heard (N,) bool -> (L,)
    min(PEER_CAP, distance to the nearest robot heard / shell[1])."""
    gap = vectors.components(position[:, None, :] - others[None, :, :])
    distance = jnp.sqrt(vectors.dot(gap, gap, jnp)) * (np.float32(1) / np.float32(shell_outer))
    distance = jnp.where(heard[None, :], distance, jnp.float32(spec.PEER_CAP))
    return jnp.minimum(jnp.min(distance, axis=-1), jnp.float32(spec.PEER_CAP))
