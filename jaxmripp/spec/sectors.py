"""Sectors: a division of the world among the team that needs no radio.

Seen from the first take-off pad `start` (on the world's boundary, as the pads are:
`jaxmripp.spec.flight`), the ground azimuths of the unit square, measured from the
direction to its centre, span [lo, hi] (the extremes over its four corners; a quarter
turn from a corner, a half turn from the middle of an edge). Robot i of a team of N owns
the i-th of N sectors, split at the N - 1 boundary azimuths b_k = lo + k (hi - lo) / N
(equal azimuth spans): a candidate whose azimuth a has b_k <= a for exactly i of them is
robot i's (so the first sector is closed below, the last above). From a corner the
sectors along the diagonal cover about twice the ground of those along the edges.
A robot is offered only the candidates in its own sector that have unknown voxels in view
(view_unknown > 0, `jaxmripp.spec.layout`) while it has any; once its sector offers none,
its whole mask. Robots that rarely hear each other (a short radio
range) thus still look at different parts of the world until their own part is seen.
The rule applies only to a radio range shorter than the unit cube's diagonal: a radio
that reaches across the whole world connects the team wherever it flies, and the robots
then divide the work by what they tell each other (shared maps, claims) instead.

Plain indexing and arithmetic with `xp` (numpy or jax.numpy), so both sides share it.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.spec.layout import FEATURES

GAIN_COLUMN = FEATURES.index("view_unknown")
WHOLE_WORLD_RANGE = float(np.sqrt(3.0))  # the unit cube's diagonal


def applies(radio_range):
    """Whether the rule is on for this radio range (a bool, or a traced one in JAX)."""
    return radio_range < WHOLE_WORLD_RANGE


def own_sector(position, start, robot, team: int, xp=np):
    """Candidate positions (..., 3), the first pad (3,), robot index (broadcasts against
    the leading axes) -> (...,) bool: the candidate lies in the robot's sector."""
    # Azimuths are measured from the direction to the square's centre, so the span of a
    # pad on any edge is one interval within (-pi, pi] (from the y = 1 edge it would
    # straddle the +-pi cut).
    inward = xp.arctan2(0.5 - start[1], 0.5 - start[0])

    def azimuth_of(dx, dy):
        return xp.mod(xp.arctan2(dy, dx) - inward + np.pi, 2 * np.pi) - np.pi

    corners = xp.asarray([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], xp.float32)
    offset = corners - start[:2]
    # A corner at the pad itself has no azimuth: it must not widen the span.
    away = xp.sum(offset * offset, axis=-1) > 0
    corner_azimuth = azimuth_of(offset[:, 0], offset[:, 1])
    lo = xp.min(xp.where(away, corner_azimuth, xp.inf))
    hi = xp.max(xp.where(away, corner_azimuth, -xp.inf))
    azimuth = azimuth_of(position[..., 0] - start[0], position[..., 1] - start[1])
    k = xp.arange(1, team, dtype=lo.dtype)
    bounds = lo + (hi - lo) * k / xp.asarray(team, lo.dtype)
    return xp.sum(azimuth[..., None] >= bounds, axis=-1) == robot


def offered(mask, features, position, start, robot, team: int, xp=np):
    """(..., L) mask, (..., L, F) features and (..., L, 3) positions of a robot's
    candidates -> (..., L) the mask the rule offers it (`own_sector`, `sector_mask`);
    the rest as `own_sector` takes them."""
    return sector_mask(mask, features, own_sector(position, start, robot, team, xp=xp))


def sector_mask(mask, features, own):
    """(..., L) mask, (..., L, F) features, (..., L) `own_sector` -> (..., L) the mask
    the robot is offered."""
    useful = mask & own & (features[..., GAIN_COLUMN] > 0)
    keep = useful.any(axis=-1)[..., None]
    return (useful & keep) | (mask & ~keep)
