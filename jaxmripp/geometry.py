"""Shared geometry: headings, voxel indexing, occupancy codes and segment sampling.

Positions are in the unit cube [0, 1]^3; a world of G voxels per side maps position p to
voxel floor(p * G) (clipped to the grid). A pose is (x, y, z, heading angle).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

# Per-robot occupancy map codes (design.md section 1).
FREE, UNKNOWN, OCCUPIED = 0, 1, 2

# The four headings d in {0, pi/2, pi, 3pi/2}: +x, +y, -x, -y.
N_HEADINGS = 4
HEADING_ANGLES = np.arange(N_HEADINGS, dtype=np.float32) * np.float32(math.pi / 2)
HEADING_VECTORS = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=np.float32)


def voxel_of(position: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) positions -> (..., 3) int32 voxel indices, clipped into the grid."""
    return jnp.clip(jnp.floor(position * size), 0, size - 1).astype(jnp.int32)


def linear_index(voxel: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) voxel indices -> (...,) flat index into a C-ordered (G, G, G) grid."""
    return (voxel[..., 0] * size + voxel[..., 1]) * size + voxel[..., 2]


def inside_world(position: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) -> (...,) True where the position lies in the closed unit cube."""
    return jnp.all((position >= 0.0) & (position <= 1.0), axis=-1)


def segment_samples(size: int, max_length: float) -> int:
    """Samples needed to step a segment of max_length at half-voxel spacing."""
    return max(2, int(math.ceil(2 * max_length * size)) + 1)


def segment_points(start: jnp.ndarray, end: jnp.ndarray, count: int) -> jnp.ndarray:
    """(3,), (3,) -> (count, 3) evenly spaced points from start (excluded) to end (included)."""
    t = jnp.arange(1, count + 1, dtype=jnp.float32) / count
    return start + t[:, None] * (end - start)


def pose(position: jnp.ndarray, heading: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) positions and (...,) heading indices -> (..., 4) poses (x, y, z, angle)."""
    angle = jnp.asarray(HEADING_ANGLES)[heading]
    return jnp.concatenate([position, angle[..., None]], axis=-1)
