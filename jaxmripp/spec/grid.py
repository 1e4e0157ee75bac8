"""Occupancy codes, headings and the segment rule.

Positions live in the unit cube [0, 1]^3; a world of G voxels per side maps position p to
voxel floor(p G), clipped to the grid, and a map is a C-ordered (G, G, G) grid of codes.
A pose is (x, y, z, heading angle); the four headings are +x, +y, -x, -y at angles
0, pi/2, pi, 3 pi/2.

A line of flight from s to e is tested at `segment_samples(G, max_length)` evenly spaced
points s + k/n (e - s), k = 1..n (the start excluded, the end included): half-voxel
spacing for the longest segment a candidate can have, the same count for every segment
so that shapes stay static. The JAX side (`jaxmripp.sim.geometry`) and the runtime
(`jaxmripp.runtime.mapping`) implement exactly this rule.
"""

from __future__ import annotations

import math

import numpy as np

FREE, UNKNOWN, OCCUPIED = 0, 1, 2

N_HEADINGS = 4
HEADING_ANGLES = np.arange(N_HEADINGS, dtype=np.float32) * np.float32(math.pi / 2)
HEADING_VECTORS = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=np.float32)
HEADING_NAMES = ("+x", "+y", "-x", "-y")


def segment_samples(size: int, max_length: float) -> int:
    """Samples needed to step a segment of max_length at half-voxel spacing."""
    return max(2, int(math.ceil(2 * max_length * size)) + 1)
