"""The view-gain features of `jaxmripp.spec.view`, in NumPy, for one robot's candidates.

The JAX side (`jaxmripp.sim.view`) computes them per candidate position for all four
headings; here every pose is looked up with its own heading, since a caller may supply
poses that do not come four to a position. The sums are integers, so both sides give
the same numbers bit for bit provided the last step is the same float32 operation: XLA
turns a division by a compile-time constant (the total weight, the shell radius) into a
multiplication by its float32 reciprocal, so this side multiplies by that reciprocal too
(a true division differs in the last bit for 13% to 60% of the possible sums, depending
on the total). `per_cost` divides by the cost, which is no constant, as the JAX side does.
`peer_distance` is the vector arithmetic of `jaxmripp.spec.vectors`, which both sides
evaluate to the same bits.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, PaddedMaps, voxel_of
from jaxmripp.spec import belief as belief_spec
from jaxmripp.spec import vectors
from jaxmripp.spec import view as spec

F32 = np.float32


class GainModel(NamedTuple):
    """What the view gain assumes of the sensor and the world (`jaxmripp.spec.view`):
    the camera's field of view and range, whether voxels mapped OCCUPIED stop its rays and
    which tops mark facade voxels (`spec.FACADE_TOPS`)."""

    fov_deg: float
    sensor_range: float
    occlusion: bool = True
    facade: str = "nearby"


_SIDES = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))
_CORNERS = ((-1, -1), (-1, 1), (1, -1), (1, 1))


def _neighbour_max(top: np.ndarray, steps) -> np.ndarray:
    """(G, G) -> (G, G) int32: the largest top over each column's offsets `steps`
    (outside the grid: 0)."""
    padded = np.pad(np.asarray(top, np.int32), 1)
    size = padded.shape[0] - 2
    return np.maximum.reduce([padded[1 + dx:1 + dx + size, 1 + dy:1 + dy + size]
                              for dx, dy in steps])


def nearby_tops(top: np.ndarray) -> np.ndarray:
    """(G, G) -> (G, G) int32: the largest top of each column and its four neighbours."""
    return _neighbour_max(top, _SIDES)


def around_tops(top: np.ndarray) -> np.ndarray:
    """(G, G) -> (G, G) int32: the largest top of each column and its eight neighbours."""
    return _neighbour_max(top, _SIDES + _CORNERS)


def facade_tops(top: np.ndarray, facade: str) -> np.ndarray:
    """(G, G) tops -> (G, G) the tops that mark facade voxels (`GainModel.facade`)."""
    if facade == "nearby":
        return nearby_tops(top)
    if facade == "around":
        return around_tops(top)
    return np.asarray(top, np.int32)


class GainTable(NamedTuple):
    """The gain samples of `jaxmripp.spec.view` as offsets into grids padded with `margin`
    OCCUPIED voxels (`PaddedMaps`), wide enough that no sample leaves them: samples outside
    the world then stop their ray as the spec's rule does, with one lookup each."""

    margin: int
    flat: np.ndarray  # (4, R, S) int64 offsets into a padded grid, per heading
    column: np.ndarray  # (4, R, S) the same into its (side, side) columns
    xyz: np.ndarray  # (3, 4, R, S) the samples' x, y and z offsets
    weights: np.ndarray  # (R * S,) float32, the spec's per-sample weights, ray-major
    scale: np.float32  # 1 / the weights' total, as XLA multiplies by it (module docstring)
    total: int  # the weights' total over all rays of a heading


@functools.lru_cache(maxsize=8)
def gain_table(fov_deg: float, sensor_range: float, size: int) -> GainTable:
    offsets, weights = spec.gain_table(fov_deg, sensor_range, size)
    margin = int(np.abs(offsets).max()) + 1
    side = size + 2 * margin
    offsets = offsets.astype(np.int64)
    column = offsets[..., 0] * side + offsets[..., 1]
    total = offsets.shape[1] * int(weights.sum())
    return GainTable(margin, column * side + offsets[..., 2], column,
                     np.moveaxis(offsets, -1, 0),
                     np.tile(np.asarray(weights, F32), offsets.shape[1]), F32(1) / F32(total),
                     total)


def padded(codes: np.ndarray | PaddedMaps, table: GainTable, size: int) -> PaddedMaps:
    """Flat codes (G^3,) or (B, G^3), or maps already padded for `table`, as `PaddedMaps`."""
    if isinstance(codes, PaddedMaps):
        if codes.margin != table.margin:
            raise ValueError(f"maps padded with margin {codes.margin}; this sensor's gain "
                             f"samples need margin {table.margin}")
        return codes
    return PaddedMaps.of(codes, size, table.margin)


def _samples(codes: np.ndarray | PaddedMaps, top: np.ndarray, position: np.ndarray,
             heading: np.ndarray, model: GainModel, size: int, rows: np.ndarray | None = None):
    """Poses (..., 3) / (...) -> the index (P, R, S) of every gain sample of the P poses
    in the padded maps (map b at b side^3 onwards), which of them are unknown and which
    facade (both (P, R, S) bool), the maps and the table. `codes`: (G^3,), or (B, G^3) (or
    their `PaddedMaps`) with `rows` (...) the map each pose looks into (default: poses
    (B, L, 3) / (B, L), pose (b, l) in map b). Last, each sample's column (P, R, S) in the
    padded (side, side) ground."""
    table = gain_table(model.fov_deg, model.sensor_range, size)
    maps = padded(codes, table, size)
    margin, side = table.margin, maps.side
    inner = slice(margin, margin + size)
    near = np.zeros((side, side), np.int8)
    near[inner, inner] = facade_tops(top, model.facade)
    heading = np.asarray(heading, np.int64)
    if len(maps.codes) == 1:
        rows = np.zeros(heading.shape, np.int64)
    elif rows is None:
        rows = np.broadcast_to(np.arange(len(maps.codes))[:, None], heading.shape)
    row = np.asarray(rows).reshape(-1)
    heading = heading.reshape(-1)
    camera = voxel_of(np.asarray(position, F32).reshape(-1, 3), size) + margin  # (P, 3)
    camera_column = camera[:, 0] * side + camera[:, 1]
    start = row * side ** 3 + camera_column * side + camera[:, 2]
    index = start[:, None, None] + table.flat[heading]
    code = maps.codes.reshape(-1)[index]

    def along(axis: int) -> np.ndarray:
        """(P, R, S) the samples' map coordinates along `axis`."""
        return (camera[:, axis] - margin)[:, None, None] + table.xyz[axis][heading]

    z = along(2)
    # A sample is clear when no earlier sample of its ray hit OCCUPIED (the margin is) or,
    # without occlusion, left the grid.
    if model.occlusion:
        stops = code == OCCUPIED
    else:
        stops = np.zeros(code.shape, bool)
        for coordinate in (along(0), along(1), z):
            stops |= (coordinate < 0) | (coordinate >= size)
    clear = np.ones_like(stops)
    clear[..., 1:] = ~np.logical_or.accumulate(stops, axis=-1)[..., :-1]
    unknown = clear & (code == UNKNOWN)
    columns = camera_column[:, None, None] + table.column[heading]
    near = near.reshape(-1)[columns]
    facade = unknown & (near > 0) & (z <= near)
    return index, unknown, facade, maps, table, columns


def view_gain(codes: np.ndarray | PaddedMaps, top: np.ndarray, position: np.ndarray,
              heading: np.ndarray, model: GainModel, size: int,
              rows: np.ndarray | None = None, rates: np.ndarray | None = None
              ) -> tuple[np.ndarray, ...]:
    """A map's flat (G^3,) codes and (G, G) tops, poses (L, 3) / (L,) -> (view_unknown,
    view_facade), each (L,) float32; with B maps' codes (B, G^3) or `PaddedMaps` (sharing
    the tops), poses (B, L, 3) / (B, L) -> each (B, L), pose (b, l) seen in map b, or poses
    (L, 3) / (L,) with `rows` (L,) -> each (L,), pose l seen in map rows[l]. With the
    robot's quantised facade rates (G, G) int (`jaxmripp.runtime.belief.facade_rates`)
    also view_windows (`jaxmripp.spec.belief`): each facade sample's weight times its
    column's rate, over RATE_SCALE times the weights' total."""
    _, unknown, facade, _, table, columns = _samples(codes, top, position, heading, model,
                                                     size, rows)
    # Weighted counts as one float32 product each: integers far below 2^24, so exact.
    unknown_sum = unknown.reshape(-1, table.weights.size).astype(F32) @ table.weights
    facade_sum = facade.reshape(-1, table.weights.size).astype(F32) @ table.weights
    shape = np.shape(heading)
    gains = ((unknown_sum * table.scale).reshape(shape),
             (facade_sum * table.scale).reshape(shape))
    if rates is None:
        return gains
    side = size + 2 * table.margin
    inner = slice(table.margin, table.margin + size)
    padded_rates = np.zeros((side, side), np.int64)  # samples beyond the grid are OCCUPIED
    padded_rates[inner, inner] = rates
    # Integer sums up to 2^31 (the JAX side's int32), exact in int64; then the same float32
    # conversion and product by the float32 reciprocal as there.
    rated = np.where(facade, padded_rates.reshape(-1)[columns], 0).reshape(
        -1, table.weights.size) @ table.weights.astype(np.int64)
    scale = F32(1) / F32(table.total * belief_spec.RATE_SCALE)
    return gains + ((rated.astype(F32) * scale).reshape(shape),)


def after_views(codes: np.ndarray, top: np.ndarray, position: np.ndarray, heading: np.ndarray,
                model: GainModel, size: int) -> PaddedMaps:
    """A map's flat (G^3,) codes, poses (B, 3) / (B,) -> B padded copies of the map (for
    `view_gain` and `known_free`): copy b with the unknown voxels pose b sees counted as
    FREE, the part of the map it would reveal (`jaxmripp.sim.view.unknown_in_view`)."""
    index, unknown, _, one, *_ = _samples(codes, top, position, heading, model, size)
    after = np.repeat(one.codes, len(index), axis=0)
    copy = np.broadcast_to(np.arange(len(index))[:, None, None], index.shape)
    after.reshape(-1)[copy[unknown] * after.shape[1] + index[unknown]] = FREE
    return one._replace(codes=after)


def per_cost(gain: np.ndarray, cost: np.ndarray, shell_outer: float) -> np.ndarray:
    """gain * (shell[1] / max(cost, COST_FLOOR)), float32."""
    cost = np.asarray(cost, F32)
    return (np.asarray(gain, F32)
            * (F32(shell_outer) / np.maximum(cost, F32(spec.COST_FLOOR)))).astype(F32)


def peer_distance(position: np.ndarray, heard: np.ndarray, shell_outer: float) -> np.ndarray:
    """Poses' positions (L, 3), positions of the robots heard this round (M, 3) -> (L,)
    min(PEER_CAP, distance to the nearest one / shell[1]); PEER_CAP when M = 0."""
    position = np.asarray(position, F32).reshape(-1, 3)
    heard = np.asarray(heard, F32).reshape(-1, 3)
    if not len(heard):
        return np.full(len(position), F32(spec.PEER_CAP), F32)
    gap = vectors.components(position[:, None, :] - heard[None, :, :])
    distance = np.sqrt(vectors.dot(gap, gap, np)) * (F32(1) / F32(shell_outer))
    return np.minimum(distance.min(axis=1), F32(spec.PEER_CAP)).astype(F32)
