"""Depth-camera sensing: which windows a pose sees, and which voxels it reveals.

Two models, picked by the static `SensorConfig.model`:

raycast (default). A pinhole camera at the exact position, looking along a horizontal
heading, casts an n x n grid of rays through the centres of the image-plane cells. Buildings
are boxes on the ground, so a ray's first hit only depends on the columns its horizontal
projection crosses, and all rays of one azimuth cross the same columns: per azimuth we list
the crossed columns exactly (each x / y boundary crossing enters a new column), turn each
into the slope below which it blocks a ray, and a ray's first hit is the nearest column
whose threshold exceeds its slope. That is one height gather per (azimuth, column) rather
than one per ray sample.

The view is the static set of voxels whose centres lie inside the field of view and range
as seen from the centre of the camera's voxel (precomputed per heading, in flat-index order
so the occupancy scatter walks memory forwards). A view voxel is observed iff the ray
nearest the direction of its centre reaches the centre unblocked or, for a building voxel,
first hits it or one of its 26 neighbours (a wall seen at an angle is entered through the
next voxel of the same wall). Observed codes are copied from the truth, so a map never
contradicts the world and OCCUPIED never turns FREE; voxels behind a wall stay UNKNOWN.
A window is seen iff one of its faces turned to the camera and open to the air is in
sight (`_windows_seen`); this finer test can see a window whose voxel the coarser map rule
leaves UNKNOWN.

frustum (the reference's, design.md section 1). Every voxel with forward offset
0 <= f <= depth - 1 and both other offsets within min(depth - 1, floor(1.5 f) + 1) of the
robot's voxel, clipped to the grid, without occlusion; windows in that set are seen.

Vectors are handled as separate x / y / z arrays: XLA:CPU runs reductions over a trailing
axis of 2 or 3 (norms, dot products, `all`) far slower than the equivalent elementwise code.
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

from jaxmripp import geometry
from jaxmripp.config import SensorConfig
from jaxmripp.world import World

# Camera frame per heading: forward f, right r = f x up (both horizontal), up = +z.
_FORWARD = geometry.HEADING_VECTORS.astype(np.int32)
_RIGHT = np.stack([_FORWARD[:, 1], -_FORWARD[:, 0], np.zeros(4, np.int32)], -1)
_FRAMES = np.stack([_FORWARD[:, 0], _FORWARD[:, 1], _RIGHT[:, 0], _RIGHT[:, 1]], -1)  # (4, 4)
_EPS = 1e-4  # slack for float comparisons on exact boundaries (45 degree edges, range)
_NUDGE = 1e-3  # voxels: a point this far past a boundary crossing names the column entered
_NONE = np.int32(2**31 - 1)
_SURFACE = 1.0  # voxels: how close a ray must come to a building voxel's centre to see it


@flax.struct.dataclass
class CastResult:
    """What one pose senses (T = target capacity, V = `view_size(sensor, G)`)."""

    seen: jax.Array  # (T,) bool windows seen from this pose (valid ones only)
    voxels: jax.Array  # (V,) int32 flat voxel indices observed; G**3 where not observed
    values: jax.Array  # (V,) int8 true code (FREE / OCCUPIED) of each observed voxel


class _Camera(NamedTuple):
    """Static tables of one (sensor, size), built once with NumPy at trace time. The camera
    sits at the centre of the robot's voxel, so all ray geometry is static."""

    reach: float  # range in voxels
    tan: float  # tan(fov / 2)
    n: int  # rays per image side
    column: np.ndarray  # (2, n, K) int32 (forward, right) offsets of the columns each
    #                     azimuth crosses, nearest first; K = the most any azimuth crosses
    s_in: np.ndarray  # (n, K) float32 horizontal distance where the azimuth enters the column
    s_out: np.ndarray  # (n, K) float32 ... and leaves it
    real: np.ndarray  # (n, K) bool: a column, not padding
    direction: np.ndarray  # (2, n) float32 (forward, right) horizontal unit vector per azimuth
    slope: np.ndarray  # (n, n) float32 rise per horizontal voxel of ray (azimuth, elevation)
    view: np.ndarray  # (4, 3, V) int32 view voxel offsets per heading, in flat-index order
    view_ray: np.ndarray  # (4, V) int32 ray nearest the direction of each view voxel
    view_distance: np.ndarray  # (4, V) float32 distance to each view voxel's centre


def _in_raycast_view(a, b, c, tan, reach):
    """Integer camera-frame offsets (forward, right, up) -> inside FOV and range."""
    edge = a * tan + _EPS
    inside = (abs(b) <= edge) & (abs(c) <= edge)
    return (a >= 1) & inside & (a * a + b * b + c * c <= reach * reach + _EPS)


def _in_frustum(a, b, c, depth, xp=jnp):
    """The reference's box-clipped pyramid, on integer camera-frame offsets."""
    half = xp.minimum(depth - 1, (3 * a) // 2 + 1)
    return (a >= 0) & (a <= depth - 1) & (abs(b) <= half) & (abs(c) <= half)


def _view_table(inside, extent: int, *fields) -> tuple[np.ndarray, ...]:
    """Camera-frame offsets (a, b, c) where inside(a, b, c) holds -> (4, 3, V) world offsets
    per heading in flat-index order (the occupancy scatter then walks memory forwards),
    and each field(a, b, c) as (4, V) in the same orders."""
    grid = np.arange(-extent, extent + 1)
    a, b, c = (x.ravel() for x in np.meshgrid(grid, grid, grid, indexing="ij"))
    keep = inside(a, b, c)
    a, b, c = a[keep], b[keep], c[keep]
    values = [field(a, b, c) for field in fields]
    tables, sorted_fields = [], []
    for h in range(geometry.N_HEADINGS):
        offsets = a[:, None] * _FORWARD[h] + b[:, None] * _RIGHT[h] + c[:, None] * np.array([0, 0, 1])
        order = np.lexsort((offsets[:, 2], offsets[:, 1], offsets[:, 0]))
        tables.append(offsets[order].T)
        sorted_fields.append([v[order] for v in values])
    return (np.stack(tables).astype(np.int32),
            *(np.stack([f[k] for f in sorted_fields]) for k in range(len(fields))))


def _crossed_columns(direction: np.ndarray, reach: float):
    """Columns a horizontal ray from a voxel centre crosses within `reach`, nearest first:
    (offsets (m, 2), entry distances (m,), exit distances (m,)). Boundaries lie at half
    integers around the camera; every boundary crossing enters a new column."""
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
    s_in = np.full((n, width), np.inf, np.float32)
    s_out = np.full((n, width), np.inf, np.float32)
    for i, (offsets, enter, leave) in enumerate(per_azimuth):
        column[:, i, : len(enter)] = offsets.T
        s_in[i, : len(enter)], s_out[i, : len(enter)] = enter, leave
    slope = (u[None, :] / np.sqrt(1 + u * u)[:, None]).astype(np.float32)

    def nearest_ray(a, b, c):
        cell = lambda x: np.clip(np.floor((x / a / tan + 1) * n / 2), 0, n - 1).astype(np.int32)
        return cell(b) * n + cell(c)

    view, view_ray, view_distance = _view_table(
        lambda a, b, c: _in_raycast_view(a, b, c, tan, reach), math.ceil(reach) + 1,
        nearest_ray, lambda a, b, c: np.sqrt(a * a + b * b + c * c).astype(np.float32))
    return _Camera(reach, tan, n, column, s_in, s_out, np.isfinite(s_in),
                   direction.astype(np.float32), slope, view, view_ray, view_distance)


@functools.lru_cache(maxsize=None)
def _frustum_view(sensor: SensorConfig, size: int) -> tuple[int, np.ndarray]:
    depth = max(1, round(sensor.range * size))
    return depth, _view_table(lambda a, b, c: _in_frustum(a, b, c, depth, np), depth)[0]


def view_size(sensor: SensorConfig, size: int) -> int:
    """V: the length of CastResult.voxels for this sensor and grid size."""
    if sensor.model == "raycast":
        return _camera(sensor, size).view.shape[-1]
    return _frustum_view(sensor, size)[1].shape[-1]


# ---------------------------------------------------------------------------------------
# Ray casting on the height map


def _clear_distances(height, camera, heading, frame, cam: _Camera, size: int):
    """(n * n,) float32 per ray (azimuth-major): how far it stays clear, i.e. the distance
    to its first hit, inf when it hits nothing within range."""
    cx, cy, cz = camera
    fx, fy, rx, ry = frame
    z0 = (cz + 0.5).astype(jnp.float32)
    along, across = cam.column
    x, y = cx + along * fx + across * rx, cy + along * fy + across * ry  # (n, K)
    inside = cam.real & (x >= 0) & (x < size) & (y >= 0) & (y < size)
    offsets = np.stack([(along * f[0] + across * r[0]) * size + along * f[1] + across * r[1]
                        for f, r in zip(_FORWARD, _RIGHT)])  # (4, n, K) flat column offsets
    index = jnp.clip(cx * size + cy + offsets, 0, size * size - 1)  # wrong only where not inside
    h = jnp.where(inside, height.reshape(-1)[_gather_index(index, heading)], 0)

    # A ray of slope m (rise per horizontal voxel) is blocked in a column iff its z dips
    # below the roof there: m < (h - z0) / s_in when the roof is above the camera, else
    # m < (h - z0) / s_out. Empty columns never block (the ground ends the ray instead).
    rise = h - z0
    with np.errstate(divide="ignore"):
        inv_in, inv_out = (1.0 / cam.s_in).astype(np.float32), (1.0 / cam.s_out).astype(np.float32)
    threshold = jnp.where(rise > 0, rise * inv_in, rise * inv_out)
    threshold = jnp.where(h > 0, threshold, -jnp.inf)

    # Columns are listed nearest first, so the first hit is the smallest blocking slot. Its
    # roof height and entry distance are read back with one-hot integer maxima (the float
    # entry distance through its bits, order-preserving for non-negative floats): integer
    # reductions vectorise on XLA:CPU, float argmin / take_along_axis run ~50x slower.
    count = cam.s_in.shape[1]
    slot = np.arange(count, dtype=np.int32)
    first = jnp.min(jnp.where(cam.slope[:, :, None] < threshold[:, None, :], slot, count), -1)
    pick = first[:, :, None] == slot
    h_k = jnp.max(jnp.where(pick, h[:, None, :], 0), -1).astype(jnp.float32)
    s_bits = np.where(cam.real, cam.s_in, 0).astype(np.float32).view(np.int32)
    s_k = jax.lax.bitcast_convert_type(jnp.max(jnp.where(pick, s_bits[:, None, :], 0), -1),
                                       jnp.float32)

    # Blocked above the camera: through a wall at s_k. Else it came down onto the roof.
    slope = cam.slope
    with np.errstate(divide="ignore"):
        inv_slope = np.where(slope != 0, 1.0 / slope, 0.0).astype(np.float32)
    side = z0 + slope * s_k < h_k
    s_hit = jnp.where(side, s_k, (h_k - z0) * inv_slope)

    # The ray ends at its range, where it leaves the grid sideways, or at ground / ceiling.
    wx = cam.direction[0] * fx + cam.direction[1] * rx  # (n,) world horizontal direction
    wy = cam.direction[0] * fy + cam.direction[1] * ry
    leave = [jnp.where(w > 0, (size - c - 0.5) / jnp.where(w == 0, 1.0, w),
                       jnp.where(w < 0, (c + 0.5) / jnp.where(w == 0, 1.0, -w), jnp.inf))
             for w, c in ((wx, cx), (wy, cy))]
    vertical = jnp.where(slope > 0, (size - z0) * inv_slope,
                         jnp.where(slope < 0, -z0 * inv_slope, jnp.inf))
    norm = np.sqrt(1.0 + slope * slope).astype(np.float32)  # 3D length per horizontal voxel
    s_end = jnp.minimum(jnp.minimum(cam.reach / norm, jnp.minimum(*leave)[:, None]), vertical)
    hit = (first < count) & (s_hit <= s_end)
    return jnp.where(hit, s_hit * norm, jnp.inf).reshape(-1)


def _nearest_ray(rel, frame, cam: _Camera):
    """Directions (x, y, z) from the camera -> (row, column) of the nearest grid ray."""
    fx, fy, rx, ry = frame
    a = jnp.maximum(rel[0] * fx + rel[1] * fy, 1e-3)  # in-view points are ahead
    per_cell = (cam.n / 2) / (a * cam.tan)

    def cell(x):
        return jnp.clip(jnp.floor(x * per_cell + cam.n / 2), 0, cam.n - 1).astype(jnp.int32)

    return cell(rel[0] * rx + rel[1] * ry), cell(rel[2])


def _windows_seen(world: World, camera, frame, cam: _Camera, clear, size: int):
    """(T,) bool: some face of the window turned to the camera and open to the air is in
    sight. A face is in sight iff the ray nearest the direction of its centre q reaches q
    unblocked, or first hits a surface within one voxel of q (rays are about a voxel apart
    at full range, so a ray aimed at q may land on the next voxel of the same wall)."""
    n = cam.n
    fx, fy, rx, ry = (x.astype(jnp.float32) for x in frame)
    x, y, z = (world.target_voxel[:, k] for k in range(3))
    rel_centre = [(v - c).astype(jnp.float32) for v, c in zip((x, y, z), camera)]
    toward = [jnp.where(r < 0, 1, -1) for r in rel_centre]  # the side facing the camera

    def column_height(cx, cy):
        inside = (cx >= 0) & (cx < size) & (cy >= 0) & (cy < size)
        index = jnp.clip(cx, 0, size - 1) * size + jnp.clip(cy, 0, size - 1)
        return jnp.where(inside, world.height.reshape(-1)[index], 0)

    open_air = (column_height(x + toward[0], y) <= z, column_height(x, y + toward[1]) <= z,
                (toward[2] > 0) & (z + 1 >= column_height(x, y)))
    seen = jnp.zeros(x.shape, bool)
    for axis in range(3):
        rel = [r + 0.5 * t if k == axis else r for k, (r, t) in enumerate(zip(rel_centre, toward))]
        i, j = _nearest_ray(rel, (fx, fy, rx, ry), cam)
        t = clear[i * n + j]
        u, v = (cam.tan * ((2 * c + 1) / n - 1) for c in (i, j))  # the ray: forward + u right + v up
        along = jnp.where(jnp.isfinite(t), t, 0.0) / jnp.sqrt(1.0 + u * u + v * v)
        landing = (along * (fx + u * rx), along * (fy + u * ry), along * v)
        miss = sum((q - r) ** 2 for q, r in zip(landing, rel))
        in_sight = (jnp.isfinite(t) & (miss <= 1.0)) | (t * t >= sum(r * r for r in rel))
        facing = rel[axis] * toward[axis] < 0
        seen |= facing & open_air[axis] & in_sight
    return seen


# ---------------------------------------------------------------------------------------
# Public API


def _select(table: np.ndarray, heading):
    """table[heading] for a static table with one entry per heading, as an elementwise
    select: indexing by a batched heading would be a gather."""
    return sum(jnp.where(heading == h, table[h], 0) for h in range(geometry.N_HEADINGS))


def _gather_index(index_per_heading, heading):
    """The heading's entry of a (4, ...) int32 index array, computed as an integer max over
    headings. XLA:CPU fuses elementwise index arithmetic into a gather's loop, which then
    runs unvectorised (~10x slower); a reduction is never fused into its consumer, so the
    index is computed vectorised once and the gather only loads."""
    chosen = heading == np.arange(geometry.N_HEADINGS).reshape((-1,) + (1,) * (index_per_heading.ndim - 1))
    return jnp.max(jnp.where(chosen, index_per_heading, -1), axis=0)


def _view(table: np.ndarray, heading, camera, size: int):
    """(4, 3, V) static offsets -> the heading's view voxels (x, y, z) around the camera and
    their flat column indices (clipped into the grid; for the height gather)."""
    voxel = [camera[k] + _select(table[:, k], heading) for k in range(3)]
    clipped = [jnp.clip(camera[k] + table[:, k], 0, size - 1) for k in range(2)]
    return voxel, _gather_index(clipped[0] * size + clipped[1], heading)


def _truth(height, voxel, column, size):
    """View voxels (x, y, z) and their columns -> in grid, true code (int8)."""
    x, y, z = voxel
    in_grid = (x >= 0) & (x < size) & (y >= 0) & (y < size) & (z >= 0) & (z < size)
    solid = z < height.reshape(-1)[column]
    return in_grid, jnp.where(solid, geometry.OCCUPIED, geometry.FREE).astype(jnp.int8)


def cast(world: World, position: jax.Array, heading: jax.Array, sensor: SensorConfig,
         size: int) -> CastResult:
    """Senses from one pose: position (3,) in [0, 1]^3, heading () int index; sensor and
    size static. The camera sits at the centre of the position's voxel. Pure; vmap over
    robots and environments."""
    chex.assert_shape(position, (3,))
    chex.assert_shape(heading, ())
    chex.assert_shape(world.height, (size, size))
    heading = heading.astype(jnp.int32)
    frame = tuple(_select(_FRAMES[:, k], heading) for k in range(4))  # fx, fy, rx, ry
    camera = tuple(geometry.voxel_of(position, size)[k] for k in range(3))
    offset = [world.target_voxel[:, k] - camera[k] for k in range(3)]
    a = offset[0] * frame[0] + offset[1] * frame[1]  # windows in camera-frame offsets
    b = offset[0] * frame[2] + offset[1] * frame[3]

    if sensor.model == "frustum":
        depth, table = _frustum_view(sensor, size)
        voxel, column = _view(table, heading, camera, size)
        keep, values = _truth(world.height, voxel, column, size)
        seen = _in_frustum(a, b, offset[2], depth)
    else:
        cam = _camera(sensor, size)
        clear = _clear_distances(world.height, camera, heading, frame, cam, size)
        voxel, column = _view(cam.view, heading, camera, size)
        keep, values = _truth(world.height, voxel, column, size)
        # A view voxel is observed iff its ray reaches its centre, or comes within
        # _SURFACE of it for a building voxel (stopping on its face, or on the next voxel
        # of a wall seen at an angle); deeper building voxels and all behind stay unknown.
        reach = clear[_gather_index(cam.view_ray, heading)]
        reach += jnp.where(values == geometry.OCCUPIED, _SURFACE, 0.0)
        keep &= _select(cam.view_distance, heading) <= reach
        seen = _in_raycast_view(a, b, offset[2], cam.tan, cam.reach) & _windows_seen(
            world, camera, frame, cam, clear, size)

    flat = (voxel[0] * size + voxel[1]) * size + voxel[2]
    return CastResult(seen=seen & world.target_valid,
                      voxels=jnp.where(keep, flat, size**3).astype(jnp.int32), values=values)


def update_occupancy(occupancy: jax.Array, result: CastResult) -> jax.Array:
    """(G, G, G) int8 map -> the map with the observed voxels set to their true codes."""
    size = occupancy.shape[0]
    chex.assert_shape(occupancy, (size, size, size))
    flat = occupancy.reshape(-1).at[result.voxels].set(result.values, mode="drop")
    return flat.reshape(occupancy.shape)


def empty_occupancy(size: int) -> jax.Array:
    """(G, G, G) int8 map with every voxel UNKNOWN."""
    return jnp.full((size, size, size), geometry.UNKNOWN, jnp.int8)


def utility(result: CastResult) -> jax.Array:
    """int32 number of windows seen (per cast; batched results give one per cast)."""
    return jnp.sum(result.seen, axis=-1, dtype=jnp.int32)
