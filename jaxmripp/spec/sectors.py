"""Sectors: a division of the world among the team that needs no radio.

Seen from the first take-off pad `start` (on the world's boundary, as the pads are:
`jaxmripp.spec.flight`), the ground azimuths of the unit square, measured from the
direction to its centre, span [lo, hi] (the extremes over its four corners; a quarter
turn from a corner, a half turn from the middle of an edge). Robot i of a team of N owns
the i-th of N sectors, split at N - 1 boundary azimuths b_1 < ... < b_{N-1}: a candidate
whose azimuth a has b_k <= a for exactly i of them is robot i's (so the first sector is
closed below, the last above). With `radio.sector_split = angle` the boundaries divide
[lo, hi] evenly, b_k = lo + k (hi - lo) / N; from a corner the sectors along the diagonal
then cover about twice the ground of those along the edges. With `area` each sector covers
1/N of the square: the fan from the pad through the corners, in azimuth order, is cut
where its cumulative area reaches k / N (the area up to a point on the square's boundary
grows linearly along each edge, so each cut is found within one triangle of the fan).
With `radio.sector_count = K` (K >= 1; 0: one sector per robot, robot i the i-th) the
world is cut into K sectors instead, and the robots share them in order of their take-off
pads' distance from the first pad (the pad grid's column, `jaxmripp.spec.flight`: pad
rank 0 is the first robot of the farthest column, then down that column by index, then
the next column inward): the robot of pad rank r owns sector floor(r K / N). The first
sectors lie along the pad row (from a pad on the y = start_y edge, sector 0 borders +x),
so each robot starts beside its own sector, and K < N sectors are wide enough for the
candidates around a robot to reach into them.
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

import math

import numpy as np

from jaxmripp.spec.layout import FEATURES

GAIN_COLUMN = FEATURES.index("view_unknown")
WHOLE_WORLD_RANGE = float(np.sqrt(3.0))  # the unit cube's diagonal
SPLITS = ("angle", "area")  # radio.sector_split


def applies(radio_range):
    """Whether the rule is on for this radio range (a bool, or a traced one in JAX)."""
    return radio_range < WHOLE_WORLD_RANGE


def own_sector(position, start, robot, team: int, xp=np, equal_area=False, count=0):
    """Candidate positions (..., 3), the first pad (3,), robot index (broadcasts against
    the leading axes) -> (...,) bool: the candidate lies in the robot's sector.
    `equal_area` (a bool, or a traced one in JAX): the `area` split, else `angle`;
    `count` (a number, or a traced one): radio.sector_count, 0 for one sector per robot."""
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
    shared = xp.asarray(count) > 0
    sectors = xp.where(shared, xp.asarray(count, lo.dtype), xp.asarray(team, lo.dtype))
    # K sectors need K - 1 cuts; the team's N - 1 slots hold them and the rest stay at
    # +inf, where no azimuth reaches.
    k = xp.arange(1, team, dtype=lo.dtype)
    even = lo + (hi - lo) * k / sectors
    bounds = xp.where(equal_area,
                      _equal_area_bounds(offset, away, corner_azimuth, k, sectors, xp,
                                         azimuth_of),
                      even)
    bounds = xp.where(k < sectors, bounds, xp.inf)
    sector = xp.where(shared, xp.floor(pad_rank(robot, team, xp) * sectors / team),
                      xp.asarray(robot))
    return xp.sum(azimuth[..., None] >= bounds, axis=-1) == sector


def pad_rank(robot, team: int, xp=np):
    """Robot indices (any shape) -> their pads' rank, the farthest column from the first
    pad first and by index within a column (pads of `jaxmripp.spec.flight`: robot i in
    column i mod m, row i div m, m = ceil(sqrt N))."""
    side = math.ceil(math.sqrt(team))
    robot = xp.asarray(robot)
    column = xp.arange(side)
    per_column = (team - column + side - 1) // side  # robots whose pads are in each column
    farther = xp.where(column > (robot % side)[..., None], per_column, 0)
    return xp.sum(farther, axis=-1) + robot // side


def _equal_area_bounds(offset, away, corner_azimuth, k, sectors, xp, azimuth_of):
    """(team - 1,) azimuths that cut the square where the fan from the pad has swept k /
    `sectors` of its area, for the cut indices k (team - 1,), from the corners' offsets
    from the pad (4, 2)."""
    # The corners in azimuth order; one at the pad goes last, and its zero offset gives
    # the triangles it bounds no area.
    fan = offset[xp.argsort(xp.where(away, corner_azimuth, xp.inf))]
    side = 0.5 * xp.abs(fan[:-1, 0] * fan[1:, 1] - fan[:-1, 1] * fan[1:, 0])  # (3,)
    reached = xp.concatenate([xp.zeros(1, side.dtype), xp.cumsum(side)])  # (4,)
    target = reached[-1] * k / sectors
    tri = xp.minimum(xp.sum(reached[None, 1:3] <= target[:, None], axis=-1), 2)
    along = (target - reached[tri]) / xp.maximum(side[tri], 1e-12)
    cut = fan[tri] + along[:, None] * (fan[tri + 1] - fan[tri])
    return azimuth_of(cut[:, 0], cut[:, 1])


def offered(mask, features, position, start, robot, team: int, xp=np, equal_area=False,
            count=0):
    """(..., L) mask, (..., L, F) features and (..., L, 3) positions of a robot's
    candidates -> (..., L) the mask the rule offers it (`own_sector`, `sector_mask`);
    the rest as `own_sector` takes them."""
    own = own_sector(position, start, robot, team, xp=xp, equal_area=equal_area, count=count)
    return sector_mask(mask, features, own)


def sector_mask(mask, features, own):
    """(..., L) mask, (..., L, F) features, (..., L) `own_sector` -> (..., L) the mask
    the robot is offered."""
    useful = mask & own & (features[..., GAIN_COLUMN] > 0)
    keep = useful.any(axis=-1)[..., None]
    return (useful & keep) | (mask & ~keep)
