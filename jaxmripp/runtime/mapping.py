"""A robot's own occupancy map and the geometry it needs, in NumPy.

Codes, headings and the traversal rule of a line of flight are those of
`jaxmripp.spec.grid`; this module is their NumPy implementation (`jaxmripp.sim.geometry` is
the JAX one). `traverse` computes the same float32 crossing times with the same
comparisons, so both sides list the same voxels for a segment, bit for bit; the runtime's
version is vectorised over many segment ends at once and never runs out of slots (see
`traverse`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jaxmripp.spec.grid import (FREE, HEADING_ANGLES, HEADING_VECTORS, N_HEADINGS,  # noqa: F401
                                OCCUPIED, UNKNOWN)

F32 = np.float32


def voxel_of(position: np.ndarray, size: int) -> np.ndarray:
    """(..., 3) positions -> (..., 3) int voxel indices, clipped into the grid."""
    return np.clip(np.floor(position * np.float32(size)), 0, size - 1).astype(np.int64)


def linear_index(voxel: np.ndarray, size: int) -> np.ndarray:
    """(..., 3) voxel indices -> (...,) flat index into a C-ordered (G, G, G) grid."""
    return (voxel[..., 0] * size + voxel[..., 1]) * size + voxel[..., 2]


def inside_world(position: np.ndarray) -> np.ndarray:
    return np.all((position >= 0.0) & (position <= 1.0), axis=-1)


def traverse(start: np.ndarray, end: np.ndarray, size: int, max_length: float | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Starts (3,) or (..., 3), ends (..., 3) -> voxels (..., V, 3) int32 and entry
    (..., V) float32: every voxel each line of flight start -> end traverses (the rule of
    `jaxmripp.spec.grid`), each with the t in [0, 1] where the flight enters it.

    Slots: the start voxel, the leaving voxel, per crossing of a voxel boundary in time
    order (crossings at the same time in x, y, z order) the voxel owning the crossing
    point, then per crossing the voxel after it, and the end voxel; unused slots repeat
    the start voxel with entry 0. The crossing times are the spec's float32 (p - s) / d,
    so the voxels and their first entries equal those of `jaxmripp.sim.geometry.traverse`.
    The slot count fits the segment with the most crossings, so every list is complete
    whatever its length; `max_length` (the JAX side's static bound) is accepted for the
    same signature and not needed here.
    """
    g = F32(size)
    e = np.asarray(end, F32) * g  # (..., 3)
    s = np.asarray(start, F32) * g
    shape = np.broadcast_shapes(e.shape, s.shape)[:-1]
    e = np.broadcast_to(e, (*shape, 3)).reshape(-1, 3)
    s = np.broadcast_to(s, (*shape, 3)).reshape(-1, 3)  # (M, 3)
    d = e - s  # (M, 3)
    span = float(np.max(np.abs(d), initial=0.0))
    c = int(math.ceil(span)) + 1
    step = np.sign(d).astype(np.int32)
    leave = np.where(d < 0, np.ceil(s) - F32(1), np.floor(s)).astype(np.int32)  # (M, 3)
    k = np.arange(1, c + 1, dtype=F32)
    up, down = np.floor(s)[..., None] + k, np.ceil(s)[..., None] - k  # (M, 3, c)
    plane = np.where(d[..., None] > 0, up, down)  # (M, 3, c)
    crossed = np.where(d[..., None] > 0, plane < e[..., None], plane > e[..., None]) \
        & (d[..., None] != 0)
    safe_d = np.where(d == 0, F32(1), d)[..., None]
    with np.errstate(invalid="ignore", over="ignore"):
        t = np.where(crossed, (plane - s[..., None]) / safe_d, F32(np.inf)).astype(F32)
    events, at_or_before, before = _crossings_up_to(t.reshape(len(e), -1), c)
    after_voxel = leave[:, None] + step[:, None] * at_or_before
    point_voxel = leave[:, None] + step[:, None] \
        * np.where(d[:, None] < 0, before, at_or_before)
    first = np.floor(s).astype(np.int32)[:, None]  # (M, 1, 3)
    real = np.isfinite(events)[..., None]
    voxels = np.concatenate([
        first, leave[:, None], np.where(real, point_voxel, first),
        np.where(real, after_voxel, first), np.floor(e).astype(np.int32)[:, None]], axis=1)
    zeros, ones = np.zeros((len(e), 2), F32), np.ones((len(e), 1), F32)
    hit = np.where(real[..., 0], events, F32(0))
    entry = np.concatenate([zeros, hit, hit, ones], axis=1)
    np.clip(voxels, 0, size - 1, out=voxels)
    return voxels.reshape(*shape, -1, 3), entry.reshape(*shape, -1)


class PaddedMaps(NamedTuple):
    """B maps of side `size`, each inside a grid with `margin` OCCUPIED voxels added on
    every side, flat: `codes` (B, side^3) int8 with side = size + 2 margin. A lookup up to
    `margin` voxels outside the map lands on OCCUPIED, which is what the view rule wants
    of a ray leaving the world (`jaxmripp.runtime.view`)."""

    codes: np.ndarray
    size: int
    margin: int

    @property
    def side(self) -> int:
        return self.size + 2 * self.margin

    @classmethod
    def of(cls, codes: np.ndarray, size: int, margin: int) -> "PaddedMaps":
        """Flat codes (G^3,) of one map or (B, G^3) of several -> their padded copies."""
        maps = np.asarray(codes).reshape(-1, size, size, size)
        side, inner = size + 2 * margin, slice(margin, margin + size)
        padded = np.full((len(maps), side, side, side), OCCUPIED, np.int8)
        padded[:, inner, inner, inner] = maps
        return cls(padded.reshape(len(maps), -1), size, margin)

    def index(self, voxel: np.ndarray) -> np.ndarray:
        """(..., 3) voxels of the map -> (...,) flat indices into a padded grid."""
        return linear_index(voxel + self.margin, self.side)


def known_free(codes: np.ndarray | PaddedMaps, start: np.ndarray, ends: np.ndarray,
               size: int, max_length: float, rows: np.ndarray | None = None) -> np.ndarray:
    """Flat codes (G^3,) of one map, or (B, G^3) of several (or their `PaddedMaps`) with
    `rows` (...) int the map of each flight; starts (3,) or (..., 3), ends (..., 3) -> (...)
    True where every voxel the flight start -> end traverses is FREE in its map."""
    ends = np.asarray(ends, F32)
    start = np.broadcast_to(np.asarray(start, F32), ends.shape)
    # Plain codes are maps with no margin.
    maps = codes if isinstance(codes, PaddedMaps) else PaddedMaps(np.asarray(codes), size, 0)
    table = maps.codes
    rows = None if table.ndim == 1 else np.broadcast_to(np.asarray(rows), ends.shape[:-1])

    def code(voxel, rows):
        return table[maps.index(voxel)] if rows is None else table[rows, maps.index(voxel)]

    # The end voxel, which every traversal lists, first: flights ending in a voxel not
    # known FREE need no traversal.
    free = code(voxel_of(ends, size), rows) == FREE
    if free.any():
        voxels, _ = traverse(start[free], ends[free], size, max_length)
        free[free] = np.all(code(voxels, None if rows is None else rows[free][:, None])
                            == FREE, axis=-1)
    return free


def _crossings_up_to(events: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crossing times (M, 3c), axis-major (inf: no crossing) -> the crossings in time
    order (M, n), n the most any segment has (ties in axis order), and per crossing and
    axis (M, n, 3) int32 the crossings of that axis at or before it and strictly before
    it: the counts up to the last and up to before the first of its equal times, which
    replace the comparison of every pair of crossings."""
    m, total = events.shape
    order = np.argsort(events, axis=1, kind="stable")
    ranked = np.take_along_axis(events, order, axis=1)
    n = int(np.isfinite(ranked).sum(axis=1).max(initial=0))
    axis = (order // c)[..., None] == np.arange(3)  # (M, 3c, 3) the sorted events' axes
    upto = np.zeros((m, total + 1, 3), np.int32)  # row i: crossings among the i first
    np.cumsum(axis, axis=1, dtype=np.int32, out=upto[:, 1:])
    index = np.arange(total)
    starts = np.ones((m, total), bool)
    starts[:, 1:] = ranked[:, 1:] != ranked[:, :-1]
    ends = np.ones((m, total), bool)
    ends[:, :-1] = starts[:, 1:]
    first = np.maximum.accumulate(np.where(starts, index, 0), axis=1)[:, :n]
    last = np.minimum.accumulate(np.where(ends, index, total)[:, ::-1], axis=1)[:, ::-1][:, :n]
    rows = upto.reshape(-1, 3)
    base = (np.arange(m) * (total + 1))[:, None]
    return ranked[:, :n], rows[base + last + 1], rows[base + first]


def fly_until(start: np.ndarray, end: np.ndarray, blocking: np.ndarray, size: int,
              max_length: float) -> tuple[np.ndarray, bool, np.ndarray]:
    """Flies start -> end until the first traversed voxel for which `blocking` (a (G^3,)
    bool table) is True, as `jaxmripp.sim.geometry.fly_until`: returns (stop (3,) float32,
    hit, that voxel (3,) or None). With a hit the robot stops midway through the last
    piece of the segment before the blocking voxel."""
    start, end = np.asarray(start, F32), np.asarray(end, F32)
    voxels, entry = traverse(start, end, size, max_length)
    blocked = np.asarray(blocking)[linear_index(voxels, size)]
    if not blocked.any():
        return end.copy(), False, None
    hit_entry = np.min(entry[blocked])
    previous = np.max(np.where(entry < hit_entry, entry, F32(0)))
    t_stop = F32(0.5) * (previous + hit_entry)
    stop = (start + t_stop * (end - start)).astype(F32)
    return stop, True, voxels[int(np.argmin(np.where(blocked, entry, np.inf)))]


def voxel_ahead(start: np.ndarray, end: np.ndarray, stop: np.ndarray, codes: np.ndarray,
                size: int, max_length: float) -> np.ndarray | None:
    """The voxel a flight start -> end that stopped at `stop` was stopped by: the first
    traversed voxel entered after the stop (`fly_until` stops midway before it). Where
    several are entered at that moment (an edge or corner), the first one the map (flat
    `codes`) does not know to be FREE. None when the stop is past every entry."""
    start, end = np.asarray(start, F32), np.asarray(end, F32)
    voxels, entry = traverse(start, end, size, max_length)
    d = (end - start).astype(np.float64)
    length2 = float(d @ d)
    t_stop = float((np.asarray(stop, np.float64) - start) @ d) / length2 if length2 else 0.0
    later = entry > t_stop
    if not later.any():
        return None
    ahead = np.nonzero(later & (entry == np.min(entry[later])))[0]
    unknown = [i for i in ahead if codes[linear_index(voxels[i], size)] != FREE]
    return voxels[unknown[0] if unknown else ahead[0]]


def raise_tops(top: np.ndarray, flat: np.ndarray, values: np.ndarray, size: int) -> None:
    """Building tops (`jaxmripp.spec.view`), in place: every voxel in `flat` written
    OCCUPIED raises its column to z + 1, whatever else is written there in the same call
    (the JAX side raises from every written pair too)."""
    occupied = np.asarray(flat, np.int64)[np.asarray(values) == OCCUPIED]
    np.maximum.at(top.reshape(-1), occupied // size, (occupied % size + 1).astype(np.int8))


class OccupancyMap:
    """One robot's (G, G, G) map, stored flat, with its building tops (`jaxmripp.spec.view`,
    (G, G) int8, 1 + the highest z ever mapped OCCUPIED per column) and its window bits
    (the OCCUPIED voxels known to be windows, `jaxmripp.spec.belief`); every voxel starts
    UNKNOWN and no window, every top 0."""

    def __init__(self, size: int):
        self.size = size
        self.codes = np.full(size ** 3, UNKNOWN, np.int8)
        self.top = np.zeros((size, size), np.int8)
        self.window = np.zeros(size ** 3, bool)

    @property
    def grid(self) -> np.ndarray:
        """(G, G, G) view of the codes."""
        return self.codes.reshape(self.size, self.size, self.size)

    def update(self, flat: np.ndarray, values: np.ndarray) -> None:
        """Sets observed voxels (flat indices in [0, G^3)) to their codes; later wins."""
        self.codes[flat] = values
        raise_tops(self.top, flat, values, self.size)

    def mark_occupied(self, voxel: np.ndarray) -> None:
        flat = linear_index(np.asarray(voxel), self.size)
        self.codes[flat] = OCCUPIED
        raise_tops(self.top, np.array([flat]), np.array([OCCUPIED]), self.size)

    def merge(self, flat: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, int]:
        """Another robot's codes at voxels `flat`, by the merge rule of
        `jaxmripp.spec.sharing`: an UNKNOWN voxel takes the sender's code, a FREE one
        becomes OCCUPIED where the sender holds it OCCUPIED, an OCCUPIED one stays; every
        OCCUPIED one raises the tops (the maximum of the two maps' tops, since a map's tops
        are those of the OCCUPIED voxels it ever held). Returns the flat indices whose code
        changed and the number of voxels the two maps disagreed on (FREE here and
        OCCUPIED there, or the other way round)."""
        flat = np.asarray(flat, np.int64)
        values = np.asarray(values, np.int8)
        ours = self.codes[flat]
        known = values != UNKNOWN
        disagree = known & (ours != UNKNOWN) & (ours != values)
        change = known & ((ours == UNKNOWN) | ((ours == FREE) & (values == OCCUPIED)))
        self.codes[flat[change]] = values[change]
        raise_tops(self.top, flat, values, self.size)
        return flat[change], int(disagree.sum())

    def mark_windows(self, flat: np.ndarray) -> np.ndarray:
        """Marks voxels `flat` (mapped OCCUPIED: callers check) as windows; returns those
        that were not marked before. A window stays one (a static world)."""
        flat = np.unique(np.asarray(flat, np.int64))
        fresh = flat[~self.window[flat]]
        self.window[fresh] = True
        return fresh

    def mark_own_voxel(self, position: np.ndarray) -> None:
        """The voxel the robot is in is FREE (it is there; `jaxmripp.spec.flight`)."""
        self.codes[linear_index(voxel_of(np.asarray(position, F32), self.size),
                                self.size)] = FREE

    def known_free(self, start: np.ndarray, ends: np.ndarray, max_length: float
                   ) -> np.ndarray:
        """(3,), (M, 3) -> (M,) True where every voxel the flight start -> end traverses
        is FREE in this map (`jaxmripp.sim.geometry.known_free`)."""
        ends = np.asarray(ends, F32).reshape(-1, 3)
        return known_free(self.codes, start, ends, self.size, max_length)
