"""Target belief (jaxmripp.spec.belief): buildings, counts and posterior rates of a robot's
map against a NumPy reference written from the rule's text, the rate-weighted view gain
against a sample-by-sample reference, and the environment's optional belief input."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import deque
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.config import ConfigError, SensorConfig, WorldConfig, from_dict
from jaxmripp.sim import belief, env, maps, sensing, tops, view
from jaxmripp.sim import world as worldmod
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.spec import belief as spec
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN
from jaxmripp.spec.layout import BELIEF_FEATURES, FEATURES, features
from gain_reference import brute_tops, samples_total, visible_samples

WORLD = WorldConfig(size=30, layout="random", buildings=36, targets=(250, 250))
SENSOR = SensorConfig(range=0.3)
gain = jax.jit(view.view_gain, static_argnums=(3, 4))
box_labels = jax.jit(belief.box_labels, static_argnums=(2, 3))


@functools.partial(jax.jit, static_argnums=(4, 5))
def team_rates(world, team_map, top, strength, sensor, true=False):
    """`belief.team_rates` (or `true_rates`) of the fields the belief reads, as the belief
    planners and teachers get them (`belief.rates_for`)."""
    state = SimpleNamespace(world=world, team_map=team_map, building_top=top,
                            position=jnp.zeros((top.shape[0], 3)))
    return belief.rates_for("truth" if true else "belief", strength, sensor, WORLD)(state)


def test_a_rates_source_other_than_belief_or_truth_is_refused():
    with pytest.raises(ValueError, match="allowed: belief, truth"):
        belief.rates_for("oracle", 3.0, SENSOR, WORLD)


# ---------------------------------------------------------------------------------------
# The reference: the rule of jaxmripp.spec.belief, column by column


def reference_labels(top: np.ndarray) -> np.ndarray:
    """8-connected components of the columns with top > 0, labelled by their smallest flat
    index (breadth-first search); G * G elsewhere."""
    size = top.shape[0]
    labels = np.full(top.shape, size * size, np.int64)
    for start in zip(*np.nonzero(top > 0)):
        if labels[start] < size * size:
            continue
        component, queue = [start], deque([start])
        labels[start] = -1
        while queue:
            x, y = queue.popleft()
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    i, j = x + dx, y + dy
                    if 0 <= i < size and 0 <= j < size and top[i, j] > 0 and labels[i, j] != -1:
                        labels[i, j] = -1
                        component.append((i, j))
                        queue.append((i, j))
        smallest = min(x * size + y for x, y in component)
        for cell in component:
            labels[cell] = smallest
    return labels


def reference_rates(grid, top, target_voxel, target_valid, strength, prior, facade_mode):
    """(G, G) int q of one robot's facade rates: counts per building, rho in float32,
    the columns' rates, their quantisation and the facade maximum."""
    size = grid.shape[0]
    labels = reference_labels(top)
    rho = {}
    for label in np.unique(labels[labels < size * size]):
        columns = labels == label
        seen = int((grid[columns] == OCCUPIED).sum())
        found = sum(1 for (x, y, z), valid in zip(target_voxel, target_valid)
                    if valid and labels[x, y] == label and grid[x, y, z] != UNKNOWN)
        k, m = np.float32(strength), np.float32(prior)
        rho[label] = (k + np.float32(found)) / (k + m * np.float32(seen))
    rate = np.zeros((size, size), np.float32)
    for (x, y), label in np.ndenumerate(labels):
        if label < size * size:
            rate[x, y] = rho[label]
    q = np.minimum(np.floor(rate * np.float32(256) + np.float32(0.5)), 64 * 256).astype(int)
    if facade_mode == "column":
        return q
    padded = np.pad(q, 1)
    steps = [(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)]
    if facade_mode == "around":
        steps += [(-1, -1), (-1, 1), (1, -1), (1, 1)]
    return np.max([padded[1 + dx:1 + dx + size, 1 + dy:1 + dy + size] for dx, dy in steps],
                  axis=0)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _maps(key, robots: int, poses: int):
    """A generated city and the team map and tops of robots whose maps were written by
    casts from random poses."""
    key_world, key_pose = jax.random.split(key)
    world = worldmod.generate(key_world, WORLD)
    size = WORLD.size
    position = jax.random.uniform(key_pose, (robots, poses, 3), minval=0.02, maxval=0.98)
    heading = jax.random.randint(jax.random.fold_in(key_pose, 1), (robots, poses), 0, 4)
    casts = jax.vmap(jax.vmap(lambda p, h: sensing.cast(world, p, h, SENSOR, size)))(
        position, heading)
    team = maps.empty(world.height, robots)
    top = jnp.zeros((robots, size, size), jnp.int8)
    for k in range(poses):
        team = maps.observe(team, casts.voxels[:, k])
        top = jax.vmap(tops.raise_tops)(top, casts.voxels[:, k], casts.values[:, k])
    return world, team, top


def _scene(seed: int, robots: int = 2, poses: int = 6):
    """`_maps` with each robot's int8 map and tops, and the state fields the belief reads."""
    world, team, top = _maps(jax.random.PRNGKey(seed), robots, poses)
    state = SimpleNamespace(world=world, team_map=team, building_top=top,
                            position=jnp.zeros((robots, 3)))
    return state, np.asarray(maps.robot_maps(team, robots)), np.asarray(top)


@pytest.fixture(scope="module")
def scenes():
    return [_scene(seed) for seed in range(3)]


def test_the_prior_is_the_generators_windows_per_slot():
    # 25 buildings with 8 ring columns of mean height floor(u 50) for u in [0.2, 0.99],
    # clipped to [10, 49]: 29.25; 250 windows.
    assert spec.mean_height(50, (0.2, 0.99)) == pytest.approx(29.25, abs=0.01)
    assert belief.prior(WorldConfig()) == pytest.approx(250 / (25 * 8 * 29.25), rel=1e-3)
    # Windows inside footprints use every column; rectangles average their rings.
    assert spec.window_columns(3, 0, "footprint") == 9
    assert spec.window_columns(3, 2, "facade") == pytest.approx((4 + 6 + 6 + 8) / 4)


def test_labels_are_the_8_connected_components_of_the_known_columns(scenes):
    for state, _, tops in scenes:
        cells = belief.building_boxes(state.world.height, WORLD)
        for top in tops:
            known = (cells < WORLD.size**2) & (top.reshape(-1)[np.minimum(
                cells, WORLD.size**2 - 1)] > 0)
            labels = box_labels(known, cells, WORLD.footprint, WORLD.size)
            grid = np.full(WORLD.size**2, WORLD.size**2)
            grid[np.asarray(cells).reshape(-1)[np.asarray(known).reshape(-1)]] = np.asarray(
                labels).reshape(-1)[np.asarray(known).reshape(-1)]
            np.testing.assert_array_equal(grid.reshape(top.shape), reference_labels(top))


def test_two_walls_of_one_building_are_two_buildings_until_a_column_joins_them():
    top = np.zeros((10, 10), np.int8)
    top[2, 2:5] = 5  # the x = 2 wall of a 3 x 3 building at (2..4, 2..4)
    top[4, 2:5] = 5  # the x = 4 wall
    height = np.zeros((10, 10), np.int32)
    height[2:5, 2:5] = 5
    world = dataclasses.replace(WORLD, size=10, buildings=1)
    cells = belief.building_boxes(jnp.asarray(height), world)
    labels = lambda t: set(np.asarray(box_labels(  # noqa: E731
        t.reshape(-1)[np.asarray(cells)] > 0, cells, 3, 10)).reshape(-1)) - {100}
    assert labels(top) == {22, 42}
    top[3, 4] = 5  # the middle column of the y = 4 wall
    assert labels(top) == {22}


@pytest.mark.parametrize("strength", [1.0, 3.0])
def test_rates_equal_the_reference_robot_by_robot(scenes, strength):
    sensors = [SENSOR, dataclasses.replace(SENSOR, gain_facade="column"),
               dataclasses.replace(SENSOR, gain_facade="around")]
    for (state, grids, tops), sensor in zip(scenes, sensors * 2):
        rates = np.asarray(team_rates(state.world, state.team_map, state.building_top,
                                      strength, sensor))
        assert rates.max() > 0
        for rate, grid, top in zip(rates, grids, tops):
            want = reference_rates(grid, top, np.asarray(state.world.target_voxel),
                                   np.asarray(state.world.target_valid), strength,
                                   belief.prior(WORLD), sensor.gain_facade)
            # float32 on both sides; a fused multiply-add may move q by one unit.
            assert np.abs(rate - want).max() <= 1
            assert np.mean(rate == want) > 0.99


def test_found_windows_raise_a_buildings_rate_and_bare_facade_lowers_it():
    assert spec.relative_rate(0, 0, 3.0, 0.04) == pytest.approx(1.0)
    assert spec.relative_rate(6, 50, 3.0, 0.04) == pytest.approx(9 / 5)
    assert spec.relative_rate(0, 50, 3.0, 0.04) == pytest.approx(3 / 5)
    assert spec.quantised(np.float32([0.5, 1.0, 1e6])).tolist() == [128, 256, 64 * 256]


def test_true_rates_spread_the_windows_left_over_the_unseen_surface(scenes):
    state, grids, _ = scenes[0]
    rates = np.asarray(team_rates(state.world, state.team_map, state.building_top, 0.0,
                                  dataclasses.replace(SENSOR, gain_facade="column"), True))
    height = np.asarray(state.world.height)
    labels = reference_labels(height)
    voxel, valid = np.asarray(state.world.target_voxel), np.asarray(state.world.target_valid)
    surface = np.asarray(belief.surface(jnp.asarray(height)))
    for rate, grid in zip(rates, grids):
        for label in np.unique(labels[labels < WORLD.size**2])[:8]:
            columns = labels == label
            left = sum(1 for (x, y, z), v in zip(voxel, valid)
                       if v and columns[x, y] and grid[x, y, z] == UNKNOWN)
            unseen = max(surface[columns].sum() - (grid[columns] == OCCUPIED).sum(), 1)
            want = math.floor(256 * left / unseen / belief.prior(WORLD) + 0.5)
            assert np.abs(rate[columns] - min(want, 64 * 256)).max() <= 1


# ---------------------------------------------------------------------------------------
# The rate-weighted gain


def reference_windows(grid, top, q, position, heading, sensor):
    """view_windows of one pose, sample by sample (jaxmripp.spec.belief)."""
    total = sum(int(w) * int(q[x, y])
                for x, y, z, w, near in visible_samples(grid, top, position, heading, sensor)
                if grid[x, y, z] == UNKNOWN and near > 0 and z <= near)
    return total / (samples_total(grid, heading, sensor) * spec.RATE_SCALE)


@pytest.mark.parametrize("seed,sensor", [(0, SENSOR), (1, dataclasses.replace(
    SENSOR, gain_occlusion=False, gain_facade="column"))])
def test_rated_gain_equals_the_sample_by_sample_reference(seed, sensor):
    size = 20
    rng = np.random.default_rng(seed)
    grid = rng.choice([FREE, UNKNOWN, OCCUPIED], size=(size,) * 3,
                      p=[0.5, 0.45, 0.05]).astype(np.int8)
    top = brute_tops(grid)
    q = tops.facade_tops(jnp.asarray(rng.integers(0, 4 * 256, (size, size)), jnp.int32), sensor)
    position = rng.uniform(0, 1, (4, 3)).astype(np.float32)
    unknown, facade, windows = gain(grid, top, position, sensor, size, q)
    plain = gain(grid, top, position, sensor, size)
    np.testing.assert_array_equal(np.asarray(unknown), np.asarray(plain[0]))
    np.testing.assert_array_equal(np.asarray(facade), np.asarray(plain[1]))
    want = [[reference_windows(grid, top, np.asarray(q), p, h, sensor) for h in range(4)]
            for p in position]
    assert np.asarray(windows).max() > 0
    np.testing.assert_allclose(np.asarray(windows), want, rtol=1e-6, atol=1e-9)
    # Every rate at the prior (q = RATE_SCALE): the facade gain itself, bit for bit.
    ones = jnp.full((size, size), spec.RATE_SCALE, jnp.int32)
    np.testing.assert_array_equal(np.asarray(gain(grid, top, position, sensor, size, ones)[2]),
                                  np.asarray(plain[1]))


def test_team_rated_gain_equals_the_gain_robot_by_robot(scenes):
    state, grids, tops = scenes[1]
    rates = team_rates(state.world, state.team_map, state.building_top, 3.0, SENSOR)
    position = jax.random.uniform(jax.random.PRNGKey(5), (2, 6, 3))
    origin = position[:, 0]
    got = jax.jit(view.team_view_gain, static_argnums=(4, 5))(
        state.team_map, state.building_top, position, origin, SENSOR, WORLD.size, rates)
    for i in range(2):
        want = gain(grids[i], tops[i], position[i], SENSOR, WORLD.size, rates[i])
        for g, w in zip(got, want):
            np.testing.assert_array_equal(np.asarray(g[i]), np.asarray(w))


# ---------------------------------------------------------------------------------------
# The policy's optional input


@pytest.mark.slow
def test_belief_input_is_off_by_default_and_appends_two_columns():
    assert features() == FEATURES
    assert features(ahead=True, belief=True)[-3:] == (*BELIEF_FEATURES, "ahead_rate")
    cfg = from_dict({"world": {"size": 30, "buildings": 36}, "candidates": {"positions": 8},
                     "policy": {"belief_features": True}})
    params, dyn = EnvParams.from_config(cfg), DynamicParams.from_config(cfg)
    assert params.n_features == len(FEATURES) + 2
    obs, state = jax.jit(env.reset, static_argnums=1)(jax.random.PRNGKey(0), params, dyn)
    rates = belief.team_rates(state, cfg.policy.belief_strength, params.sensor, params.world)
    c = state.candidates
    windows = jax.vmap(lambda o, t, p, r: view.view_gain(o, t, p, params.sensor, params.size,
                                                         r)[2])(
        state.occupancy, state.building_top, c.position[:, ::4], rates)
    np.testing.assert_array_equal(np.asarray(obs.features[..., len(FEATURES)]),
                                  np.asarray(windows).reshape(c.cost.shape))
    per_cost = obs.features[..., len(FEATURES) + 1]
    np.testing.assert_allclose(np.asarray(per_cost), np.asarray(view.per_cost(
        obs.features[..., len(FEATURES)], c.cost, cfg.candidates.shell[1])), rtol=1e-6)


@pytest.mark.parametrize("overrides,key", [
    ({"eval": {"planners": ["nbv_targets"]}, "world": {"clearance": 0,
                                                        "target_placement": "footprint"},
      "sensor": {"model": "frustum"}}, "world.clearance"),
    ({"eval": {"planners": ["nbv_targets"], "nbv_targets_branches": 200}},
     "eval.nbv_targets_branches"),
])
def test_settings_the_belief_cannot_use_are_refused(overrides, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        from_dict(overrides)
