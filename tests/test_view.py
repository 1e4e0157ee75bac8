"""View gain (jaxmripp.spec.view): the sample table, building tops and the gain of candidate
poses, against hand-worked cases and a loop-by-loop reference; the next-best-view planners."""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.config import SensorConfig, from_dict
from jaxmripp.evaluation import baselines
from jaxmripp.sim import claims, env, maps, sensing, tops, view
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.spec import view as spec
from jaxmripp.spec.layout import FEATURES
from jaxmripp.spec.grid import FREE, HEADING_VECTORS, OCCUPIED, UNKNOWN
from gain_reference import brute_tops, reference_gains

SENSOR = SensorConfig(range=0.3)
G = 20
gain = jax.jit(view.view_gain, static_argnums=(3, 4))


# Both settings of the gain's model (sensor.gain_occlusion, sensor.gain_facade) away from
# the defaults: the reference's frustum and windows inside footprints.
SEE_THROUGH = dataclasses.replace(SENSOR, gain_occlusion=False, gain_facade="column")
SENSORS = [SENSOR, dataclasses.replace(SENSOR, gain_occlusion=False),
           dataclasses.replace(SENSOR, gain_facade="column"),
           dataclasses.replace(SENSOR, gain_facade="around"), SEE_THROUGH]


def test_table_rays_fan_out_from_the_heading_and_stay_in_the_sensor_view():
    offsets, weights = spec.gain_table(SENSOR.fov_deg, SENSOR.range, G)
    s = spec.samples_per_ray(SENSOR.range, G)
    assert offsets.shape == (4, spec.RAYS_PER_SIDE**2, s, 3)
    assert s * spec.SAMPLE_STEP + math.sqrt(3) / 2 <= SENSOR.range * G
    np.testing.assert_array_equal(weights, (spec.SAMPLE_STEP * np.arange(1, s + 1)) ** 2)
    centre = spec.RAYS_PER_SIDE**2 // 2
    tan = math.tan(math.radians(SENSOR.fov_deg) / 2)
    for h in range(4):
        d = spec.SAMPLE_STEP * np.arange(1, s + 1)
        np.testing.assert_array_equal(offsets[h, centre], d[:, None] * HEADING_VECTORS[h])
        forward, right = HEADING_VECTORS[h][:2], np.cross(HEADING_VECTORS[h], [0, 0, 1])[:2]
        o = offsets[h].reshape(-1, 3)
        inside = sensing._in_raycast_view(o[:, :2] @ forward, o[:, :2] @ right, o[:, 2], tan,
                                          SENSOR.range * G)
        assert inside.all()


def test_unknown_world_is_all_gain_and_a_wall_ahead_hides_what_is_behind_it():
    occupancy = np.full((G, G, G), UNKNOWN, np.int8)
    top = np.zeros((G, G), np.int8)
    position = np.full((1, 3), 0.5, np.float32)
    unknown, facade = (np.asarray(x) for x in gain(occupancy, top, position, SENSOR, G))
    np.testing.assert_array_equal(unknown, 1.0)
    np.testing.assert_array_equal(facade, 0.0)
    # The first sample (d = 1) of the central and the four corner rays (directions
    # (1, 0, 0) and (3, +-2, +-2) / sqrt(17)) rounds to the voxel just ahead, that of the
    # four edge rays ((3, +-2, 0) / sqrt(13)) to a side neighbour: a known building voxel
    # just ahead hides 5 of the 9 rays of heading 0, and nothing of the others.
    occupancy[11, 10, 10] = OCCUPIED
    unknown, _ = (np.asarray(x) for x in gain(occupancy, top, position, SENSOR, G))
    np.testing.assert_allclose(unknown[0], [4 / 9, 1.0, 1.0, 1.0], rtol=1e-6)
    # Three voxels ahead only the central ray meets it (S = 5 samples, weights d^2 = 1, 4,
    # 9, 16, 25 on each of 9 rays): it loses d = 3, 4, 5.
    occupancy[11, 10, 10] = UNKNOWN
    occupancy[13, 10, 10] = OCCUPIED
    top = tops.raise_tops(jnp.asarray(top), jnp.asarray([(13 * G + 10) * G + 10]),
                          jnp.asarray([OCCUPIED], jnp.int8))
    assert int(top[13, 10]) == 11
    unknown, facade = (np.asarray(x) for x in gain(occupancy, top, position, SENSOR, G))
    assert spec.samples_per_ray(SENSOR.range, G) == 5
    assert unknown[0, 0] == pytest.approx(1 - (9 + 16 + 25) / (9 * 55), abs=1e-6)
    # Facade: unknown samples at z <= 11 over the columns around (13, 10): heading 0 sees
    # them in front of the voxel, heading 2 (-x) looks away.
    assert facade[0, 0] > 0 and facade[0, 2] == 0
    np.testing.assert_allclose(np.stack([unknown, facade], -1),
                               reference_gains(occupancy, np.asarray(top), position, SENSOR),
                               atol=1e-6)


def test_a_sensor_that_sees_through_buildings_gains_behind_a_known_wall():
    """Without occlusion a known building voxel ahead hides nothing (only it is not
    unknown); with column facade only its own column is facade."""
    occupancy = np.full((G, G, G), UNKNOWN, np.int8)
    occupancy[13, 10, 10] = OCCUPIED  # 3 voxels ahead of voxel (10, 10, 10); top 11
    top = np.zeros((G, G), np.int8)
    top[13, 10] = 11
    position = np.full((1, 3), 0.5, np.float32)
    occluded, _ = (np.asarray(x) for x in gain(occupancy, top, position, SENSOR, G))
    unknown, facade = (np.asarray(x) for x in gain(occupancy, top, position, SEE_THROUGH, G))
    # The central ray (along +x, samples d = 1..5, weights d^2 of 9 x 55 in all) meets it
    # at d = 3: with occlusion it loses d = 3, 4, 5; without, only d = 3.
    assert occluded[0, 0] == pytest.approx(1 - (9 + 16 + 25) / (9 * 55), abs=1e-6)
    assert unknown[0, 0] == pytest.approx(1 - 9 / (9 * 55), abs=1e-6)
    np.testing.assert_array_equal(unknown[0, 1:], 1.0)
    # Column (13, 10) up to z = 11 is facade: of the samples in it, the downward edge ray
    # ((3, 0, -2) / sqrt(13)) has d = 4 at (13, 10, 8); the upward one's lands at z = 12,
    # the central ray's on the known voxel. Other headings look away from it.
    assert facade[0, 0] == pytest.approx(16 / (9 * 55), abs=1e-6)
    np.testing.assert_array_equal(facade[0, 1:], 0.0)
    np.testing.assert_allclose(np.stack([unknown, facade], -1),
                               reference_gains(occupancy, top, position, SEE_THROUGH), atol=1e-6)


@pytest.mark.parametrize("seed,sensor", [(0, SENSORS[0]), (1, SENSORS[0]), (2, SENSORS[0]),
                                         (3, SENSORS[1]), (4, SENSORS[2]), (5, SENSORS[3]),
                                         (6, SENSORS[4])])
def test_gain_equals_the_sample_by_sample_reference_on_random_maps(seed, sensor):
    rng = np.random.default_rng(seed)
    occupancy = rng.choice([FREE, UNKNOWN, OCCUPIED], size=(G, G, G),
                           p=[0.5, 0.45, 0.05]).astype(np.int8)
    top = brute_tops(occupancy)
    position = rng.uniform(0, 1, (5, 3)).astype(np.float32)
    unknown, facade = gain(occupancy, top, position, sensor, G)
    expected = reference_gains(occupancy, top, position, sensor)
    np.testing.assert_allclose(np.asarray(unknown), expected[..., 0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(facade), expected[..., 1], atol=1e-6)


def _team_scene(seed, robots=4, slots=6):
    """Random maps (each a random part of one truth) as int8 maps and as their team map,
    tops and candidate positions; some slots sit in their robot's voxel (as padding does),
    the rest elsewhere."""
    rng = np.random.default_rng(seed)
    building = rng.uniform(size=(G, G, G)) < 0.1
    known = rng.uniform(size=(robots, G, G, G)) < 0.55
    occupancy = np.where(known, np.where(building, OCCUPIED, FREE), UNKNOWN).astype(np.int8)
    team = np.asarray(maps.pack(jnp.asarray(occupancy), jnp.asarray(building)))
    top = np.stack([brute_tops(o) for o in occupancy])
    origin = rng.uniform(0, 1, (robots, 3)).astype(np.float32)
    position = rng.uniform(0, 1, (robots, slots, 3)).astype(np.float32)
    at_robot = rng.uniform(size=(robots, slots)) < 0.5
    position[at_robot] = np.broadcast_to(origin[:, None], position.shape)[at_robot]
    # Another point of the robot's own voxel takes the same gain.
    position[0, 0] = (np.floor(origin[0] * G) + 0.75) / G
    return occupancy, team, top, position, origin


def _robot_by_robot(occupancy, top, position, sensor=SENSOR):
    return [np.stack([np.asarray(gain(o, t, p, sensor, G)[k])
                      for o, t, p in zip(occupancy, top, position)]) for k in range(2)]


@pytest.mark.parametrize("sensor", [SENSOR, SEE_THROUGH])
def test_team_gain_equals_the_gain_robot_by_robot_also_under_nested_vmaps(sensor):
    scenes = [_team_scene(seed) for seed in range(6)]
    team = jax.jit(view.team_view_gain, static_argnums=(4, 5))
    for occupancy, team_map, top, position, origin in scenes[:2]:
        got = team(team_map, top, position, origin, sensor, G)
        for g, want in zip(got, _robot_by_robot(occupancy, top, position, sensor)):
            np.testing.assert_array_equal(np.asarray(g), want)
    # Two vmapped levels (as a sweep over an env batch): the batch folds into one list.
    stacked = [np.stack(x).reshape(3, 2, *x[0].shape) for x in list(zip(*scenes))[1:]]
    nested = jax.jit(jax.vmap(jax.vmap(lambda o, t, p, r: view.team_view_gain(
        o, t, p, r, sensor, G))))
    got = nested(*stacked)
    for i in range(3):
        for j in range(2):
            occupancy, _, top, position, _ = scenes[2 * i + j]
            for g, want in zip(got, _robot_by_robot(occupancy, top, position, sensor)):
                np.testing.assert_array_equal(np.asarray(g)[i, j], want)


def test_team_gain_with_every_or_no_slot_away_and_robot_by_robot_beyond_flat_indices(
        monkeypatch):
    occupancy, team_map, top, position, origin = _team_scene(7, robots=3, slots=5)
    want = _robot_by_robot(occupancy, top, position)
    # Every slot away from its robot's voxel; every slot in it; a mix.
    origin_far = np.full_like(origin, 0.999)
    away = np.where(np.floor(position * G) == np.floor(origin_far[:, None] * G), 0.0, position)
    cases = [(away, origin_far), (np.broadcast_to(origin[:, None], position.shape), origin),
             (position, origin)]
    team = jax.jit(view.team_view_gain, static_argnums=(4, 5))
    for pos, org in cases:
        expected = _robot_by_robot(occupancy, top, pos)
        for g, e in zip(team(team_map, top, pos, org, SENSOR, G), expected):
            np.testing.assert_array_equal(np.asarray(g), e)
    # Where one flat index over all maps would overflow int32, robot by robot.
    monkeypatch.setattr(view, "_FLAT_LIMIT", G**3)
    view._team_gains.cache_clear()
    try:
        team = jax.jit(view.team_view_gain, static_argnums=(4, 5))  # traced anew
        for g, e in zip(team(team_map, top, position, origin, SENSOR, G), want):
            np.testing.assert_array_equal(np.asarray(g), e)
    finally:
        view._team_gains.cache_clear()


def test_gain_in_a_large_world_equals_the_runtime():
    """At G = 125 the weight totals pass 2^15 (the packed one-accumulator sum no longer
    fits): the JAX gain still equals the NumPy runtime's, pose by pose."""
    from jaxmripp.runtime import view as runtime_view

    size, sensor = 125, SensorConfig()
    assert spec.RAYS_PER_SIDE**2 * int(spec.gain_table(sensor.fov_deg, sensor.range,
                                                       size)[1].sum()) >= 1 << 15
    rng = np.random.default_rng(7)
    occupancy = rng.choice([FREE, UNKNOWN, OCCUPIED], size=(size,) * 3,
                           p=[0.6, 0.38, 0.02]).astype(np.int8)
    top = np.max(np.where(occupancy == OCCUPIED, np.arange(size) + 1, 0),
                 axis=-1).astype(np.int8)
    position = rng.uniform(0.2, 0.8, (3, 3)).astype(np.float32)
    unknown, facade = gain(occupancy, top, position, sensor, size)
    poses, headings = np.repeat(position, 4, axis=0), np.tile(np.arange(4), 3)
    expected = runtime_view.view_gain(occupancy.reshape(-1), top, poses, headings,
                                      runtime_view.GainModel(sensor.fov_deg, sensor.range), size)
    assert np.asarray(facade).max() > 0
    np.testing.assert_allclose(np.asarray(unknown).reshape(-1), expected[0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(facade).reshape(-1), expected[1], atol=1e-6)


def test_tops_follow_the_cast_writes():
    rng = np.random.default_rng(3)
    voxels = rng.integers(0, G**3 + 5, 200).astype(np.int32)  # some beyond the grid
    values = rng.choice([FREE, OCCUPIED], 200).astype(np.int8)
    top = np.asarray(tops.raise_tops(jnp.zeros((G, G), jnp.int8), voxels, values))
    expected = np.zeros((G, G), int)
    for v, code in zip(voxels, values):
        if v < G**3 and code == OCCUPIED:
            x, y, z = np.unravel_index(v, (G, G, G))
            expected[x, y] = max(expected[x, y], z + 1)
    np.testing.assert_array_equal(top, expected)


def test_peer_distance_caps_and_ignores_robots_not_heard():
    cands = jnp.asarray([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    others = jnp.asarray([[0.0, 0.0, 0.0], [0.9, 0.0, 0.0], [0.0, 0.4, 0.0]])
    heard = jnp.asarray([False, True, False])
    d = np.asarray(view.peer_distance(cands, others, heard, 0.15))
    np.testing.assert_allclose(d, [spec.PEER_CAP, 0.6 / 0.15], rtol=1e-6)  # 0.9 / 0.15 > cap
    far = np.asarray(view.peer_distance(cands, others, jnp.zeros(3, bool), 0.15))
    np.testing.assert_array_equal(far, spec.PEER_CAP)


@functools.partial(jax.jit, static_argnums=1)
def _observe(state, params):
    """The team's observations as the env builds them, the lookahead input aside."""
    return env.observe(state, params, env.belief_rates(state, params))


def _twins():
    """A reset team whose robot 1 is a copy of robot 0: one spot, one map, one candidate
    set (both hear each other)."""
    cfg = from_dict({"world": {"size": 20}, "candidates": {"positions": 6}})
    params, dyn = EnvParams.from_config(cfg), DynamicParams.from_config(cfg)
    _, state = jax.jit(env.reset, static_argnums=1)(jax.random.PRNGKey(0), params, dyn)
    twin = lambda x: x.at[1].set(x[0])  # noqa: E731
    state = state.replace(position=twin(state.position), heading=twin(state.heading),
                          team_map=maps.pack(twin(state.occupancy), maps.buildings(state.team_map)),
                          building_top=twin(state.building_top),
                          candidates=jax.tree.map(twin, state.candidates))
    assert bool(state.heard[0, 1]) and bool(state.heard[1, 0])
    return params, dyn, state, _observe(state, params)


def test_deciding_in_turn_hides_exactly_the_views_peers_claimed():
    params, _, state, obs = _twins()
    column = {name: FEATURES.index(name) for name in FEATURES}
    decide = lambda i, mine, occupancy: (jnp.argmax(jnp.where(  # noqa: E731
        mine.mask, mine.features[:, column["view_unknown_per_cost"]], -1.0)), None)
    run = jax.jit(lambda obs, state: claims.in_turn(decide, obs, state, params.sensor,
                                                    params.candidates.shell[1]))
    decided, actions, _ = run(obs, state)
    first = int(actions[0])
    assert float(obs.features[1, first, column["view_unknown"]]) > 0
    # Robot 0 decides on what observe wrote; robot 1, with robot 0's map, finds nothing
    # left to see from robot 0's pose, and only the VIEW columns change.
    np.testing.assert_array_equal(decided.features[0], obs.features[0])
    for name in ("view_unknown", "view_facade", "view_unknown_per_cost", "view_facade_per_cost"):
        assert float(decided.features[1, first, column[name]]) == 0.0, name
    others = [j for j in range(len(FEATURES)) if not FEATURES[j].startswith("view_")]
    np.testing.assert_array_equal(decided.features[1][:, others], obs.features[1][:, others])
    assert int(actions[1]) != first
    # Robots that hear nobody decide on their own observations.
    alone = state.replace(heard=jnp.eye(state.heard.shape[0], dtype=bool))
    decided, actions, _ = run(obs, alone)
    np.testing.assert_array_equal(decided.features, obs.features)
    assert int(actions[0]) == int(actions[1])


def test_with_relay_a_robot_hears_the_claims_of_its_whole_component():
    """Three copies of one robot in a chain (0 - 1 - 2): robot 2 sees robot 0's view
    claimed only when claims are relayed."""
    params, _, state, obs = _twins()
    triple = lambda x: x.at[2].set(x[0])  # noqa: E731
    chain = jnp.asarray([[1, 1, 0], [1, 1, 1], [0, 1, 1]], bool)
    state = state.replace(position=triple(state.position), heading=triple(state.heading),
                          team_map=maps.pack(triple(state.occupancy), maps.buildings(state.team_map)),
                          building_top=triple(state.building_top),
                          candidates=jax.tree.map(triple, state.candidates), heard=chain)
    obs = _observe(state, params)
    unknown = FEATURES.index("view_unknown")
    decide = lambda i, mine, occupancy: (jnp.argmax(jnp.where(  # noqa: E731
        mine.mask, mine.features[:, FEATURES.index("view_unknown_per_cost")], -1.0)), None)
    left = {}
    for relay in (False, True):
        decided, actions, _ = jax.jit(lambda obs, state: claims.in_turn(
            decide, obs, state, params.sensor, params.candidates.shell[1], relay))(obs, state)
        left[relay] = float(decided.features[2, int(actions[0]), unknown])
    assert left[True] == 0.0 < left[False]


def test_nbv_team_robots_do_not_claim_the_same_view():
    """Two robots at one spot with one map and one candidate set: the second never takes
    the first one's pose (its view is claimed) while another pose has gain."""
    params, dyn, state, obs = _twins()
    key = jax.random.PRNGKey(1)
    _, alone = jax.jit(baselines.nbv_planner().act)(key, None, obs)
    _, team = jax.jit(baselines.nbv_team_planner(params).act)(key, None, obs, state, dyn)
    alone, team = np.asarray(alone), np.asarray(team)
    assert alone[0] == alone[1] == team[0]
    assert team[1] != team[0]
