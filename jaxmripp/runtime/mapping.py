"""A robot's own occupancy map and the geometry it needs, in NumPy.

Codes, headings and the segment rule are those of `jaxmripp.spec.grid`; this module is
their NumPy implementation (`jaxmripp.sim.geometry` is the JAX one).

Two segment tests:
- `sampled_clear`: the candidate rule of jaxmripp.sim.geometry.mapped_clear (the spec's
  segment points), used to sample candidates exactly as the JAX env does;
- `exact_clear`: every voxel whose interior the segment passes through, start voxel
  included (a voxel traversal, no sampling), used by the safety filter, so a returned pose
  never crosses a voxel the robot knows to be occupied, not even at a corner the sampled
  rule steps over.
"""

from __future__ import annotations

import math

import numpy as np

from jaxmripp.spec.grid import (HEADING_ANGLES, HEADING_VECTORS, N_HEADINGS, OCCUPIED,  # noqa: F401
                                UNKNOWN, segment_samples)


def voxel_of(position: np.ndarray, size: int) -> np.ndarray:
    """(..., 3) positions -> (..., 3) int voxel indices, clipped into the grid."""
    return np.clip(np.floor(position * np.float32(size)), 0, size - 1).astype(np.int64)


def linear_index(voxel: np.ndarray, size: int) -> np.ndarray:
    """(..., 3) voxel indices -> (...,) flat index into a C-ordered (G, G, G) grid."""
    return (voxel[..., 0] * size + voxel[..., 1]) * size + voxel[..., 2]


def inside_world(position: np.ndarray) -> np.ndarray:
    return np.all((position >= 0.0) & (position <= 1.0), axis=-1)


def segment_voxels(start: np.ndarray, ends: np.ndarray, size: int,
                   max_length: float) -> tuple[np.ndarray, np.ndarray]:
    """(3,), (M, 3) -> points and voxels (M, n, 3) of the spec's segment rule
    (`jaxmripp.spec.grid`; `jaxmripp.sim.geometry.segment_voxels` in JAX)."""
    count = segment_samples(size, max_length)
    t = np.arange(1, count + 1, dtype=np.float32) / np.float32(count)
    points = start + t[None, :, None] * (ends - start)[:, None, :]
    return points, voxel_of(points, size)


class OccupancyMap:
    """One robot's (G, G, G) map, stored flat; every voxel starts UNKNOWN."""

    def __init__(self, size: int):
        self.size = size
        self.codes = np.full(size ** 3, UNKNOWN, np.int8)

    @property
    def grid(self) -> np.ndarray:
        """(G, G, G) view of the codes."""
        return self.codes.reshape(self.size, self.size, self.size)

    def update(self, flat: np.ndarray, values: np.ndarray) -> None:
        """Sets observed voxels (flat indices in [0, G^3)) to their codes; later wins."""
        self.codes[flat] = values

    def mark_occupied(self, voxel: np.ndarray) -> None:
        self.codes[linear_index(np.asarray(voxel), self.size)] = OCCUPIED

    def sampled_clear(self, start: np.ndarray, ends: np.ndarray, max_length: float) -> np.ndarray:
        """(3,), (M, 3) -> (M,) True where no half-voxel sample is mapped OCCUPIED.

        jaxmripp.sim.geometry.mapped_clear: the sample count is fixed by the longest
        segment (max_length); unknown voxels count as free.
        """
        _, voxels = segment_voxels(start, ends, self.size, max_length)
        return np.all(self.codes[linear_index(voxels, self.size)] != OCCUPIED, axis=-1)

    def exact_clear(self, start: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """(3,), (M, 3) -> (M,) True where no voxel the segment passes through is OCCUPIED.

        In voxel units, the segment s + t (e - s), t in [0, 1], crosses the integer planes
        strictly between s and e along each axis; between consecutive crossings it stays in
        one voxel, named by the midpoint. Zero-length pieces (passing exactly through an
        edge or corner) touch but do not enter a voxel and are skipped. Float64 throughout.
        """
        g = self.size
        s = np.asarray(start, np.float64) * g
        e = np.asarray(ends, np.float64).reshape(-1, 3) * g
        d = e - s  # (M, 3)
        lo, hi = np.minimum(s, e), np.maximum(s, e)
        span = int(math.ceil(float(np.max(hi - lo, initial=0.0)))) + 1
        planes = np.floor(lo)[..., None] + np.arange(1, span + 1)  # (M, 3, span)
        crossing = planes < hi[..., None]
        safe_d = np.where(d == 0.0, 1.0, d)[..., None]
        t = np.where(crossing, (planes - s[None, :, None]) / safe_d, 1.0).reshape(len(e), -1)
        ends_t = np.zeros((len(e), 1)), np.ones((len(e), 1))
        t = np.sort(np.concatenate([ends_t[0], t, ends_t[1]], axis=1), axis=1)
        mid = 0.5 * (t[:, 1:] + t[:, :-1])
        real = (t[:, 1:] - t[:, :-1]) > 1e-12
        real[:, 0] |= ~real.any(axis=1)  # a zero-length segment: its own voxel
        points = s + mid[..., None] * d[:, None, :]
        voxel = np.clip(np.floor(points), 0, g - 1).astype(np.int64)
        hit = self.codes[linear_index(voxel, g)] == OCCUPIED
        return ~np.any(hit & real, axis=1)
