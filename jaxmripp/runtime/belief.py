"""The target belief of `jaxmripp.spec.belief` in NumPy, for one robot.

The rule is written once, in that module's docstring; `jaxmripp.sim.belief` is its JAX
implementation. This side follows the text directly, on the robot's whole ground: its
buildings are the 8-connected components of the columns its tops mark (labelled by their
smallest flat column index), n_b counts the voxels of b's columns its map holds OCCUPIED
and f_b the voxels of b's columns it knows to be windows (`OccupancyMap.window`: its own
classifier's reports and those merged from peers' map deltas). The posterior rates, their
quantisation and the facade maximum use the spec's functions and the view gain's facade
tops, so both sides give the same integers q from the same counts (the spec allows one
unit where a compiler fuses a multiply-add); the rate-weighted gain itself is
`jaxmripp.runtime.view.view_gain(..., rates=)`.

The simulator computes the same labels on the boxes of the real buildings instead of the
whole ground: every column a robot's tops mark belongs to a real building, and with
`world.clearance` >= 1 no component leaves one.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxmripp.runtime.mapping import OCCUPIED, OccupancyMap
from jaxmripp.runtime.view import facade_tops
from jaxmripp.spec import belief as spec

F32 = np.float32


class Belief(NamedTuple):
    """One robot's belief: its buildings, their counts and posterior rates."""

    labels: np.ndarray  # (G, G) int64 each known building column's label, G * G elsewhere
    buildings: np.ndarray  # (B,) int64 the labels, increasing
    seen: np.ndarray  # (B,) int64 n_b, facade voxels mapped OCCUPIED
    found: np.ndarray  # (B,) int64 f_b, known windows
    rho: np.ndarray  # (B,) float32 relative posterior rates (k + f_b) / (k + m n_b)

    def column_rates(self) -> np.ndarray:
        """(G, G) float32: each known building column's rho, 0 elsewhere."""
        size = self.labels.shape[0]
        known = self.labels < size * size
        rates = np.zeros(self.labels.shape, F32)
        rates[known] = self.rho[np.searchsorted(self.buildings, self.labels[known])]
        return rates


def building_labels(top: np.ndarray) -> np.ndarray:
    """(G, G) tops -> (G, G) int64 labels: the smallest flat column index x G + y of each
    8-connected component of the columns with top > 0, G * G for the other columns.
    Neighbourhood minima spread until nothing changes (a component's diameter rounds)."""
    top = np.asarray(top)
    size = top.shape[0]
    none = size * size
    known = top > 0
    labels = np.where(known, np.arange(none, dtype=np.int64).reshape(size, size), none)
    while True:
        padded = np.pad(labels, 1, constant_values=none)
        rows = np.minimum(np.minimum(padded[:-2], padded[1:-1]), padded[2:])
        least = np.minimum(np.minimum(rows[:, :-2], rows[:, 1:-1]), rows[:, 2:])
        spread = np.where(known, least, none)
        if np.array_equal(spread, labels):
            return labels
        labels = spread


def belief(occupancy: OccupancyMap, strength: float, prior: float) -> Belief:
    """The buildings of a robot's map and tops, their counts and rates, with prior
    strength k = `strength` and prior rate m = `prior` (the export's)."""
    size = occupancy.size
    labels = building_labels(occupancy.top)
    known = labels < size * size
    buildings = np.unique(labels[known])
    index = np.searchsorted(buildings, labels[known])
    occupied = (occupancy.codes == OCCUPIED).reshape(size, size, size).sum(axis=-1)
    seen = np.zeros(len(buildings), np.int64)
    np.add.at(seen, index, occupied[known].astype(np.int64))
    windows = np.flatnonzero(occupancy.window)
    window_labels = labels.reshape(-1)[windows // size]
    window_labels = window_labels[window_labels < size * size]
    found = np.bincount(np.searchsorted(buildings, window_labels), minlength=len(buildings))
    rho = spec.relative_rate(found, seen, strength, prior).astype(F32)
    return Belief(labels, buildings, seen, found.astype(np.int64), rho)


def facade_rates(occupancy: OccupancyMap, strength: float, prior: float,
                 facade: str) -> np.ndarray:
    """(G, G) int32 quantised facade rates q (`jaxmripp.spec.belief`): the largest q of the
    columns that make each column's facade top, for the gain's facade model `facade`
    (`jaxmripp.runtime.view.GainModel.facade`)."""
    rates = belief(occupancy, strength, prior).column_rates()
    return facade_tops(spec.quantised(rates), facade).astype(np.int32)
