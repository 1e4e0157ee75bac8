"""The view-gain features of `jaxmripp.spec.view`, in NumPy, for one robot's candidates.

The JAX side (`jaxmripp.sim.view`) computes them per candidate position for all four
headings; here every pose is looked up with its own heading, since a caller may supply
poses that do not come four to a position. The sums are integers, so both sides give
the same numbers bit for bit provided the last step is the same float32 operation: XLA
turns a division by a compile-time constant (the total weight, the shell radius) into a
multiplication by its float32 reciprocal, so this side multiplies by that reciprocal too
(a true division differs in the last bit for 13% to 60% of the possible sums, depending
on the total). `per_cost` divides by the cost, which is no constant, as the JAX side does.
`peer_distance` sums the three squares left to right, as XLA does without LLVM
optimisation; with it, XLA may round that sum differently, by one unit in the last place.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime.mapping import OCCUPIED, UNKNOWN, voxel_of
from jaxmripp.spec import view as spec

F32 = np.float32


def nearby_tops(top: np.ndarray) -> np.ndarray:
    """(G, G) -> (G, G) int32: the largest top of each column and its four neighbours."""
    padded = np.pad(np.asarray(top, np.int32), 1)
    return np.maximum.reduce([padded[1:-1, 1:-1], padded[:-2, 1:-1], padded[2:, 1:-1],
                              padded[1:-1, :-2], padded[1:-1, 2:]])


def _samples(codes: np.ndarray, top: np.ndarray, position: np.ndarray, heading: np.ndarray,
             fov_deg: float, sensor_range: float, size: int):
    """Poses (L, 3) / (L,) -> the flat voxel index (L, R, S) of every gain sample, which of
    them are unknown and which facade (both (L, R, S) bool), and the weights (S,)."""
    offsets, weights = spec.gain_table(fov_deg, sensor_range, size)
    position = np.asarray(position, F32).reshape(-1, 3)
    camera = voxel_of(position, size)  # (L, 3)
    sample = camera[:, None, None, :] + offsets[np.asarray(heading, np.int64).reshape(-1)]
    inside = np.all((sample >= 0) & (sample < size), axis=-1)
    x, y, z = (np.clip(sample[..., a], 0, size - 1) for a in range(3))
    column = x * size + y
    flat = column * size + z
    code = np.asarray(codes)[flat]
    # A sample is clear when no earlier sample of its ray left the grid or hit OCCUPIED.
    stops = ~inside | (code == OCCUPIED)
    clear = np.ones_like(stops)
    clear[..., 1:] = ~np.logical_or.accumulate(stops, axis=-1)[..., :-1]
    unknown = clear & inside & (code == UNKNOWN)
    near = nearby_tops(top).reshape(-1)[column]
    facade = unknown & (near > 0) & (sample[..., 2] <= near)
    return flat, unknown, facade, weights


def view_gain(codes: np.ndarray, top: np.ndarray, position: np.ndarray, heading: np.ndarray,
              fov_deg: float, sensor_range: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A map's flat (G^3,) codes and (G, G) tops, poses (L, 3) / (L,) -> (view_unknown,
    view_facade), each (L,) float32."""
    _, unknown, facade, weights = _samples(codes, top, position, heading, fov_deg,
                                           sensor_range, size)
    total = F32(unknown.shape[1] * int(weights.sum()))
    unknown_sum = (unknown * weights).sum(axis=(1, 2))
    facade_sum = (facade * weights).sum(axis=(1, 2))
    scale = F32(1) / total
    return unknown_sum.astype(F32) * scale, facade_sum.astype(F32) * scale


def unknown_in_view(codes: np.ndarray, top: np.ndarray, position: np.ndarray, heading: int,
                    fov_deg: float, sensor_range: float, size: int) -> np.ndarray:
    """The flat indices of one pose's unknown samples: the part of the map it would reveal
    (`jaxmripp.sim.view.unknown_in_view`)."""
    flat, unknown, _, _ = _samples(codes, top, position, heading, fov_deg, sensor_range,
                                   size)
    return flat[unknown]


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
    gap = position[:, None, :] - heard[None, :, :]
    square = gap * gap
    scale = F32(1) / F32(shell_outer)
    distance = np.sqrt(square[..., 0] + square[..., 1] + square[..., 2]) * scale
    return np.minimum(distance.min(axis=1), F32(spec.PEER_CAP)).astype(F32)
