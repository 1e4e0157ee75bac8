"""Occupancy codes, headings and the traversal rule of a line of flight.

Positions live in the unit cube [0, 1]^3; a world of G voxels per side maps position p to
voxel floor(p G), clipped to the grid, and a map is a C-ordered (G, G, G) grid of codes.
A pose is (x, y, z, heading angle); the four headings are +x, +y, -x, -y at angles
0, pi/2, pi, 3 pi/2.

A line of flight from s to e *traverses* every voxel that contains a point of the closed
segment s + t (e - s), t in [0, 1], with voxels as the half-open cells
[i, i + 1) / G that `voxel_of` assigns points to (clipped into the grid). Nothing is
sampled, so no corner can be stepped over. In voxel units (x G), with d = e - s:

- the flight starts in voxel floor(s) and, for t just above 0, is in its *leaving* voxel:
  per axis floor(s_a) if d_a >= 0, else ceil(s_a) - 1;
- it crosses the integer planes strictly between s_a and e_a on each axis a, at
  t = (p - s_a) / d_a; `traversal_steps(G, max_length)` bounds the number of distinct
  crossing times of any segment a candidate can have (the fixed shapes of the JAX side);
- after the crossings with t' <= t, its index on axis a is the leaving index moved by
  sign(d_a) per crossing of that axis; at a crossing point itself, the index on an axis
  with d_a < 0 still counts only crossings t' < t (the point lies on the plane, which
  belongs to the cell above it);
- it ends in voxel floor(e).

So a segment through a voxel's corner or edge visits the voxels that own the points it
passes, a segment lying in a voxel face visits the cells on the face's upper side, and a
zero-length segment visits its own voxel. The t values come from one float32 subtraction
and division each (no fused arithmetic), so the JAX side (`jaxmripp.sim.geometry`) and the
runtime (`jaxmripp.runtime.mapping`) visit the same voxels bit for bit. Every use of a line
of flight -- candidate masks, the truth a flight is checked against, the tree search's
model, the onboard safety filter -- goes through this rule.
"""

from __future__ import annotations

import math

import numpy as np

FREE, UNKNOWN, OCCUPIED = 0, 1, 2

N_HEADINGS = 4
HEADING_ANGLES = np.arange(N_HEADINGS, dtype=np.float32) * np.float32(math.pi / 2)
HEADING_VECTORS = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=np.float32)
HEADING_NAMES = ("+x", "+y", "-x", "-y")


def traversal_steps(size: int, max_length: float) -> int:
    """Distinct crossing times of a segment of at most max_length: axis a has at most
    ceil(|d_a|) crossings and sum |d_a| <= sqrt(3) |d|, plus one for rounding."""
    return int(math.floor(math.sqrt(3.0) * max_length * size)) + 4
