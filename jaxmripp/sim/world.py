"""City generation: a 2.5D height map of box buildings plus a fixed-capacity window list.

Every building is a vertical box standing on the ground, so the ground truth is a height
map: voxel (x, y, z) is occupied iff z < height[x, y] (axes x, y, z; z up). Windows
(targets) are building voxels, stored in a fixed-capacity list with a validity mask.

Footprints are `footprint` voxels square, or with `footprint_min` > 0 rectangles whose
sides are drawn from [footprint_min, footprint], set in their lot's low corner. Layouts
place footprints on a lattice of lots sized for the largest footprint; each lot is at
least footprint + clearance wide and lots start `clearance` voxels from the low border
and end at the high border, so buildings in distinct lots never overlap and keep
`clearance` free voxels between them and from the border, by construction and with fixed
shapes (no rejection sampling):
- grid: one lot per building, as few rows as possible, each building centred in its lot;
- random: a finer lattice (about `_RANDOM_LOTS_PER_BUILDING` lots per building) from which
  a random subset of lots is drawn, each building jittered uniformly inside its lot.
"""

from __future__ import annotations

import math

import chex
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.sim import geometry
from jaxmripp.config import WorldConfig

_RANDOM_LOTS_PER_BUILDING = 2.0  # more lots -> more irregular layouts, less jitter per lot


FACES = np.array([(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, 1)], np.int32)


@flax.struct.dataclass
class World:
    """Ground truth of one city (G = grid size, T = cfg.target_capacity)."""

    height: jax.Array  # (G, G) int32 building height in voxels per (x, y) column; 0 = none
    target_voxel: jax.Array  # (T, 3) int32 voxel of each window
    target_valid: jax.Array  # (T,) bool; valid windows come first, padding slots are False
    target_open: jax.Array  # (T, 5) bool faces of each window open to the air, in the
    #                         order of FACES (its bottom face rests on the building)

    @classmethod
    def build(cls, height: jax.Array, target_voxel: jax.Array,
              target_valid: jax.Array) -> World:
        """The world with these truths and the faces derived from them (build a changed
        world anew rather than `replace` a truth, so the faces follow)."""
        # A face is open where the voxel beyond it is not a building: out of the grid,
        # above a roof, or beside a shorter column.
        beside = target_voxel[..., None, :] + jnp.asarray(FACES)
        return cls(height=height, target_voxel=target_voxel, target_valid=target_valid,
                   target_open=~_in_building(height, beside))

    @property
    def n_targets(self) -> jax.Array:
        """int32 number of valid windows (batched worlds give one count per world)."""
        return jnp.sum(self.target_valid, axis=-1, dtype=jnp.int32)


# ---------------------------------------------------------------------------------------
# Static layout geometry (NumPy, evaluated once per config at trace time)


def _lot_edges(size: int, clearance: int, lots: int) -> tuple[np.ndarray, np.ndarray]:
    """Lot starts (lots,) and spare width (lots,) beyond footprint + clearance; see module doc."""
    edges = clearance + (np.arange(lots + 1) * (size - clearance)) // lots
    return edges[:-1], np.diff(edges)


def _max_lots(cfg: WorldConfig) -> int:
    return (cfg.size - cfg.clearance) // (cfg.footprint + cfg.clearance)


def _footprint_columns(footprint: int) -> np.ndarray:
    """(F, 2) column offsets of a footprint, F = footprint^2."""
    cells = np.meshgrid(np.arange(footprint), np.arange(footprint), indexing="ij")
    return np.stack(cells, -1).reshape(-1, 2)


def _window_columns(cfg: WorldConfig) -> np.ndarray:
    """(P, 2) footprint-relative columns that may hold windows, per cfg.target_placement:
    the outer ring for facades (every ring voxel faces the clearance gap), else all. With
    varied footprints every column of the largest one (`_window_slots` masks them)."""
    cells = _footprint_columns(cfg.footprint)
    if cfg.target_placement == "facade" and not cfg.footprint_min:
        cells = cells[np.any((cells == 0) | (cells == cfg.footprint - 1), axis=1)]
    return cells


def _window_slots(sides: jax.Array, cfg: WorldConfig) -> jax.Array:
    """(B, P) bool: column p of `_window_columns` lies in building b's footprint of
    `sides` (B, 2), on its outer ring for facades."""
    cells = jnp.asarray(_window_columns(cfg))[None]  # (1, P, 2)
    side = sides[:, None, :]
    inside = jnp.all(cells < side, axis=-1)
    if cfg.target_placement != "facade":
        return inside
    return inside & jnp.any((cells == 0) | (cells == side - 1), axis=-1)


def _fewest_window_columns(cfg: WorldConfig) -> int:
    """Window columns of the smallest footprint a building can have."""
    side = cfg.footprint_min or cfg.footprint
    inner = max(side - 2, 0) ** 2 if cfg.target_placement == "facade" else 0
    return side * side - inner


def _height_bounds(cfg: WorldConfig) -> tuple[int, int]:
    lo, hi = cfg.height_range
    return max(1, math.floor(lo * cfg.size)), max(1, min(cfg.size, math.floor(hi * cfg.size)))


def _check(cfg: WorldConfig) -> None:
    """Raises ValueError for configs whose static shapes cannot hold what is asked for."""
    n, lots = cfg.n_buildings, _max_lots(cfg)
    if lots < 1 or n > lots * lots:
        raise ValueError(f"world: {n} buildings of footprint {cfg.footprint} with clearance "
                         f"{cfg.clearance} do not fit a {cfg.size}^2 ground "
                         f"({max(lots, 0)}^2 lots)")
    if cfg.target_placement == "facade" and cfg.clearance < 1:
        raise ValueError("world: facade windows need world.clearance >= 1 so that every "
                         "perimeter voxel faces free space")
    slots = n * _fewest_window_columns(cfg) * _height_bounds(cfg)[0]
    if cfg.target_capacity > slots:
        raise ValueError(f"world: {cfg.target_capacity} windows requested but the lowest "
                         f"possible city only has {slots} {cfg.target_placement} voxels")


# ---------------------------------------------------------------------------------------
# Generation


def _grid_origins(cfg: WorldConfig) -> np.ndarray:
    """(B, 2) footprint origins on a regular lattice, each centred in its lot."""
    n = cfg.n_buildings
    nx = math.ceil(math.sqrt(n))
    ny = math.ceil(n / nx)
    axes = []
    for lots in (nx, ny):
        start, width = _lot_edges(cfg.size, cfg.clearance, lots)
        spare = width - cfg.footprint - cfg.clearance
        axes.append(start + spare // 2)
    ox, oy = np.meshgrid(axes[0], axes[1], indexing="ij")
    return np.stack([ox.ravel(), oy.ravel()], -1)[:n].astype(np.int32)


def _random_origins(key: chex.PRNGKey, cfg: WorldConfig) -> jax.Array:
    """(B, 2) footprint origins in distinct random lots of a fine lattice, jittered."""
    n = cfg.n_buildings
    lots = min(_max_lots(cfg), math.ceil(math.sqrt(_RANDOM_LOTS_PER_BUILDING * n)))
    start, width = _lot_edges(cfg.size, cfg.clearance, lots)
    spare = jnp.asarray(width - cfg.footprint - cfg.clearance)
    key_lot, key_jitter = jax.random.split(key)
    chosen = jax.random.choice(key_lot, lots * lots, (n,), replace=False)
    lot = jnp.stack([chosen // lots, chosen % lots], -1)  # (B, 2)
    jitter = jax.random.randint(key_jitter, (n, 2), 0, spare[lot] + 1)
    return jnp.asarray(start)[lot] + jitter


def _height_map(origins: jax.Array, heights: jax.Array, cfg: WorldConfig,
                sides: jax.Array | None = None) -> jax.Array:
    offsets = _footprint_columns(cfg.footprint)
    columns = origins[:, None, :] + offsets[None]  # (B, F, 2)
    values = jnp.broadcast_to(heights[:, None], columns.shape[:2])
    if sides is not None:  # columns outside a smaller footprint add nothing
        values = jnp.where(jnp.all(offsets[None] < sides[:, None], axis=-1), values, 0)
    return jnp.zeros((cfg.size, cfg.size), jnp.int32).at[
        columns[..., 0], columns[..., 1]].max(values)


def _windows(key: chex.PRNGKey, origins: jax.Array, heights: jax.Array, cfg: WorldConfig,
             sides: jax.Array | None = None):
    """Draws distinct window voxels among (building, column, z) slots below each roof.

    Each building gets a random weight (exponential, i.e. Dirichlet(1) shares); Gumbel
    top-k over all slots, with per-slot log-weight log(w_b / slots_b), is weighted sampling
    without replacement, so a building's expected share is w_b until it runs out of slots.
    """
    size, capacity = cfg.size, cfg.target_capacity
    columns = jnp.asarray(_window_columns(cfg))  # (P, 2)
    n_cols = columns.shape[0]
    key_weight, key_gumbel, key_count = jax.random.split(key, 3)
    weight = jax.random.exponential(key_weight, heights.shape)
    z = jnp.arange(size)
    below_roof = z[None, :] < heights[:, None]  # (B, G)
    open_column = (jnp.ones((heights.shape[0], n_cols), bool) if sides is None
                   else _window_slots(sides, cfg))  # (B, P) columns that may hold windows
    log_w = jnp.log(weight) - jnp.log(
        (jnp.sum(open_column, axis=1) * heights).astype(jnp.float32))
    logits = jnp.where(below_roof[:, None, :] & open_column[:, :, None],
                       log_w[:, None, None], -jnp.inf).reshape(-1)
    scores = logits + jax.random.gumbel(key_gumbel, logits.shape)
    _, slot = jax.lax.top_k(scores, capacity)  # best first; _check guarantees finite scores
    building, rest = jnp.divmod(slot, n_cols * size)
    column, height = jnp.divmod(rest, size)
    xy = origins[building] + columns[column]
    voxel = jnp.concatenate([xy, height[:, None]], -1).astype(jnp.int32)
    count = jax.random.randint(key_count, (), cfg.target_min, capacity + 1)
    return voxel, jnp.arange(capacity) < count


def generate(key: chex.PRNGKey, cfg: WorldConfig) -> World:
    """Samples one city; jit with cfg static. Deterministic per key."""
    _check(cfg)
    key_layout, key_height, key_window = jax.random.split(key, 3)
    if cfg.layout == "grid":
        origins = jnp.asarray(_grid_origins(cfg))
    else:
        origins = _random_origins(key_layout, cfg)
    lo, hi = cfg.height_range
    u = jax.random.uniform(key_height, (cfg.n_buildings,), minval=lo, maxval=hi)
    heights = jnp.clip(jnp.floor(u * cfg.size).astype(jnp.int32), *_height_bounds(cfg))
    sides = None
    if cfg.footprint_min:  # a key of its own: square-footprint cities stay as they were
        sides = jax.random.randint(jax.random.fold_in(key, 1), (cfg.n_buildings, 2),
                                   cfg.footprint_min, cfg.footprint + 1)
    target_voxel, target_valid = _windows(key_window, origins, heights, cfg, sides)
    return World.build(_height_map(origins, heights, cfg, sides), target_voxel, target_valid)


# ---------------------------------------------------------------------------------------
# Queries


def occupied(world: World, voxel: jax.Array) -> jax.Array:
    """(..., 3) int voxels -> (...,) bool: inside a building. Out-of-grid voxels are free."""
    return _in_building(world.height, voxel)


def _in_building(height: jax.Array, voxel: jax.Array) -> jax.Array:
    size = height.shape[-1]
    x, y, z = (voxel[..., k] for k in range(3))  # per axis: no small trailing reductions
    inside = (x >= 0) & (x < size) & (y >= 0) & (y < size) & (z >= 0) & (z < size)
    return inside & (z < height[jnp.clip(x, 0, size - 1), jnp.clip(y, 0, size - 1)])


def truth_occupancy(world: World, size: int) -> jax.Array:
    """(G, G, G) int8 dense FREE / OCCUPIED grid; for tests and plots, not hot paths."""
    chex.assert_shape(world.height, (size, size))
    solid = jnp.arange(size)[None, None, :] < world.height[:, :, None]
    return jnp.where(solid, geometry.OCCUPIED, geometry.FREE).astype(jnp.int8)
