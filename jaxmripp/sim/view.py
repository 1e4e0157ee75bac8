"""The JAX implementation of `jaxmripp.spec.view`: the view gain of candidate poses on a
robot's map, with facade marked by its building tops (`jaxmripp.sim.tops`), and the
distance to the robots heard.

Per robot and step the gain costs K * 4 * R * S lookups (K candidate positions, 4
headings, R rays, S samples) in the map with facade marked, at static offsets from the
candidate's voxel; the four headings of a position share its voxel. The clear-line test
runs over the S distances as S whole-array steps instead of a scan over a trailing axis.
The env scores a whole batch at once (`team_view_gain`): only candidates away from their
robot's voxel are computed, listed across the batch.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.config import SensorConfig
from jaxmripp.sim import geometry, maps
from jaxmripp.sim.geometry import FREE, OCCUPIED, UNKNOWN
from jaxmripp.sim.geometry import take_flat
from jaxmripp.sim.tops import facade_tops
from jaxmripp.spec import belief as belief_spec
from jaxmripp.spec import vectors
from jaxmripp.spec import view as spec


def samples_per_pose(sensor: SensorConfig, size: int) -> int:
    """R * S: the gain samples of one pose."""
    return spec.RAYS_PER_SIDE**2 * spec.samples_per_ray(sensor.range, size)


FACADE = 3  # the gain's own code for an UNKNOWN voxel that is facade (jaxmripp.spec.view)


def _marked_code(code: jax.Array, near: jax.Array, z: jax.Array,
                 sensor: SensorConfig) -> jax.Array:
    """Codes as the gain reads them, elementwise: FACADE for unknown facade voxels (at
    height z, under their column's facade top `near`, `tops.facade_tops`) and, without
    occlusion, known buildings marked FREE (then only leaving the grid, coded OCCUPIED by
    `_codes`, stops a ray)."""
    known = code if sensor.gain_occlusion else jnp.where(code == OCCUPIED, jnp.int8(FREE), code)
    return jnp.where((code == UNKNOWN) & (near > 0) & (z <= near), jnp.int8(FACADE), known)


def _marked_map(occupancy: jax.Array, near: jax.Array, sensor: SensorConfig,
                size: int) -> jax.Array:
    """One robot's map (G, G, G) as the gain reads it (`_marked_code`), flat (G**3,) int8.
    XLA fuses it into the reads of `_codes`: each sample reads its voxel's code and its
    column's facade top."""
    z = jnp.arange(size, dtype=jnp.int8)[None, None, :]
    return _marked_code(occupancy, near[:, :, None], z, sensor).reshape(-1)


def _map_reader(marked: jax.Array):
    """The `_codes` reader of one marked map, flat (G**3,)."""
    return lambda flat, x, y, z: take_flat(marked, flat)


def _sample_major(sensor: SensorConfig, size: int) -> tuple[np.ndarray, np.ndarray]:
    """`spec.gain_table` with the sample axis before the rays: offsets (4, S, R, 3) and
    weights (S,), so that the clear-line test steps over leading sample slices."""
    offsets, weights = spec.gain_table(sensor.fov_deg, sensor.range, size)
    return np.moveaxis(offsets, 2, 1), weights


def _total_weight(sensor: SensorConfig, size: int) -> int:
    """The largest possible gain sum: every sample of every ray of a heading."""
    _, weights = _sample_major(sensor, size)
    return spec.RAYS_PER_SIDE**2 * int(weights.sum())


def _codes(read, camera: jax.Array, offsets: jax.Array, size: int, rated: bool = False):
    """Camera voxels (..., 3) plus voxel offsets (..., 3) (broadcast) -> the samples' flat
    voxel indices and marked codes, read by `read(flat, x, y, z)` at the clipped voxels,
    OCCUPIED outside the grid. A `rated` reader returns (code, quantised facade rate,
    `jaxmripp.spec.belief`), and so does this, with rate 0 outside the grid."""
    x, y, z = (camera[..., a] + offsets[..., a] for a in range(3))
    inside = (x >= 0) & (x < size) & (y >= 0) & (y < size) & (z >= 0) & (z < size)
    x, y, z = (jnp.clip(v, 0, size - 1) for v in (x, y, z))
    flat = (x * size + y) * size + z
    if not rated:
        return flat, jnp.where(inside, read(flat, x, y, z), jnp.int8(OCCUPIED))
    code, rate = read(flat, x, y, z)
    return flat, jnp.where(inside, code, jnp.int8(OCCUPIED)), jnp.where(inside, rate, 0)


def _gain_sums(marked: jax.Array, camera: jax.Array, sensor: SensorConfig,
               size: int) -> tuple[jax.Array, ...]:
    """One robot's marked map, camera voxels (K, 3) -> the integer sums (unknown, facade),
    each (K, 4) int32, of the gain samples' weights."""
    return _heading_sums(_ray_sums(_map_reader(marked), camera, sensor, size), sensor, size)


def _column_table(near: jax.Array, rates: jax.Array) -> jax.Array:
    """Facade tops and quantised facade rates (..., G, G) -> one int32 per column, the top
    in the low byte and the rate above it: a rated sample reads both with one gather."""
    return near.astype(jnp.int32) | (rates << 8)


def _rated_sums(occupancy: jax.Array, table: jax.Array, camera: jax.Array,
                sensor: SensorConfig, size: int) -> tuple[jax.Array, ...]:
    """`_gain_sums` of one robot's map (G, G, G) with its column table (G, G)
    (`_column_table`), then its rate-weighted facade sums (K, 4)."""
    codes, columns = occupancy.reshape(-1), table.reshape(-1)

    def read(flat, x, y, z):
        column = take_flat(columns, x * size + y)
        return _marked_code(take_flat(codes, flat), column & 0xFF, z, sensor), column >> 8

    return _heading_sums(_ray_sums(read, camera, sensor, size, rated=True), sensor, size)


def _packed(sensor: SensorConfig, size: int) -> bool:
    """Whether `_ray_sums` packs the unknown and facade sums into one int32."""
    return _total_weight(sensor, size) < 1 << 15


def _ray_sums(read, camera: jax.Array, sensor: SensorConfig, size: int,
              rated: bool = False) -> tuple[jax.Array, ...]:
    """`_gain_sums` per ray, (K, 4 * R) int32 each, with codes from `read` (see `_codes`;
    it reads samples (K, 4 * R)), in the layout `_heading_sums` reads: (packed,) while
    both totals fit 15 bits (`_packed`), else (unknown, facade); with a `rated` reader
    (see `_codes`) then the rate-weighted facade sums.

    Integer sums are exact in any order. While both totals fit 15 bits (ranges up to about
    75 voxels) they share one int32, unknown weight in the low 16 bits and facade weight
    above, so each sample costs one accumulation instead of two."""
    offsets, weights = _sample_major(sensor, size)
    rays = spec.RAYS_PER_SIDE**2
    # Samples (K, 4 * R) at one distance at a time, their voxels computed where they are
    # read: XLA then fuses the whole sum into one pass, where (S, K * 4 * R) coordinate
    # arrays would be written to memory and read back.
    per_distance = np.moveaxis(offsets, 1, 0).reshape(len(weights), 1, -1, 3)
    camera = camera[:, None, :]
    packed = _packed(sensor, size)
    unknown_sum = jnp.zeros((camera.shape[0], 4 * rays), jnp.int32)
    facade_sum = jnp.zeros_like(unknown_sum)
    windows_sum = jnp.zeros_like(unknown_sum)
    if rated:
        _check_rate_sums(sensor, size)
    clear = jnp.ones(unknown_sum.shape, bool)
    for s, w in enumerate(weights.astype(int)):
        code, *rate = _codes(read, camera, per_distance[s], size, rated)[1:]
        unknown = clear & ((code == UNKNOWN) | (code == FACADE))
        facade = clear & (code == FACADE)
        if rated:
            windows_sum = windows_sum + jnp.where(facade, jnp.int32(w) * rate[0], 0)
        if packed:
            unknown_sum = unknown_sum + jnp.where(unknown, jnp.int32(w), 0) \
                + jnp.where(facade, jnp.int32(w << 16), 0)
        else:
            unknown_sum = unknown_sum + jnp.where(unknown, jnp.int32(w), 0)
            facade_sum = facade_sum + jnp.where(facade, jnp.int32(w), 0)
        clear = clear & (code != OCCUPIED)
    sums = (unknown_sum,) if packed else (unknown_sum, facade_sum)
    return sums + ((windows_sum,) if rated else ())


def _check_rate_sums(sensor: SensorConfig, size: int) -> None:
    """The rate-weighted sums must fit int32."""
    largest = _total_weight(sensor, size) * belief_spec.RATE_CAP * belief_spec.RATE_SCALE
    if largest >= 2**31:
        raise ValueError(f"view_windows: sensor.range {sensor.range} at G = {size} gives "
                         f"sums up to {largest}; allowed: below 2^31 (a shorter range)")


def _heading_sums(ray_sums: tuple[jax.Array, ...], sensor: SensorConfig,
                  size: int) -> tuple[jax.Array, ...]:
    """`_ray_sums` -> the sums (unknown, facade[, windows]) per heading, (K, 4) each."""
    rays = spec.RAYS_PER_SIDE**2
    sums = tuple(x.reshape(x.shape[0], 4, rays).sum(-1) for x in ray_sums)
    if _packed(sensor, size):
        return (sums[0] & 0xFFFF, sums[0] >> 16) + sums[1:]
    return sums


def _scaled(sums: tuple[jax.Array, ...], sensor: SensorConfig,
            size: int) -> tuple[jax.Array, ...]:
    """Integer weight sums -> the gains, fractions of the largest possible sum (a third,
    rate-weighted sum also divided by RATE_SCALE)."""
    total = _total_weight(sensor, size)
    scales = [np.float32(1) / np.float32(total)] * 2 \
        + [np.float32(1) / np.float32(total * belief_spec.RATE_SCALE)]
    return tuple(x.astype(jnp.float32) * scale for x, scale in zip(sums, scales))


def view_gain(occupancy: jax.Array, top: jax.Array, position: jax.Array,
              sensor: SensorConfig, size: int,
              rates: jax.Array | None = None) -> tuple[jax.Array, ...]:
    """One robot's map (G, G, G) int8 and building tops (G, G) int8, positions (K, 3) ->
    (view_unknown, view_facade), each (K, 4) float32 per position and heading; with the
    robot's quantised facade rates (G, G) int32 (`jaxmripp.sim.belief.facade_rates`) also
    view_windows (`jaxmripp.spec.belief`), (K, 4)."""
    near = facade_tops(top, sensor)
    camera = geometry.voxel_of(position, size)
    if rates is None:
        sums = _gain_sums(_marked_map(occupancy, near, sensor, size), camera, sensor, size)
    else:
        sums = _rated_sums(occupancy, _column_table(near, rates), camera, sensor, size)
    return _scaled(sums, sensor, size)


def team_view_gain(team_map: jax.Array, top: jax.Array, position: jax.Array,
                   origin: jax.Array, sensor: SensorConfig, size: int,
                   rates: jax.Array | None = None) -> tuple[jax.Array, ...]:
    """`view_gain` for a team: its team map (W, G, G, G) (`sim.maps`), tops (N, G, G),
    positions (N, K, 3), each robot's own position (N, 3) and optionally its facade rates
    (N, G, G) int32 -> (N, K, 4) each, equal to `view_gain` on each robot's map.

    The gain depends on the camera voxel only, and the positions that share the robot's
    voxel (padding candidates sit at the robot) take its gain, computed once. Under `vmap`
    the batch folds into the robots (`_team_gains`), so the positions that need their own
    gain are gathered across the whole batch and computed in chunks, as many as there are:
    the work follows the candidates there are rather than the slots.
    """
    extra = () if rates is None else (rates,)
    sums = _team_gains(sensor, size, top.shape[0], bool(extra))(team_map, top, position,
                                                                 origin, *extra)
    return _scaled(sums, sensor, size)


_CHUNKS = 32  # the needed positions are computed in chunks of 1 / _CHUNKS of the slots
_FLAT_LIMIT = 2**31  # flat indices into all maps at once must stay below this (int32)


def _listed_sums(team: jax.Array, n_robots: int, near: jax.Array, camera: jax.Array,
                 needed: jax.Array, sensor: SensorConfig, size: int, rated: bool = False):
    """The gain sums of the needed entries (P,) in their order, each (P, 4) int32 (rows
    past their count are 0): computed chunk by chunk, only as many chunks as are needed.

    `team` are E team maps (E, W, G, G, G) and `near` the facade tops (E * N, G, G) of
    their robots (or, rated, their column tables, `_column_table`); entry p belongs to
    robot p // (K + 1) of that folded order. A sample
    reads its map byte and its column's facade top and decodes them for its robot, so
    no robot's map is ever written out. The loop keeps the sums per ray and adds up the
    rays after it: each chunk is then one elementwise pass, which XLA:CPU runs faster than
    a reduction over the short ray axis."""
    chunk = -(-needed.shape[0] // _CHUNKS)
    (listed,) = jnp.nonzero(needed, size=chunk * _CHUNKS, fill_value=0)
    count = jnp.sum(needed, dtype=jnp.int32)
    per_robot = needed.shape[0] // near.shape[0]
    cells = size**3
    # The maps' words side by side: word w of environment e's map at w * E * G**3 + e * G**3.
    words = jnp.swapaxes(team.reshape(-1, team.shape[-4], cells), 0, 1).reshape(
        team.shape[-4], -1)
    near = near.reshape(-1)

    def one_chunk(i, sums):
        at = jax.lax.dynamic_slice_in_dim(listed, i * chunk, chunk)
        robot = (at // per_robot)[:, None]

        def read(flat, x, y, z):
            code = maps.codes_at(words, robot % n_robots, (robot // n_robots) * cells + flat)
            column = take_flat(near, (robot * size + x) * size + y)
            if not rated:
                return _marked_code(code, column, z, sensor)
            return _marked_code(code, column & 0xFF, z, sensor), column >> 8

        part = _ray_sums(read, camera[at], sensor, size, rated)
        return tuple(jax.lax.dynamic_update_slice_in_dim(s, p, i * chunk, 0)
                     for s, p in zip(sums, part))

    def zero(flat, *_):
        code = jnp.zeros(flat.shape, jnp.int8)
        return (code, jnp.zeros(flat.shape, jnp.int32)) if rated else code

    shapes = jax.eval_shape(lambda c: _ray_sums(zero, c, sensor, size, rated), camera[:chunk])
    empty = tuple(jnp.zeros((chunk * _CHUNKS, *x.shape[1:]), x.dtype) for x in shapes)
    sums = jax.lax.fori_loop(0, (count + chunk - 1) // chunk, one_chunk, empty)
    return _heading_sums(sums, sensor, size)


@functools.lru_cache(maxsize=None)
def _team_gains(sensor: SensorConfig, size: int, n_robots: int, rated: bool = False):
    """The integer sums of `team_view_gain` as a function of arrays only (team, top,
    position, origin, and with `rated` the facade rates), batched by folding (a
    custom_vmap needs its static arguments closed over)."""

    def sums_of(team, top, position, origin, rates=None):
        robots, slots = position.shape[:2]
        near = jax.vmap(facade_tops, in_axes=(0, None))(top, sensor)
        if rates is not None:
            near = _column_table(near, rates)
        if robots * size**3 >= _FLAT_LIMIT:  # robot by robot, every slot
            robot_maps = maps.robot_maps(team, n_robots).reshape(robots, size, size, size)
            camera = geometry.voxel_of(position, size)
            if rates is not None:
                return jax.vmap(lambda m, t, c: _rated_sums(m, t, c, sensor, size))(
                    robot_maps, near, camera)
            marked = jax.vmap(_marked_map, in_axes=(0, 0, None, None))(robot_maps, near,
                                                                       sensor, size)
            return jax.vmap(lambda m, c: _gain_sums(m, c, sensor, size))(marked, camera)
        # Each robot's slots, then its own voxel; a slot needs its own gain unless it is in
        # that voxel.
        own = geometry.voxel_of(origin, size)[:, None, :]
        camera = jnp.concatenate([geometry.voxel_of(position, size), own], axis=1)
        needed = jnp.concatenate([jnp.any(camera[:, :slots] != own, axis=-1),
                                  jnp.ones((robots, 1), bool)], axis=1)
        sums = _listed_sums(team, n_robots, near, camera.reshape(-1, 3), needed.reshape(-1),
                            sensor, size, rates is not None)
        # Where each slot's sums were listed: at its own rank, or at its robot's voxel's.
        rank = (jnp.cumsum(needed.reshape(-1)) - 1).reshape(robots, slots + 1)
        source = jnp.where(needed, rank, rank[:, -1:])[:, :slots]
        return tuple(s[source] for s in sums)

    if rated:
        gains = jax.custom_batching.custom_vmap(
            lambda team, top, position, origin, rates: sums_of(team, top, position, origin,
                                                               rates))
    else:
        gains = jax.custom_batching.custom_vmap(
            lambda team, top, position, origin: sums_of(team, top, position, origin))

    def gains_vmap(axis_size, in_batched, *args):
        # An argument without the axis is broadcast: for maps that is a copy per entry,
        # so the env vmaps maps and candidates together. The robots fold into one axis;
        # the team maps keep theirs, N robots to a map.
        args = [x if b else jnp.broadcast_to(x, (axis_size, *x.shape))
                for x, b in zip(args, in_batched)]
        robots = args[2].shape[1]
        folded = [x.reshape(axis_size * robots, *x.shape[2:]) for x in args[1:]]
        sums = gains(args[0], *folded)
        return tuple(s.reshape(axis_size, robots, *s.shape[1:]) for s in sums), \
            (True,) * len(sums)

    gains.def_vmap(gains_vmap)
    return gains


def unknown_in_view(occupancy: jax.Array, top: jax.Array, position: jax.Array,
                    heading: jax.Array, sensor: SensorConfig, size: int) -> jax.Array:
    """The flat indices of the unknown samples of one pose ((3,), () int32) -> (R * S,)
    int32, G**3 for the other samples: the part of the map that pose would reveal."""
    offsets, _ = _sample_major(sensor, size)
    camera = geometry.voxel_of(position, size)
    marked = _marked_map(occupancy, facade_tops(top, sensor), sensor, size)
    flat, code = _codes(_map_reader(marked), camera, jnp.asarray(offsets)[heading],
                        size)  # (S, R)
    blocked = jnp.cumsum(code == OCCUPIED, axis=0) - (code == OCCUPIED) > 0
    unknown = ~blocked & ((code == UNKNOWN) | (code == FACADE))
    return jnp.where(unknown, flat, size**3).reshape(-1)


def per_cost(gain: jax.Array, cost: jax.Array, shell_outer: float) -> jax.Array:
    """gain * (shell[1] / max(cost, COST_FLOOR)), elementwise."""
    return gain * (jnp.float32(shell_outer) / jnp.maximum(cost, jnp.float32(spec.COST_FLOOR)))


def peer_distance(position: jax.Array, others: jax.Array, heard: jax.Array,
                  shell_outer: float) -> jax.Array:
    """Candidate positions (L, 3), all robots' positions (N, 3), heard (N,) bool -> (L,)
    min(PEER_CAP, distance to the nearest robot heard / shell[1])."""
    gap = vectors.components(position[:, None, :] - others[None, :, :])
    distance = jnp.sqrt(vectors.dot(gap, gap, jnp)) * (np.float32(1) / np.float32(shell_outer))
    distance = jnp.where(heard[None, :], distance, jnp.float32(spec.PEER_CAP))
    return jnp.minimum(jnp.min(distance, axis=-1), jnp.float32(spec.PEER_CAP))
