"""The JAX implementation of `jaxmripp.spec.grid`: voxel indexing and segment points.

Codes, headings and the segment sample count are defined in the spec and re-exported here
for the simulation's modules.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxmripp.spec.grid import (FREE, HEADING_ANGLES, HEADING_VECTORS, N_HEADINGS,  # noqa: F401
                                OCCUPIED, UNKNOWN, segment_samples)


def voxel_of(position: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) positions -> (..., 3) int32 voxel indices, clipped into the grid."""
    return jnp.clip(jnp.floor(position * size), 0, size - 1).astype(jnp.int32)


def linear_index(voxel: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) voxel indices -> (...,) flat index into a C-ordered (G, G, G) grid."""
    return (voxel[..., 0] * size + voxel[..., 1]) * size + voxel[..., 2]


def inside_world(position: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) -> (...,) True where the position lies in the closed unit cube."""
    return jnp.all((position >= 0.0) & (position <= 1.0), axis=-1)



def segment_voxels(start: jnp.ndarray, ends: jnp.ndarray, size: int,
                   max_length: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(3,), (..., 3) -> points and voxels (..., n, 3) of the spec's segment rule.

    n = segment_samples(size, max_length) points from start (excluded) to each end
    (included), evenly spaced.
    """
    count = segment_samples(size, max_length)
    t = jnp.arange(1, count + 1, dtype=jnp.float32) / count
    points = start + t[:, None] * (ends[..., None, :] - start)
    return points, voxel_of(points, size)


def mapped_clear(start: jnp.ndarray, ends: jnp.ndarray, occupancy: jnp.ndarray, size: int,
                 max_length: float) -> jnp.ndarray:
    """(3,), (M, 3), (G, G, G) map -> (M,) True where no segment point is mapped OCCUPIED.

    Unknown voxels count as free: the robot plans optimistically and the environment
    checks the flight against the ground truth.
    """
    _, voxels = segment_voxels(start, ends, size, max_length)
    return jnp.all(occupancy.reshape(-1)[linear_index(voxels, size)] != OCCUPIED, axis=-1)


def pose(position: jnp.ndarray, heading: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) positions and (...,) heading indices -> (..., 4) poses (x, y, z, angle)."""
    angle = jnp.asarray(HEADING_ANGLES)[heading]
    return jnp.concatenate([position, angle[..., None]], axis=-1)
