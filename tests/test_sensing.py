"""Sensing: the ray caster against a brute-force line-of-sight check, hand-built scenes
where the answer is known, occupancy-map invariants, the reference frustum, jit / vmap."""

import functools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import geometry, sensing, tops, world
from jaxmripp.config import SensorConfig, WorldConfig


def update_occupancy(occupancy, result: sensing.CastResult):
    """A robot's (G, G, G) int8 map with the observed voxels set to their true codes: the
    reference the team map's bits (jaxmripp.sim.maps) must read as."""
    size = occupancy.shape[0]
    chex.assert_shape(occupancy, (size, size, size))
    return sensing.scatter_set(occupancy.reshape(-1), result.voxels,
                               result.values).reshape(occupancy.shape)


def empty_occupancy(size: int):
    """(G, G, G) int8 map with every voxel UNKNOWN."""
    return jnp.full((size, size, size), geometry.UNKNOWN, jnp.int8)


_cast = jax.jit(sensing.cast, static_argnums=(3, 4))
_generate = jax.jit(world.generate, static_argnums=1)
_FORWARD = geometry.HEADING_VECTORS.astype(int)
_RIGHT = np.stack([_FORWARD[:, 1], -_FORWARD[:, 0], 0 * _FORWARD[:, 0]], -1)

G = 50
SENSOR = SensorConfig()
REACH = SENSOR.range * G
HALF_FOV = math.radians(SENSOR.fov_deg / 2)


@functools.lru_cache(maxsize=None)
def random_world(seed: int, **overrides) -> world.World:
    return _generate(jax.random.PRNGKey(seed), WorldConfig(layout="random", **overrides))


def free_poses(w: world.World, count: int, seed: int, size: int = G):
    """Random positions in free space (z in the lower 60%) with random headings."""
    rng = np.random.default_rng(seed)
    height = np.asarray(w.height)
    poses = []
    while len(poses) < count:
        p = rng.uniform([0, 0, 0], [1, 1, 0.6])
        v = np.floor(p * size).astype(int)
        if v[2] >= height[v[0], v[1]]:
            poses.append((p.astype(np.float32), int(rng.integers(4))))
    return poses


def scene(size: int, columns: dict, windows: list, capacity: int = 8) -> world.World:
    """A hand-built world: {(x, y): height} buildings and a list of window voxels."""
    height = np.zeros((size, size), np.int32)
    for (x, y), h in columns.items():
        height[x, y] = h
    voxel = np.zeros((capacity, 3), np.int32)
    voxel[: len(windows)] = windows
    return world.World.build(jnp.asarray(height), jnp.asarray(voxel),
                             jnp.arange(capacity) < len(windows))


def centre(voxel, size):
    return (np.asarray(voxel, np.float32) + 0.5) / size


# ---------------------------------------------------------------------------------------
# Brute-force line of sight in NumPy


def line_clear(solid: np.ndarray, start: np.ndarray, end: np.ndarray, target) -> bool:
    """Steps 0.05 voxel from start to end; clear iff every voxel passed is free (or target)."""
    steps = max(2, int(np.ceil(np.linalg.norm(end - start) / 0.05)))
    t = (np.arange(steps) + 0.5) / steps
    v = np.floor(start + t[:, None] * (end - start)).astype(int)
    inside = np.all((v >= 0) & (v < solid.shape[0]), axis=1)
    v = v[inside]
    hit = solid[v[:, 0], v[:, 1], v[:, 2]] & ~np.all(v == target, axis=1)
    return not hit.any()


def los_visible(solid, camera, target) -> bool:
    """Visible iff the line to the voxel centre, or to a face centre turned to the camera,
    is clear."""
    c = np.asarray(target) + 0.5
    points = [c]
    for axis in range(3):
        for sign in (-1, 1):
            face = c.copy()
            face[axis] += 0.5 * sign
            if (camera[axis] - face[axis]) * sign > 0:
                points.append(face)
    return any(line_clear(solid, camera, q, target) for q in points)


def in_view(camera, heading, target, margin_deg=3.0, margin_range=1.0):
    rel = np.asarray(target) + 0.5 - camera
    a, b, c = rel[:2] @ _FORWARD[heading, :2], rel[:2] @ _RIGHT[heading, :2], rel[2]
    limit = math.tan(HALF_FOV - math.radians(margin_deg))
    return a > 0 and abs(b) <= a * limit and abs(c) <= a * limit and \
        np.linalg.norm(rel) <= REACH - margin_range


def test_agrees_with_brute_force_line_of_sight():
    agree = total = visible = 0
    for seed in range(3):
        w = random_world(seed)
        solid = np.asarray(world.truth_occupancy(w, G)) == geometry.OCCUPIED
        windows = np.asarray(w.target_voxel)[np.asarray(w.target_valid)]
        for position, heading in free_poses(w, 50, seed):
            seen = np.asarray(_cast(w, jnp.asarray(position), jnp.int32(heading), SENSOR, G).seen)
            camera = np.floor(position * G) + 0.5  # the sensor sits at its voxel's centre
            for t, v in enumerate(windows):
                if in_view(camera, heading, v):
                    truth = los_visible(solid, camera, v)
                    agree += truth == seen[t]
                    visible += truth
                    total += 1
    assert total > 200 and 0.2 < visible / total < 0.9, (total, visible)  # a real test
    assert agree / total >= 0.95, f"{agree}/{total} agree"


# ---------------------------------------------------------------------------------------
# Hand-built scenes (G = 20, range 10 voxels), camera at the centre of voxel (2, 10, 5)

S = 20
NEAR = SensorConfig(range=0.5)
CAMERA = (2, 10, 5)


def cast_scene(w, heading=0, camera=CAMERA):
    return _cast(w, jnp.asarray(centre(camera, S)), jnp.int32(heading), NEAR, S)


def observed_codes(result, size=S) -> np.ndarray:
    occupancy = update_occupancy(empty_occupancy(size), result)
    return np.asarray(occupancy)


def test_wall_hides_window_and_voxels_behind_it():
    wall = {(8, y): 12 for y in range(6, 15)}
    w = scene(S, {**wall, (12, 10): 10}, [(12, 10, 5), (8, 10, 5)])
    result = cast_scene(w)
    np.testing.assert_array_equal(np.asarray(result.seen)[:2], [False, True])
    codes = observed_codes(result)
    assert codes[CAMERA] == geometry.FREE  # the camera's own voxel is always observed
    assert codes[5, 10, 5] == geometry.FREE
    assert codes[8, 10, 5] == geometry.OCCUPIED
    assert codes[9, 10, 5] == geometry.UNKNOWN  # free, but right behind the wall
    assert codes[10, 10, 5] == geometry.UNKNOWN
    assert codes[12, 10, 5] == geometry.UNKNOWN
    assert int(sensing.utility(result)) == 1


@pytest.mark.parametrize("fraction, expected", [(0.8, True), (1.2, False)])
def test_range_straight_ahead(fraction, expected):
    x = CAMERA[0] + round(fraction * NEAR.range * S)
    w = scene(S, {(x, 10): 8}, [(x, 10, 5)])
    assert bool(cast_scene(w).seen[0]) is expected


def test_field_of_view():
    # Azimuths: atan(6 / 4) = 56.3 and atan(5 / 7) = 35.5 degrees; elevation atan(6 / 4).
    outside, inside, above = (6, 16, 5), (9, 15, 5), (6, 10, 11)
    w = scene(S, {(6, 16): 8, (9, 15): 8}, [outside, inside])
    np.testing.assert_array_equal(np.asarray(cast_scene(w).seen)[:2], [False, True])
    w = scene(S, {(6, 10): 12}, [above])
    assert not bool(cast_scene(w).seen[0])


def test_facing_away_sees_nothing():
    wall = {(8, y): 12 for y in range(6, 15)}
    w = scene(S, {**wall, (12, 10): 10}, [(12, 10, 5), (8, 10, 5), (8, 9, 4)])
    camera = (6, 10, 5)
    assert int(sensing.utility(cast_scene(w, heading=0, camera=camera))) == 2
    result = cast_scene(w, heading=2, camera=camera)  # facing -x
    assert not np.asarray(result.seen).any()
    observed = np.asarray(result.voxels)
    own = (camera[0] * S + camera[1]) * S + camera[2]
    observed = observed[(observed < S ** 3) & (observed != own)]  # its own voxel: always
    assert len(observed) > 0 and np.all(observed // (S * S) < camera[0])
    # In a random city only windows on the camera's side of its voxel are ever seen.
    w = random_world(0)
    for heading in range(4):
        result = _cast(w, jnp.asarray(centre((25, 25, 20), G)), jnp.int32(heading), SENSOR, G)
        ahead = (np.asarray(w.target_voxel) - 25) @ _FORWARD[heading]
        assert np.all(ahead[np.asarray(result.seen)] >= 1)


# ---------------------------------------------------------------------------------------
# Occupancy maps


def test_maps_match_truth_and_occupied_never_turns_free():
    w = random_world(1)
    truth = np.asarray(world.truth_occupancy(w, G))
    update = jax.jit(update_occupancy, donate_argnums=0)
    occupancy = empty_occupancy(G)
    before = np.asarray(occupancy)
    for position, heading in free_poses(w, 12, seed=5):
        result = _cast(w, jnp.asarray(position), jnp.int32(heading), SENSOR, G)
        voxels, values = np.asarray(result.voxels), np.asarray(result.values)
        keep = voxels < G ** 3  # may be empty, e.g. facing the border from next to it
        np.testing.assert_array_equal(values[keep], truth.reshape(-1)[voxels[keep]])
        occupancy = update(occupancy, result)
        after = np.asarray(occupancy)
        known = after != geometry.UNKNOWN
        np.testing.assert_array_equal(after[known], truth[known])
        assert np.all(after[before == geometry.OCCUPIED] == geometry.OCCUPIED)
        assert np.all(known[before != geometry.UNKNOWN])
        before = after
    assert (before == geometry.OCCUPIED).sum() > 0 and (before == geometry.FREE).sum() > 1000


@pytest.mark.parametrize("model", ["raycast", "frustum"])
def test_a_cast_raises_each_column_to_its_highest_voxel_observed_occupied(model):
    w = random_world(4)
    sensor = SensorConfig(model=model)
    raised = 0
    for position, heading in free_poses(w, 12, seed=7):
        result = _cast(w, jnp.asarray(position), jnp.int32(heading), sensor, G)
        voxels, values = np.asarray(result.voxels), np.asarray(result.values)
        expected = np.zeros((G, G), int)
        for v in voxels[(voxels < G**3) & (values == geometry.OCCUPIED)]:
            x, y, z = np.unravel_index(v, (G, G, G))
            expected[x, y] = max(expected[x, y], z + 1)
        top = tops.raise_tops_from_cast(jnp.zeros((G, G), jnp.int8), result)
        np.testing.assert_array_equal(np.asarray(top), expected)
        raised += expected.max() > 0
    assert raised >= 3


@pytest.mark.parametrize("size", [75, 125])
def test_larger_worlds(size):
    w = random_world(size, size=size)
    truth = np.asarray(world.truth_occupancy(w, size)).reshape(-1)
    cast = jax.jit(jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None)), static_argnums=(3, 4))
    poses = free_poses(w, 8, seed=size, size=size)
    position = jnp.asarray(np.stack([p for p, _ in poses]))
    result = cast(w, position, jnp.asarray([h for _, h in poses]), SENSOR, size)
    voxels, values = np.asarray(result.voxels), np.asarray(result.values)
    assert voxels.shape[1] == sensing.view_size(SENSOR, size)
    keep = voxels < size**3
    assert keep.sum() > 0
    np.testing.assert_array_equal(values[keep], truth[voxels[keep]])
    seen = np.asarray(result.seen)
    assert not seen[:, ~np.asarray(w.target_valid)].any()


# ---------------------------------------------------------------------------------------
# The reference frustum


def reference_frustum(camera, heading, depth, size):
    """NumPy: the set of flat indices the reference's sensor observes."""
    grid = np.stack(np.meshgrid(*[np.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3)
    o = grid - np.asarray(camera)
    f, b, c = o @ _FORWARD[heading], o @ _RIGHT[heading], o[:, 2]
    half = np.minimum(depth - 1, np.floor(1.5 * f) + 1)
    keep = (f >= 0) & (f <= depth - 1) & (np.abs(b) <= half) & (np.abs(c) <= half)
    return set(np.flatnonzero(keep))


def test_frustum_matches_reference_rule():
    w = random_world(2, target_placement="footprint")
    sensor = SensorConfig(model="frustum")
    depth = round(sensor.range * G)
    truth = np.asarray(world.truth_occupancy(w, G)).reshape(-1)
    windows = np.asarray(w.target_voxel)
    flat_windows = windows @ np.array([G * G, G, 1])
    valid = np.asarray(w.target_valid)
    for position, heading in free_poses(w, 6, seed=3) + [(np.zeros(3, np.float32), 1)]:
        result = _cast(w, jnp.asarray(position), jnp.int32(heading), sensor, G)
        camera = np.floor(position * G).astype(int)
        expected = reference_frustum(camera, heading, depth, G)
        voxels, values = np.asarray(result.voxels), np.asarray(result.values)
        keep = voxels < G ** 3
        assert set(voxels[keep]) == expected and keep.sum() == len(expected)
        np.testing.assert_array_equal(values[keep], truth[voxels[keep]])
        seen = np.array([fw in expected for fw in flat_windows]) & valid
        np.testing.assert_array_equal(np.asarray(result.seen), seen)


# ---------------------------------------------------------------------------------------
# Transformations


@pytest.mark.parametrize("model", ["raycast", "frustum"])
def test_vmap_over_envs_and_robots_matches_single_casts(model):
    sensor = SensorConfig(model=model)
    worlds = jax.tree.map(lambda *x: jnp.stack(x), random_world(0), random_world(1))
    key_p, key_h = jax.random.split(jax.random.PRNGKey(1))
    position = jax.random.uniform(key_p, (2, 3, 3))
    heading = jax.random.randint(key_h, (2, 3), 0, 4)
    per_robot = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))
    batched = jax.jit(jax.vmap(per_robot, in_axes=(0, 0, 0, None, None)), static_argnums=(3, 4))
    result = batched(worlds, position, heading, sensor, G)
    for e in range(2):
        w = jax.tree.map(lambda x: x[e], worlds)
        for r in range(3):
            single = _cast(w, position[e, r], heading[e, r], sensor, G)
            for x, y in zip(jax.tree.leaves(single), jax.tree.leaves(result)):
                np.testing.assert_array_equal(x, y[e, r])
    # The batched update folds all maps into one flat scatter; it must equal per-map ones,
    # also when the maps are shared (unbatched) at the inner level.
    empty = empty_occupancy(G)
    maps = jax.jit(jax.vmap(jax.vmap(update_occupancy)))(
        jnp.broadcast_to(empty, (2, 3, G, G, G)), result)
    shared = jax.jit(jax.vmap(jax.vmap(update_occupancy, in_axes=(None, 0))))(
        jnp.broadcast_to(empty, (2, G, G, G)), result)
    update = jax.jit(update_occupancy)
    for e in range(2):
        for r in range(3):
            single = update(empty, jax.tree.map(lambda x: x[e, r], result))
            np.testing.assert_array_equal(maps[e, r], single)
            np.testing.assert_array_equal(shared[e, r], single)
    assert sensing.utility(result).shape == (2, 3)


def test_cast_traces_once():
    chex.clear_trace_counter()
    traced = jax.jit(chex.assert_max_traces(sensing.cast, n=1), static_argnums=(3, 4))
    w = random_world(0)
    for position, heading in free_poses(w, 4, seed=8):
        traced(w, jnp.asarray(position), jnp.int32(heading), SENSOR, G)
