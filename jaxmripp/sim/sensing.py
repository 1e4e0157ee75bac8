"""Depth-camera sensing: which windows a pose sees, and which voxels it reveals.

The camera sits at the centre of the robot's voxel and looks along one of the four
horizontal headings; the static `SensorConfig.model` picks one of two sensors.

raycast (default): an n x n grid of rays through the centres of the image-plane cells,
stopped by buildings. Buildings are boxes on the ground, so a ray's first hit depends only
on the columns its horizontal projection crosses, and all rays of one azimuth cross the
same columns (listed once, statically, nearest first). Per cast that is one height lookup
per (azimuth, column), a slope threshold per column, and a minimum over columns per ray.
The view is the static set of voxels whose centres lie in the field of view and range, and
the camera's own voxel (a robot's own voxel is always mapped: FREE, since it is there); a
view voxel is observed iff the ray nearest its direction reaches its centre, or for a
building voxel comes within `_SURFACE` of it. Codes are copied from the truth, so a map
never contradicts the world, OCCUPIED never turns FREE and what is behind a wall stays
UNKNOWN. A window is seen iff a face of it that is turned to the camera and open to the
air is in sight (`_windows_seen`), a finer test than the map's.

frustum (the reference's, docs/design.md section 1): every voxel with forward offset
0 <= f <= depth - 1 and both other offsets within min(depth - 1, floor(1.5 f) + 1) of the
robot's voxel, clipped to the grid, without occlusion; windows in that set are seen.

Performance notes (XLA:CPU, measured): vectors are separate x / y / z arrays, since small
trailing-axis reductions do not vectorise; per-cast scalars and per-ray distances come out
of integer reductions, which XLA never fuses into their consumers, so they are computed
once instead of inside every gather that reads them (`optimization_barrier` is dropped on
CPU); and gathers from batched tables (height maps, rays) fold the batch into one flat
table (`geometry.take_flat`), as do the map scatters and the building tops'
(`_flat_scatter`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import chex
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.sim import geometry
from jaxmripp.sim.geometry import take_flat
from jaxmripp.config import SensorConfig
from jaxmripp.sim.world import World

# Camera frame per heading: forward f, right r = f x up (both horizontal), up = +z.
_FORWARD = geometry.HEADING_VECTORS[:, :2].astype(np.int32)
_RIGHT = np.stack([_FORWARD[:, 1], -_FORWARD[:, 0]], -1)
_EPS = 1e-4  # slack for float comparisons on exact 45 degree edges and at the range
_SURFACE = 1.0  # voxels: how close a ray must come to a building voxel's centre to see it
_INF_BITS = np.float32(np.inf).view(np.int32)


@flax.struct.dataclass
class CastResult:
    """What one pose senses (T = target capacity, V = `view_size(sensor, G)`)."""

    seen: jax.Array  # (T,) bool windows seen from this pose (valid ones only)
    voxels: jax.Array  # (V,) int32 flat voxel indices observed; G**3 where not observed
    values: jax.Array  # (V,) int8 true code (FREE / OCCUPIED) of each observed voxel


# ---------------------------------------------------------------------------------------
# Static tables, built once per (sensor, size) with NumPy at trace time


class _Camera(NamedTuple):
    reach: float  # range in voxels
    tan: float  # tan(fov / 2)
    n: int  # rays per image side
    column: np.ndarray  # (2, n, K) int32 (forward, right) offsets of the columns each azimuth
    #                     crosses, nearest first; K = the most any azimuth crosses
    s_in: np.ndarray  # (n, K) float32 horizontal distance where the azimuth enters it (inf: pad)
    s_out: np.ndarray  # (n, K) float32 ... and where it leaves it
    direction: np.ndarray  # (2, n) float32 (forward, right) horizontal unit vector per azimuth
    slope: np.ndarray  # (n, n) float32 rise per horizontal voxel of ray (azimuth, elevation)
    view: np.ndarray  # (3, V) int32 (forward, right, up) offsets of the view voxels
    view_ray: np.ndarray  # (V,) int32 ray nearest the direction of each view voxel
    view_distance: np.ndarray  # (V,) float32 distance to each view voxel's centre


def _in_raycast_view(a, b, c, tan, reach):
    """Camera-frame offsets (forward, right, up) -> centre inside the FOV and range, or the
    camera's own voxel (always observed: the robot is in it, so it maps FREE)."""
    edge = a * tan + _EPS
    inside = (abs(b) <= edge) & (abs(c) <= edge)
    own = (a == 0) & (b == 0) & (c == 0)
    return ((a >= 1) & inside & (a * a + b * b + c * c <= reach * reach + _EPS)) | own


def _in_frustum(a, b, c, depth, xp=jnp):
    """The reference's box-clipped pyramid, on camera-frame offsets."""
    half = xp.minimum(depth - 1, (3 * a) // 2 + 1)
    return (a >= 0) & (a <= depth - 1) & (abs(b) <= half) & (abs(c) <= half)


def _view_table(inside, extent: int) -> np.ndarray:
    """(3, V) int32 camera-frame offsets where inside(a, b, c) holds. (Sorting them by
    each heading's flat index was measured not to speed the occupancy scatter up.)"""
    grid = np.arange(-extent, extent + 1)
    offsets = np.stack([x.ravel() for x in np.meshgrid(grid, grid, grid, indexing="ij")])
    return offsets[:, inside(*offsets)].astype(np.int32)


def _crossed_columns(direction: np.ndarray, reach: float):
    """Columns a horizontal ray from a voxel centre crosses within `reach`, nearest first:
    offsets (m, 2), entry and exit distances (m,). Column boundaries lie at half integers
    around the camera and every boundary crossing enters a new column."""
    crossings = [np.zeros(1)]
    for d in np.abs(direction):
        if d > 1e-12:
            crossings.append((0.5 + np.arange(math.ceil(reach * d + 0.5) + 1)) / d)
    s = np.unique(np.concatenate(crossings))
    s_in, s_out = s[:-1], s[1:]
    keep = (s_out - s_in > 1e-9) & (s_in <= reach)  # drop corner touches and far columns
    s_in, s_out = s_in[keep], s_out[keep]
    offsets = np.floor(0.5 * (s_in + s_out)[:, None] * direction + 0.5).astype(np.int32)
    return offsets, s_in, s_out


@functools.lru_cache(maxsize=None)
def _camera(sensor: SensorConfig, size: int) -> _Camera:
    reach = sensor.range * size
    tan = math.tan(math.radians(sensor.fov_deg) / 2)
    n = max(2, math.ceil(sensor.rays_per_voxel * reach * tan - 1e-6))
    u = tan * ((2 * np.arange(n) + 1) / n - 1)  # image-plane coordinate of each ray
    direction = np.stack([np.ones(n), u]) / np.sqrt(1 + u * u)
    per_azimuth = [_crossed_columns(direction[:, i], reach) for i in range(n)]
    width = max(len(s_in) for _, s_in, _ in per_azimuth)
    column = np.zeros((2, n, width), np.int32)
    s_in, s_out = np.full((2, n, width), np.inf, np.float32)
    for i, (offsets, enter, leave) in enumerate(per_azimuth):
        column[:, i, : len(enter)] = offsets.T
        s_in[i, : len(enter)], s_out[i, : len(enter)] = enter, leave
    slope = (u[None, :] / np.sqrt(1 + u * u)[:, None]).astype(np.float32)
    view = _view_table(lambda a, b, c: _in_raycast_view(a, b, c, tan, reach), math.ceil(reach) + 1)
    a, b, c = view
    ahead = np.maximum(a, 1)  # the own voxel (a = 0) takes the central ray; any would do
    cell = lambda x: np.clip(np.floor((x / ahead / tan + 1) * n / 2), 0, n - 1).astype(np.int32)
    distance = np.sqrt(a * a + b * b + c * c).astype(np.float32)
    return _Camera(reach, tan, n, column, s_in, s_out, direction.astype(np.float32), slope,
                   view, cell(b) * n + cell(c), distance)


@functools.lru_cache(maxsize=None)
def _frustum(sensor: SensorConfig, size: int) -> tuple[int, np.ndarray]:
    depth = max(1, round(sensor.range * size))
    return depth, _view_table(lambda a, b, c: _in_frustum(a, b, c, depth, np), depth)


def view_size(sensor: SensorConfig, size: int) -> int:
    """V: the length of CastResult.voxels for this sensor and grid size."""
    table = _camera(sensor, size).view if sensor.model == "raycast" else _frustum(sensor, size)[1]
    return table.shape[1]


# ---------------------------------------------------------------------------------------
# Per-cast quantities


class _Pose(NamedTuple):
    """int32 scalars of one cast: the heading's forward and right axes, the camera voxel."""

    fx: jax.Array
    fy: jax.Array
    rx: jax.Array
    ry: jax.Array
    x: jax.Array
    y: jax.Array
    z: jax.Array

    def to_world(self, a, b):
        """Camera-frame horizontal offsets (forward a, right b) -> world columns (x, y)."""
        return self.x + a * self.fx + b * self.rx, self.y + a * self.fy + b * self.ry


def _pose(position, heading, size: int) -> _Pose:
    """Computed as one masked max over the four headings: XLA:CPU never fuses a reduction
    into its consumers, so these are computed once per cast rather than re-derived in
    every per-voxel loop (which would then also stop vectorising)."""
    static = np.concatenate([_FORWARD, _RIGHT, np.zeros((4, 3), np.int32)], 1)
    dynamic = jnp.concatenate([jnp.zeros(4, jnp.int32), geometry.voxel_of(position, size)])
    chosen = jnp.arange(geometry.N_HEADINGS)[:, None] == heading
    return _Pose(*jnp.max(jnp.where(chosen, static + dynamic, jnp.iinfo(jnp.int32).min), axis=0))


def _column_height(height, x, y, size: int):
    """Building height at columns (x, y); 0 outside the grid."""
    inside = (x >= 0) & (x < size) & (y >= 0) & (y < size)
    index = jnp.clip(x, 0, size - 1) * size + jnp.clip(y, 0, size - 1)
    return jnp.where(inside, take_flat(height, index), 0)


def _clear_distances(height, pose: _Pose, cam: _Camera, size: int) -> jax.Array:
    """(n * n,) float32 per ray (azimuth-major): the distance to its first hit, inf when it
    hits nothing within range."""
    h = _column_height(height, *pose.to_world(*cam.column), size)
    h = jnp.where(np.isfinite(cam.s_in), h, 0)  # (n, K); padding slots: no building
    rise = h.astype(jnp.float32) - (pose.z + 0.5)  # (n, K) roof height above the camera

    # Where each ray ends: at its range, where it leaves the grid sideways, or at the
    # ground / ceiling; as horizontal distances.
    slope = cam.slope  # (n, n)
    with np.errstate(divide="ignore"):
        inv_slope = np.where(slope != 0, 1.0 / slope, 0.0).astype(np.float32)
        inv_in, inv_out = (1.0 / cam.s_in).astype(np.float32), (1.0 / cam.s_out).astype(np.float32)
    leave = jnp.inf
    for w, c in ((cam.direction[0] * pose.fx + cam.direction[1] * pose.rx, pose.x),
                 (cam.direction[0] * pose.fy + cam.direction[1] * pose.ry, pose.y)):
        safe = jnp.where(w == 0, 1.0, w)
        leave = jnp.minimum(leave, jnp.where(w > 0, (size - c - 0.5) / safe,
                                             jnp.where(w < 0, -(c + 0.5) / safe, jnp.inf)))
    z0 = pose.z + 0.5
    vertical = jnp.where(slope > 0, (size - z0) * inv_slope,
                         jnp.where(slope < 0, -z0 * inv_slope, jnp.inf))
    norm = np.sqrt(1.0 + slope * slope).astype(np.float32)  # 3D length per horizontal voxel
    s_end = jnp.minimum(jnp.minimum(cam.reach / norm, leave[:, None]), vertical)

    # A ray of slope m is blocked in a column iff it dips below the roof there:
    # m < rise / s_in when the roof is above the camera (it hits the wall at s_in), else
    # m < rise / s_out (it comes down onto the roof at rise / m). Empty columns never block.
    threshold = jnp.where(h > 0, jnp.where(rise > 0, rise * inv_in, rise * inv_out), -jnp.inf)
    m, s_in, rise = slope[:, :, None], cam.s_in[:, None, :], rise[:, None, :]
    s_hit = jnp.where(m * s_in < rise, s_in, rise * inv_slope[:, :, None])
    hit = (m < threshold[:, None, :]) & (s_hit <= s_end[:, :, None])

    # Columns are disjoint along a ray, so its first hit is the nearest one. The minimum
    # runs over the distances' bit patterns (order-preserving for non-negative floats):
    # XLA:CPU vectorises integer reductions, not float ones.
    bits = jax.lax.bitcast_convert_type(s_hit * norm[:, :, None], jnp.int32)
    first = jnp.min(jnp.where(hit, bits, _INF_BITS), axis=-1)
    return jax.lax.bitcast_convert_type(first, jnp.float32).reshape(-1)


def _windows_seen(world: World, pose: _Pose, cam: _Camera, clear, tested):
    """(T,) bool: the window is among `tested` (T,) bool and some face of it that is turned
    to the camera and open to the air is in sight, by the map's rule for building voxels
    applied to the face centre q: the ray nearest q's direction gets within `_SURFACE` of
    q. (Aiming at faces rather than the voxel centre matters for walls seen at an angle,
    whose centre rays enter through the neighbouring voxel.)"""
    n = cam.n
    x, y, z = (world.target_voxel[:, k] for k in range(3))
    rel_centre = [(v - c).astype(jnp.float32) for v, c in zip((x, y, z), (pose.x, pose.y, pose.z))]
    toward = [jnp.where(r < 0, 1, -1) for r in rel_centre]  # the side facing the camera
    faces = world.target_open  # (T, 5): -x, +x, -y, +y, +z (world.FACES)
    open_air = (jnp.where(toward[0] > 0, faces[:, 1], faces[:, 0]),
                jnp.where(toward[1] > 0, faces[:, 3], faces[:, 2]),
                (toward[2] > 0) & faces[:, 4])
    fx, fy, rx, ry = (v.astype(jnp.float32) for v in pose[:4])
    in_sight = []
    for axis in range(3):
        rel = [r + 0.5 * t if k == axis else r for k, (r, t) in enumerate(zip(rel_centre, toward))]
        per_cell = (n / 2) / (cam.tan * jnp.maximum(rel[0] * fx + rel[1] * fy, 1e-3))
        cell = lambda s: jnp.clip(jnp.floor(s * per_cell + n / 2), 0, n - 1).astype(jnp.int32)
        reach = take_flat(clear, cell(rel[0] * rx + rel[1] * ry) * n + cell(rel[2])) + _SURFACE
        in_sight.append(tested & (rel[axis] * toward[axis] < 0) & open_air[axis]
                        & (reach * reach >= sum(r * r for r in rel)))
    # An integer reduction, which XLA materialises once: the consumers of `seen` (rewards,
    # discoveries, the utility) would each recompute an elementwise `or`, and a boolean
    # `any` over three faces XLA rewrites into one.
    return jnp.sum(jnp.stack(in_sight).astype(jnp.int32), axis=0) > 0


# ---------------------------------------------------------------------------------------
# Public API


def cast(world: World, position: jax.Array, heading: jax.Array, sensor: SensorConfig,
         size: int) -> CastResult:
    """Senses from one pose: position (3,) in [0, 1]^3, heading () int in 0..3 (index into
    geometry.HEADING_VECTORS); sensor and size static. Pure; vmap over robots and envs."""
    chex.assert_shape(position, (3,))
    chex.assert_shape(heading, ())
    chex.assert_shape(world.height, (size, size))
    height = world.height.reshape(-1)
    pose = _pose(position, heading.astype(jnp.int32), size)
    if sensor.model == "raycast":
        cam = _camera(sensor, size)
        table = cam.view
    else:
        depth, table = _frustum(sensor, size)

    # View voxels: world coordinates and true codes.
    a, b, c = table
    voxel = (*pose.to_world(a, b), pose.z + c)
    keep = functools.reduce(jnp.logical_and, [(v >= 0) & (v < size) for v in voxel])
    solid = voxel[2] < _column_height(height, voxel[0], voxel[1], size)
    values = jnp.where(solid, geometry.OCCUPIED, geometry.FREE).astype(jnp.int8)

    # Windows in camera-frame offsets.
    offset = [world.target_voxel[:, k] - v for k, v in enumerate((pose.x, pose.y, pose.z))]
    ahead = offset[0] * pose.fx + offset[1] * pose.fy
    right = offset[0] * pose.rx + offset[1] * pose.ry

    if sensor.model == "raycast":
        clear = _clear_distances(height, pose, cam, size)
        keep &= cam.view_distance <= take_flat(clear, cam.view_ray) + jnp.where(solid, _SURFACE, 0.0)
        seen = _windows_seen(world, pose, cam, clear, world.target_valid & _in_raycast_view(
            ahead, right, offset[2], cam.tan, cam.reach))
    else:
        seen = world.target_valid & _in_frustum(ahead, right, offset[2], depth)

    flat = (voxel[0] * size + voxel[1]) * size + voxel[2]
    return CastResult(seen=seen,
                      voxels=jnp.where(keep, flat, size**3).astype(jnp.int32), values=values)


def _flat_scatter(write: str):
    """target (L,), index, values -> target with target[index] written (`write`: "set",
    "max" or "add"); indices outside [0, L) are dropped."""

    @jax.custom_batching.custom_vmap
    def scatter(target: jax.Array, index: jax.Array, values: jax.Array) -> jax.Array:
        length = target.shape[0]
        index = jnp.where((index >= 0) & (index < length), index, length)
        return getattr(target.at[index], write)(values, mode="drop")

    @scatter.def_vmap
    def scatter_vmap(axis_size, in_batched, target, index, values):
        """Batched maps become one long map, indices offset by each map's position: one
        flat scatter runs ~2.5x faster on XLA:CPU than the batched scatter vmap would emit
        (which also materialises a (map, voxel) index pair per update). Nested vmaps fold
        again."""
        target, index, values = (x if b else jnp.broadcast_to(x, (axis_size, *x.shape))
                                 for x, b in zip((target, index, values), in_batched))
        length = target.shape[-1]
        if axis_size * length >= 2**31:  # flat indices would overflow int32
            return jax.vmap(scatter.fun)(target, index, values), True
        start = (jnp.arange(axis_size, dtype=jnp.int32) * length)[:, None]
        index = jnp.where((index >= 0) & (index < length), index + start, axis_size * length)
        flat = scatter(target.reshape(-1), index.reshape(-1), values.reshape(-1))
        return flat.reshape(axis_size, length), True

    return scatter


scatter_set = _flat_scatter("set")
scatter_max = _flat_scatter("max")
scatter_add = _flat_scatter("add")


def utility(result: CastResult) -> jax.Array:
    """int32 number of windows seen (per cast; batched results give one per cast)."""
    return jnp.sum(result.seen, axis=-1, dtype=jnp.int32)
