"""The view gain's rule (jaxmripp.spec.view) written from its text, one ray sample at a
time: the reference the JAX (tests/test_view.py) and NumPy (tests/test_runtime_sharing.py)
gains are both held to."""

from __future__ import annotations

import numpy as np

from jaxmripp.config import SensorConfig
from jaxmripp.spec import view as spec
from jaxmripp.spec.grid import OCCUPIED, UNKNOWN


def brute_tops(grid: np.ndarray) -> np.ndarray:
    """Per column 1 + the highest z mapped OCCUPIED, 0 when none is."""
    top = np.zeros(grid.shape[:2], np.int8)
    for x, y, z in zip(*np.nonzero(grid == OCCUPIED)):
        top[x, y] = max(top[x, y], z + 1)
    return top


def visible_samples(grid, top, position, heading: int, sensor: SensorConfig):
    """Every ray sample of one pose the camera reaches, in order: (x, y, z, weight, near),
    near the highest top among the column and (with the "nearby" facade rule) its four
    neighbours (with "around" its eight); a ray stops at the grid's edge and, with occlusion, at an OCCUPIED voxel."""
    size = grid.shape[0]
    offsets, weights = spec.gain_table(sensor.fov_deg, sensor.range, size)
    c = np.clip(np.floor(np.float32(position) * np.float32(size)), 0, size - 1).astype(int)
    for ray in offsets[heading]:
        for (dx, dy, dz), w in zip(ray, weights):
            x, y, z = c[0] + dx, c[1] + dy, c[2] + dz
            if not (0 <= x < size and 0 <= y < size and 0 <= z < size):
                break
            if grid[x, y, z] == OCCUPIED and sensor.gain_occlusion:
                break
            columns = ((x, y), (x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1))
            if sensor.gain_facade == "column":
                columns = columns[:1]
            elif sensor.gain_facade == "around":
                columns += ((x - 1, y - 1), (x - 1, y + 1), (x + 1, y - 1), (x + 1, y + 1))
            near = max(top[i, j] for i, j in columns if 0 <= i < size and 0 <= j < size)
            yield x, y, z, w, near


def samples_total(grid, heading: int, sensor: SensorConfig) -> float:
    """The summed weight of every sample of a pose's rays: what gains are shares of."""
    offsets, weights = spec.gain_table(sensor.fov_deg, sensor.range, grid.shape[0])
    return len(offsets[heading]) * weights.sum()


def reference_gain(grid, top, position, heading: int, sensor: SensorConfig):
    """(unknown, facade) shares of one pose (float64), ray by ray and sample by sample."""
    unknown = facade = 0.0
    for x, y, z, w, near in visible_samples(grid, top, position, heading, sensor):
        if grid[x, y, z] == UNKNOWN:
            unknown += w
            facade += w * (near > 0 and z <= near)
    total = samples_total(grid, heading, sensor)
    return unknown / total, facade / total


def reference_gains(grid, top, positions, sensor: SensorConfig) -> np.ndarray:
    """(P, 4, 2) [unknown, facade] of P positions at the four headings."""
    return np.array([[reference_gain(grid, top, p, h, sensor) for h in range(4)]
                     for p in positions])
