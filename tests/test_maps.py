"""The team map (jaxmripp.sim.maps) against int8 maps built by hand in NumPy."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import geometry, maps, sensing
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN
from test_sensing import empty_occupancy, update_occupancy

G = 5


def _truth(rng):
    height = rng.integers(0, G + 1, (G, G))
    return height, np.arange(G)[None, None, :] < height[:, :, None]


@pytest.mark.parametrize("n", [1, 3, 7, 8, 9])
def test_words_hold_the_building_bit_and_one_bit_per_robot(n):
    assert maps.words(n) * 8 >= n + 1 > (maps.words(n) - 1) * 8


@pytest.mark.parametrize("n", [3, 9])
def test_an_empty_team_map_knows_nothing_but_holds_the_truth(n):
    height, solid = _truth(np.random.default_rng(0))
    team = maps.empty(jnp.asarray(height, jnp.int8), n)
    chex.assert_shape(team, (maps.words(n), G, G, G))
    assert team.dtype == jnp.uint8
    np.testing.assert_array_equal(maps.buildings(team), solid)
    np.testing.assert_array_equal(maps.robot_maps(team, n), np.full((n, G, G, G), UNKNOWN))


@pytest.mark.parametrize("n", [3, 9])
def test_observed_voxels_take_their_true_codes_for_their_robot_only(n):
    rng = np.random.default_rng(1)
    height, solid = _truth(rng)
    voxels = np.stack([rng.permutation(G**3)[:40] for _ in range(n)])  # distinct per robot
    voxels[:, -3:] = [G**3, G**3 + 7, -1]  # outside the grid: dropped
    team = jax.jit(maps.observe)(maps.empty(jnp.asarray(height, jnp.int8), n),
                                 jnp.asarray(voxels, jnp.int32))
    expected = np.full((n, G**3), UNKNOWN, np.int8)
    for i in range(n):
        seen = voxels[i][(voxels[i] >= 0) & (voxels[i] < G**3)]
        expected[i, seen] = np.where(solid.reshape(-1)[seen], OCCUPIED, FREE)
    np.testing.assert_array_equal(maps.robot_maps(team, n).reshape(n, -1), expected)


def test_observing_under_vmap_equals_observing_each_environment():
    rng = np.random.default_rng(2)
    heights = np.stack([_truth(rng)[0] for _ in range(3)]).astype(np.int8)
    voxels = jnp.asarray(np.stack([[rng.permutation(G**3 + 5)[:30] for _ in range(2)]
                                   for _ in range(3)]), jnp.int32)
    empty = jax.vmap(maps.empty, in_axes=(0, None))(jnp.asarray(heights), 2)
    batched = jax.jit(jax.vmap(maps.observe))(empty, voxels)
    for e in range(3):
        np.testing.assert_array_equal(batched[e], maps.observe(empty[e], voxels[e]))


def _random_team(rng, n):
    """n int8 maps that each know a random part of one random truth, its building voxels
    (G, G, G) bool and their team map."""
    _, solid = _truth(rng)
    known = rng.random((n, G, G, G)) < 0.4
    robot_maps = np.where(known, np.where(solid, OCCUPIED, FREE), UNKNOWN).astype(np.int8)
    return robot_maps, solid, maps.pack(jnp.asarray(robot_maps), jnp.asarray(solid))


@pytest.mark.parametrize("n", [3, 9])
def test_pack_inverts_robot_maps(n):
    robot_maps, solid, team = _random_team(np.random.default_rng(3), n)
    np.testing.assert_array_equal(maps.buildings(team), solid)
    np.testing.assert_array_equal(maps.robot_maps(team, n), robot_maps)


@pytest.mark.parametrize("n", [3, 9])
def test_a_robot_map_reads_as_its_int8_map(n):
    rng = np.random.default_rng(4)
    robot_maps, _, team = _random_team(rng, n)
    flat = jnp.asarray(rng.integers(0, G**3, 50), jnp.int32)
    for robot in (0, n - 1):
        reader = maps.robot_map(team, robot)
        assert isinstance(reader, geometry.CodeReader)
        assert not isinstance(jnp.asarray(robot_maps[robot]), geometry.CodeReader)
        np.testing.assert_array_equal(geometry.read_codes(reader, flat),
                                      geometry.read_codes(jnp.asarray(robot_maps[robot]), flat))
        np.testing.assert_array_equal(geometry.read_codes(reader, flat),
                                      robot_maps[robot].reshape(-1)[np.asarray(flat)])


def test_observe_and_merge_trace_once_and_keep_the_shape():
    n = 3
    team = maps.empty(jnp.zeros((G, G), jnp.int8), n)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(team, voxels, linked):
        return maps.merge(maps.observe(team, voxels), linked)

    linked = jnp.ones((n, n), bool)
    for seed in range(3):
        voxels = jnp.stack([jax.random.permutation(jax.random.PRNGKey(3 * seed + i), G**3)[:10]
                            for i in range(n)])
        team = step(team, voxels, linked)
    chex.assert_shape(team, (1, G, G, G))
    # All hear all: every robot knows what any robot observed.
    robot_maps = np.asarray(maps.robot_maps(team, n))
    assert (robot_maps != UNKNOWN).any()
    np.testing.assert_array_equal(robot_maps[1:], np.broadcast_to(robot_maps[0], (2, G, G, G)))


def test_team_map_updates_match_int8_maps_on_a_cast():
    """A real cast, written as the env writes it and as an int8 map would hold it."""
    from jaxmripp.config import SensorConfig, WorldConfig
    from jaxmripp.sim import world

    size = 20

    @jax.jit  # one compilation rather than hundreds of operations dispatched one by one
    def world_and_casts(key):
        w = world.generate(key, WorldConfig(size=size, layout="random"))
        position = jnp.asarray([[0.5, 0.5, 0.5], [0.2, 0.7, 0.4]], jnp.float32)
        casts = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))(
            w, position, jnp.asarray([0, 3]), SensorConfig(), size)
        int8_maps = jax.vmap(update_occupancy)(
            jnp.broadcast_to(empty_occupancy(size), (2, size, size, size)), casts)
        return w, casts, int8_maps

    w, casts, int8_maps = world_and_casts(jax.random.PRNGKey(4))
    # `observe` needs each robot's in-grid voxels distinct: a cast's are.
    for voxels in np.asarray(casts.voxels):
        inside = voxels[voxels < size**3]
        assert len(np.unique(inside)) == len(inside) > 100
    # Twice, as robots re-observe voxels: set bits stay set, no bit carries into another.
    team = maps.observe(maps.empty(w.height, 2), casts.voxels)
    team = maps.observe(team, casts.voxels)
    np.testing.assert_array_equal(maps.robot_maps(team, 2), int8_maps)
