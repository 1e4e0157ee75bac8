"""Target belief: where the windows a robot has not found yet are likely to be.

The view gain (`jaxmripp.spec.view`) counts the unknown facade a pose would see, but
windows cluster: the world generator gives each building a Dirichlet(1) share of the
city's windows (`jaxmripp.sim.world`), so what a team has already found on a building
says how much is left there. This rule turns a robot's map into a posterior rate of
windows per unseen facade voxel for every building it knows, and weighs the facade a pose
would see by it. The JAX side is `jaxmripp.sim.belief` (with the gain of
`jaxmripp.sim.view`), the onboard one `jaxmripp.runtime.belief` (with the gain of
`jaxmripp.runtime.view`); the rule below is what both follow.

What the rule reads: the robot's map (with `radio.share_maps` what it and the robots it
heard have seen), its building tops (`jaxmripp.spec.view`) and the windows it knows: the
mapped voxels that its classifier, or a peer's, reported as windows. Each window is a
building voxel, so a window is known exactly when its voxel is mapped (the simulator
takes the flag from the world's window list wherever the voxel is mapped; the runtime
keeps it as one more bit per OCCUPIED voxel, set from its classifier's reports and merged
with the map: the map deltas carry it, `jaxmripp.spec.protocol`).

Buildings
    A *known building column* is a column whose top is > 0. Known building columns that
    touch, sides or corners (8-connectivity), form one *building*; its label is the
    smallest flat column index x G + y among its columns. With `world.clearance` >= 1 the
    columns of two different buildings differ by at least 2 in x or in y, so they never
    touch and a building never spans two real ones. What a robot has seen of one real
    building may fall apart (two opposite walls and nothing between them): each part is
    then a building of its own, and the parts join once a corner or roof that links them
    is mapped. Buildings nobody has seen are not in the belief: their windows are reached
    through the unknown space of the view gain, and once a wall of one is mapped it
    enters with the prior.

Counts per building b
    n_b  the voxels of b's columns that are mapped OCCUPIED (the facade seen so far)
    f_b  the known windows whose column is one of b's

Posterior
    Each facade voxel of a building holds a window with a small probability; as a Poisson
    rate lambda_b per voxel with a Gamma prior of mean m (PRIOR below, from the world
    generator's statistics) and strength k (pseudo-windows: shape k, rate k / m), the
    posterior mean after n_b voxels with f_b windows is (k + f_b) / (k / m + n_b). The
    rule keeps it relative to the prior mean,

        rho_b = (k + f_b) / (k + m n_b),

    1 for a building nobody has looked at, above 1 where more windows were found than
    the prior expects on that much facade, below 1 where fewer were. k = 1 is the
    generator's own prior (a Dirichlet(1) share is an exponential weight); larger k trusts
    the first windows less. Computed in float32: m n_b, k + that, k + f_b, one division
    (a compiler may fuse k + m n_b into one multiply-add, so two sides may differ in the
    last bit, and q below by one unit where rho falls on a rounding boundary).

Rates of columns and of samples
    A known building column's rate is its building's rho; every other column's is 0. A
    column's *facade rate* is the largest rate of the columns that make its facade top
    (`jaxmripp.spec.view`: the column and its four neighbours for `sensor.gain_facade`
    nearby, its eight for around, the column alone for column). It is quantised, q = min(floor(RATE_SCALE rho +
    0.5), RATE_CAP RATE_SCALE), an integer.

Features (the policy's optional BELIEF columns, `jaxmripp.spec.layout`)
    view_windows           sum over the pose's facade samples (`jaxmripp.spec.view`: clear,
                           unknown, facade) of weight x q of the sample's column, divided
                           by RATE_SCALE x the sum of all weights: the facade gain with each
                           sample weighed by its building's relative rate (equal to
                           view_facade while every building is at its prior)
    view_windows_per_cost  view_windows * (shell[1] / max(cost, COST_FLOOR))
    The sums are integers, so both sides give the same float32 numbers from the same q.
    Expected new windows in view: m x view_windows x (the samples' total weight x the
    voxels each unit of weight stands for), i.e. proportional to view_windows.

PRIOR (m): the generator's expected window count over its expected window slots, from
the world config (`prior_rate`): windows (min + max) / 2, buildings x the mean number of
footprint columns that hold windows (the outer ring for facade windows, every column for
footprint windows; averaged over the footprint sides with `world.footprint_min`) x the
mean building height in voxels (the generator's floor and clipping included).
"""

from __future__ import annotations

import numpy as np

RATE_SCALE = 256  # q units per unit of relative rate
RATE_CAP = 64  # relative rates above this count as this (a whole facade of windows)


def relative_rate(found, seen, strength, prior, xp=np):
    """rho = (k + f) / (k + m n) elementwise (float32), for windows found f and facade
    voxels seen n (integers), strength k and prior rate m; `xp` is numpy or jax.numpy."""
    k, m = xp.float32(strength), xp.float32(prior)
    seen_expected = m * xp.asarray(seen).astype(xp.float32)
    return (k + xp.asarray(found).astype(xp.float32)) / (k + seen_expected)


def quantised(rate, xp=np):
    """q of relative rates (float32) as int32."""
    q = xp.floor(rate * xp.float32(RATE_SCALE) + xp.float32(0.5))
    return xp.minimum(q, RATE_CAP * RATE_SCALE).astype(xp.int32)


def mean_height(size: int, height_range: tuple[float, float]) -> float:
    """The generator's mean building height in voxels: floor(u G) for u uniform in the
    range, clipped to [max(1, floor(lo G)), max(1, min(G, floor(hi G)))]."""
    lo, hi = height_range
    low = max(1, int(np.floor(lo * size)))
    high = max(1, min(size, int(np.floor(hi * size))))
    u = lo + (hi - lo) * (np.arange(100_000) + 0.5) / 100_000
    return float(np.mean(np.clip(np.floor(u * size), low, high)))


def window_columns(footprint: int, footprint_min: int, placement: str) -> float:
    """The mean number of footprint columns that may hold windows."""
    sides = np.arange(footprint_min or footprint, footprint + 1)
    a, b = np.meshgrid(sides, sides, indexing="ij")
    inner = np.maximum(a - 2, 0) * np.maximum(b - 2, 0) if placement == "facade" else 0
    return float(np.mean(a * b - inner))


def prior_rate(size: int, buildings: int, footprint: int, footprint_min: int,
               height_range: tuple[float, float], targets: tuple[int, int],
               placement: str) -> float:
    """m: expected windows per window slot of the generator (counts already scaled to the
    world size, as `WorldConfig.n_buildings` and `target_capacity` give them)."""
    windows = 0.5 * (targets[0] + targets[1])
    slots = buildings * window_columns(footprint, footprint_min, placement) \
        * mean_height(size, height_range)
    return float(windows / max(slots, 1.0))
