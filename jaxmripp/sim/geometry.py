"""The JAX implementation of `jaxmripp.spec.grid`: voxel indexing and the traversal of a
line of flight.

Codes, headings and the traversal's slot count are defined in the spec and re-exported
here for the simulation's modules.
"""

from __future__ import annotations

from typing import Protocol, Union, runtime_checkable

import jax
import jax.numpy as jnp

from jaxmripp.spec import vectors
from jaxmripp.spec.grid import (FREE, HEADING_ANGLES, HEADING_VECTORS, N_HEADINGS,  # noqa: F401
                                OCCUPIED, UNKNOWN, traversal_steps)


def voxel_of(position: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) positions -> (..., 3) int32 voxel indices, clipped into the grid."""
    # The position rounded on its own: XLA:CPU would otherwise fold the scaling into the
    # arithmetic that made it (a take-off pad's start + spacing * i), and a pad on a voxel
    # boundary would land in the voxel beside the one the traversal (and the runtime) use.
    scaled = vectors.rounded(position, jnp) * size
    return jnp.clip(jnp.floor(scaled), 0, size - 1).astype(jnp.int32)


def linear_index(voxel: jnp.ndarray, size: int) -> jnp.ndarray:
    """(..., 3) voxel indices -> (...,) flat index into a C-ordered (G, G, G) grid."""
    return (voxel[..., 0] * size + voxel[..., 1]) * size + voxel[..., 2]


@jax.custom_batching.custom_vmap
def take_flat(table: jax.Array, index: jax.Array) -> jax.Array:
    """table (L,)[index] for indices known to lie in [0, L)."""
    return jnp.take(table, index, mode="clip")


@take_flat.def_vmap
def take_flat_vmap(axis_size, in_batched, table, index):
    """Batched tables become one long table, indices offset by each table's position: a
    flat gather, rather than the (table, entry) index pairs vmap would otherwise build."""
    if not in_batched[0]:
        return take_flat(table, index), in_batched[1]
    if not in_batched[1]:
        index = jnp.broadcast_to(index, (axis_size, *index.shape))
    length = table.shape[-1]
    if axis_size * length >= 2**31:  # flat indices would overflow int32
        return jax.vmap(take_flat.fun)(table, index), True
    start = jnp.arange(axis_size, dtype=jnp.int32) * length
    start = start.reshape((-1,) + (1,) * (index.ndim - 1))
    return take_flat(table.reshape(-1), index + start), True


def inside_world(position: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) -> (...,) True where the position lies in the closed unit cube."""
    return jnp.all((position >= 0.0) & (position <= 1.0), axis=-1)


def traverse(start: jnp.ndarray, end: jnp.ndarray, size: int, max_length: float,
             flat: bool = False) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """(3,), (3,) -> voxels (V, 3) int32 (with `flat`: (V,) their `linear_index`), entry
    (V,) float32, complete () bool: the traversal rule of `jaxmripp.spec.grid`, V = 3 + 2 K
    with K = traversal_steps(G, max_length).

    Steps from crossing to crossing (all axes that cross at the same t at once) and lists,
    per step, the voxel owning the crossing point and the voxel entered after it, with the
    t in [0, 1] where the flight enters it; then the end voxel. Unused slots repeat the
    start voxel (entry 0), so `all` and `any` over the list need no mask. `complete` is
    False when a segment longer than max_length had crossings left after K steps: callers
    treat the rest of such a flight as not clear, so nothing is skipped silently.
    """
    g = jnp.float32(size)
    # Per-axis scalars throughout: XLA:CPU does not vectorise reductions over a trailing
    # axis of 3.
    # Positions rounded on their own, then scaled to voxels and rounded again: XLA:CPU
    # would otherwise fold the scaling into the arithmetic that made a position, or fuse
    # the product into the subtraction after it (one rounding instead of two), and visit
    # other voxels than the spec (and the runtime) at exact ties.
    start, end = (vectors.rounded(v.astype(jnp.float32), jnp) for v in (start, end))
    s = [vectors.rounded(start[k] * g, jnp) for k in range(3)]
    e = [vectors.rounded(end[k] * g, jnp) for k in range(3)]
    d = [e[k] - s[k] for k in range(3)]
    step = [jnp.sign(d[k]).astype(jnp.int32) for k in range(3)]
    safe_d = [jnp.where(d[k] == 0, 1.0, d[k]) for k in range(3)]
    first = [jnp.floor(s[k]).astype(jnp.int32) for k in range(3)]

    def crossing_t(k, plane):
        ahead = jnp.where(d[k] > 0, plane < e[k], plane > e[k]) & (d[k] != 0)
        return jnp.where(ahead, (plane - s[k]) / safe_d[k], jnp.inf)

    leave = [jnp.where(d[k] < 0, jnp.ceil(s[k]) - 1, jnp.floor(s[k])).astype(jnp.int32)
             for k in range(3)]
    plane = [jnp.where(d[k] > 0, jnp.floor(s[k]) + 1, jnp.ceil(s[k]) - 1) for k in range(3)]

    def emit(voxel):
        """Per-axis int32 indices -> the clipped voxel (3,), or its flat index: one int32
        per voxel instead of three (the map lookups of 60 flights per robot read only it)."""
        clipped = jnp.stack([jnp.clip(voxel[k], 0, size - 1) for k in range(3)], axis=-1)
        return linear_index(clipped, size) if flat else clipped

    def advance(carry, _):
        voxel, plane, t = carry
        t_min = jnp.minimum(jnp.minimum(t[0], t[1]), t[2])
        live = jnp.isfinite(t_min)
        tie = [(t[k] == t_min) & live for k in range(3)]  # axes crossing at this t step now
        point = [voxel[k] + jnp.where(tie[k] & (d[k] > 0), step[k], 0) for k in range(3)]
        voxel = [voxel[k] + jnp.where(tie[k], step[k], 0) for k in range(3)]
        plane = [plane[k] + jnp.where(tie[k], step[k], 0).astype(jnp.float32) for k in range(3)]
        t = [jnp.where(tie[k], crossing_t(k, plane[k]), t[k]) for k in range(3)]
        out = (emit([jnp.where(live, point[k], first[k]) for k in range(3)]),
               emit([jnp.where(live, voxel[k], first[k]) for k in range(3)]),
               jnp.where(live, t_min, 0.0))
        return (voxel, plane, t), out

    t = [crossing_t(k, plane[k]) for k in range(3)]
    (_, _, left), (points, afters, times) = jax.lax.scan(
        advance, (leave, plane, t), None, length=traversal_steps(size, max_length))
    voxels = jnp.concatenate([emit(first)[None], emit(leave)[None], points, afters,
                              emit([jnp.floor(e[k]).astype(jnp.int32) for k in range(3)])[None]])
    entry = jnp.concatenate([jnp.zeros(2), times, times, jnp.ones(1)])
    complete = jnp.isinf(left[0]) & jnp.isinf(left[1]) & jnp.isinf(left[2])
    return voxels, entry.astype(jnp.float32), complete


@runtime_checkable
class CodeReader(Protocol):
    """A map read through its codes at flat voxel indices, without being written out as an
    int8 grid (a robot's view of its team map, `sim.maps.RobotMap`)."""

    def codes(self, flat: jax.Array) -> jax.Array: ...


# What the map readers below take: a (G, G, G) int8 grid of codes or a CodeReader.
Map = Union[jax.Array, CodeReader]


def read_codes(grid: Map, flat: jnp.ndarray) -> jnp.ndarray:
    """The codes of a map at flat voxel indices."""
    if isinstance(grid, CodeReader):
        return grid.codes(flat)
    return take_flat(grid.reshape(-1), flat)


def traversed_codes(start: jnp.ndarray, ends: jnp.ndarray, grid: Map, size: int,
                    max_length: float) -> jnp.ndarray:
    """(3,), (M, 3), a map (`read_codes`) -> (M, V) the codes of every traversed voxel, and
    (M,) whether each list is complete (see `traverse`)."""
    flat, _, complete = jax.vmap(traverse, in_axes=(None, 0, None, None, None))(
        start, ends, size, max_length, True)
    return read_codes(grid, flat), complete


def known_free(start: jnp.ndarray, ends: jnp.ndarray, occupancy: Map, size: int,
               max_length: float) -> jnp.ndarray:
    """(3,), (M, 3), a map (`read_codes`) -> (M,) True where every traversed voxel is FREE."""
    codes, complete = traversed_codes(start, ends, occupancy, size, max_length)
    return jnp.all(codes == FREE, axis=-1) & complete


def not_mapped_occupied(start: jnp.ndarray, ends: jnp.ndarray, occupancy: Map, size: int,
                        max_length: float) -> jnp.ndarray:
    """(3,), (M, 3), a map (`read_codes`) -> (M,) True where no traversed voxel is
    OCCUPIED."""
    codes, complete = traversed_codes(start, ends, occupancy, size, max_length)
    return jnp.all(codes != OCCUPIED, axis=-1) & complete


def line_rule(flight_mode: str):
    """The map test a candidate's line of flight must pass under `safety.flight`
    (jaxmripp.spec.flight): known_free, or for truncate / optimistic not_mapped_occupied."""
    return known_free if flight_mode == "known_free" else not_mapped_occupied


def fly_until(start: jnp.ndarray, end: jnp.ndarray, blocking, size: int, max_length: float):
    """Flies start -> end until the first traversed voxel for which `blocking` ((V, 3)
    voxels -> (V,) bool) is True.

    Returns (stop (3,), hit () bool, hit_entry () float32, voxel (3,) int32): with a hit, the
    robot stops midway through the last piece of the segment before the blocking voxel, so
    the stop lies inside a voxel the flight entered before (the start at the latest).
    """
    voxels, entry, complete = traverse(start, end, size, max_length)
    blocked = blocking(voxels)
    # An incomplete list (a segment beyond max_length) is blocked after its last step.
    unchecked = jnp.where(complete, jnp.inf, jnp.max(entry))
    hit_entry = jnp.minimum(jnp.min(jnp.where(blocked, entry, jnp.inf)), unchecked)
    hit = jnp.isfinite(hit_entry)
    previous = jnp.max(jnp.where(entry < hit_entry, entry, 0.0))
    t_stop = jnp.where(hit, 0.5 * (previous + hit_entry), 1.0)
    stop = jnp.where(hit, start + t_stop * (end - start), end)
    return stop, hit, hit_entry, voxels[jnp.argmin(jnp.where(blocked, entry, jnp.inf))]


def pose(position: jnp.ndarray, heading: jnp.ndarray) -> jnp.ndarray:
    """(..., 3) positions and (...,) heading indices -> (..., 4) poses (x, y, z, angle)."""
    angle = jnp.asarray(HEADING_ANGLES)[heading]
    return jnp.concatenate([position, angle[..., None]], axis=-1)
