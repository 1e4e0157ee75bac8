"""From a depth image to map updates, in NumPy: what a real drone's camera gives the map.

A depth image holds, per pixel, the depth of the nearest surface along that pixel's ray,
measured along the optical axis (z-depth, metres; +inf: nothing within range). The camera
is a pinhole (`DepthCamera`, OpenCV axes: x right, y down, z forward); its pose is a
position and a rotation camera -> world, in metres. `GridFrame` places the planner's unit
cube in that world: metres = origin + p * extent, per axis.

The rule (`observe`), written so that a voxel marked FREE never holds an obstacle whose
walls are set in from the voxel faces by less than `core` (a building in
`jaxmripp.flight.city` is its voxel block with walls set in by less than that):
- OCCUPIED: the voxel of every return (a pixel whose ray meets a surface within
  `max_range`) inside the grid; returns outside it (the ground below the grid) mark
  nothing.
- FREE: every voxel whose *core* -- the voxel shrunk by `core` of its size on every side
  -- holds a sample point of a ray before its return (or before `max_range`), the samples
  `step` metres apart. A ray that only grazes a voxel's rim proves nothing about the
  voxel, and leaves it as it was.
- a voxel marked OCCUPIED by any pixel of the images given together is not marked FREE;
  `OnboardPlanner.sense_depth` also keeps voxels its map already holds OCCUPIED (the
  world is static; `OccupancyMap.update` alone lets the later code win).
Samples are a spacing, so a voxel crossed only briefly may stay UNKNOWN: the rule errs
towards not knowing, never towards FREE.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxmripp.runtime.errors import InvalidPoseError
from jaxmripp.spec.grid import FREE, OCCUPIED

F32 = np.float32


@dataclasses.dataclass(frozen=True)
class DepthCamera:
    """Pinhole intrinsics in pixels; pixel (u, v) looks through (u - cx) / fx,
    (v - cy) / fy at depth 1. Returns beyond `max_range` metres (along the ray) are not
    reported; nothing nearer than `min_range` is sensed (the drone's own body)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    max_range: float
    min_range: float = 0.0

    @classmethod
    def square(cls, pixels: int, fov_deg: float, max_range: float, min_range: float = 0.0
               ) -> "DepthCamera":
        """A square image whose outer pixel edges span `fov_deg` on both axes."""
        if not (isinstance(pixels, int) and pixels >= 2):
            raise ValueError(f"camera pixels: got {pixels!r}; allowed: an integer >= 2")
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"camera fov_deg: got {fov_deg}; allowed: (0, 180)")
        if not 0.0 <= min_range < max_range < math.inf:
            raise ValueError(f"camera range: got min {min_range}, max {max_range}; allowed: "
                             "0 <= min < max < inf")
        f = 0.5 * pixels / math.tan(math.radians(fov_deg) / 2)
        c = 0.5 * (pixels - 1)
        return cls(pixels, pixels, f, f, c, c, float(max_range), float(min_range))

    def directions(self) -> np.ndarray:
        """(H, W, 3) unit ray directions in the camera frame, pixel centres."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class GridFrame:
    """Where the unit cube of a G^3 grid sits in metres, and the FREE rule's core."""

    origin: tuple[float, float, float]  # metres of the cube's corner (0, 0, 0)
    extent: tuple[float, float, float]  # metres spanned by the cube along x, y, z
    core: float = 0.25  # fraction of a voxel's size cut from every side for FREE samples

    def __post_init__(self):
        if not (len(self.extent) == 3 and all(e > 0 for e in self.extent)):
            raise ValueError(f"frame extent: got {self.extent}; allowed: 3 positive lengths")
        if not 0.0 <= self.core < 0.5:
            raise ValueError(f"frame core: got {self.core}; allowed: [0, 0.5)")

    def to_unit(self, metres: np.ndarray) -> np.ndarray:
        return (np.asarray(metres) - np.asarray(self.origin)) / np.asarray(self.extent)

    def to_metres(self, unit: np.ndarray) -> np.ndarray:
        return np.asarray(self.origin) + np.asarray(unit) * np.asarray(self.extent)

    def default_step(self, size: int) -> float:
        """Half the core's smallest side: a ray crossing a core squarely leaves a sample."""
        return 0.5 * (1.0 - 2.0 * self.core) * min(self.extent) / size


def _checked(depth, camera: DepthCamera, position, rotation, what: str):
    depth = np.asarray(depth, np.float64)
    if depth.shape != (camera.height, camera.width):
        raise InvalidPoseError(f"{what}: depth image of shape {depth.shape}; the camera's is "
                               f"{(camera.height, camera.width)}")
    bad = np.isnan(depth) | (depth < 0)
    if bad.any():
        v, u = np.argwhere(bad)[0]
        raise InvalidPoseError(f"{what}: depth must be >= 0 or +inf (no return); pixel "
                               f"({u}, {v}) holds {depth[v, u]} ({int(bad.sum())} bad pixels)")
    position = np.asarray(position, np.float64)
    rotation = np.asarray(rotation, np.float64)
    if position.shape != (3,) or not np.all(np.isfinite(position)):
        raise InvalidPoseError(f"{what}: camera position must be 3 finite numbers (metres), "
                               f"got {position.tolist()}")
    if rotation.shape != (3, 3) or not np.all(np.isfinite(rotation)) \
            or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4):
        raise InvalidPoseError(f"{what}: camera rotation must be a 3 x 3 rotation matrix "
                               "(camera -> world)")
    return depth, position, rotation


def observe(depth, camera: DepthCamera, position, rotation, frame: GridFrame, size: int,
            step: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One depth image -> (flat voxel indices (K,) int64, codes (K,) int8), each voxel
    once, by the module's rule. position (3,) and rotation (3, 3) camera -> world are the
    camera's pose in metres; step: sample spacing in metres (default
    `frame.default_step(size)`)."""
    return observe_many([(depth, position, rotation)], camera, frame, size, step)


def observe_many(images, camera: DepthCamera, frame: GridFrame, size: int,
                 step: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Several images [(depth, position, rotation), ...] taken together (a turn on the
    spot): OCCUPIED from any of them wins over FREE from another."""
    step = frame.default_step(size) if step is None else float(step)
    if not step > 0:
        raise ValueError(f"depth sample step: got {step}; allowed: > 0 metres")
    rays_cam = camera.directions()  # (H, W, 3)
    cos_axis = rays_cam[..., 2]
    extent, origin = np.asarray(frame.extent), np.asarray(frame.origin)
    hits, free = [], []
    for k, (depth, position, rotation) in enumerate(images):
        depth, position, rotation = _checked(depth, camera, position, rotation,
                                             f"depth image {k}")
        rays = (rays_cam @ rotation.T).reshape(-1, 3)  # world directions
        length = (depth / cos_axis).reshape(-1)  # along the ray; inf: no return
        returned = length <= camera.max_range
        reach = np.where(returned, length, camera.max_range)
        points = position + rays[returned] * length[returned, None]
        hits.append(_voxels(points, origin, extent, size, core=None))
        # Samples strictly before each return, from the near limit on.
        t = np.arange(camera.min_range, camera.max_range, step)
        before = t[None, :] < reach[:, None]
        samples = position + rays[:, None, :] * t[None, :, None]
        free.append(_voxels(samples[before], origin, extent, size, core=frame.core))
    occupied = np.unique(np.concatenate(hits))
    free = np.setdiff1d(np.concatenate(free), occupied)
    flat = np.concatenate([free, occupied]).astype(np.int64)
    codes = np.concatenate([np.full(len(free), FREE, np.int8),
                            np.full(len(occupied), OCCUPIED, np.int8)])
    return flat, codes


def _voxels(points, origin, extent, size: int, core: float | None) -> np.ndarray:
    """Distinct flat voxel indices of the points inside the grid (and, with `core`,
    inside their voxel's core)."""
    q = (points - origin) / extent * size
    cell = np.floor(q)
    keep = np.all((cell >= 0) & (cell < size), axis=-1)
    if core is not None:
        frac = q - cell
        keep &= np.all((frac >= core) & (frac <= 1.0 - core), axis=-1)
    cell = cell[keep].astype(np.int64)
    return np.unique((cell[:, 0] * size + cell[:, 1]) * size + cell[:, 2])
