"""Candidate sampling: shapes, geometry, reachability, separation, budget and tracing."""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import candidates, geometry
from jaxmripp.config import CandidateConfig, RobotConfig, SafetyConfig

G = 50
CAND = CandidateConfig()  # K = 20 positions, shell [0.19, 0.21], oversample 3
TURN = RobotConfig().turn_cost  # 0.05
DC = 0.05
K, L = CAND.positions, CAND.count
HERE = np.array([0.5, 0.5, 0.5], np.float32)
H0 = 1  # current heading

SAFE = SafetyConfig()  # known_free, no escape
sample = jax.jit(functools.partial(candidates.sample, cand=CAND, safety=SAFE,
                                   turn_cost=TURN, collision_distance=DC, size=G))
sample_optimistic = jax.jit(functools.partial(
    candidates.sample, cand=CAND, safety=SafetyConfig(flight="optimistic"), turn_cost=TURN,
    collision_distance=DC, size=G))


def free_map():
    return jnp.zeros((G, G, G), jnp.int8)


def alone(n=3):
    """Other robots far away and unknown; row 0 is this robot itself (never known)."""
    others = np.full((n, 3), 0.9, np.float32)
    others[0] = HERE
    return jnp.asarray(others), jnp.zeros((n,), bool)


def draw(seed=0, position=HERE, heading=H0, budget=10.0, occupancy=None, others=None, known=None,
         sampler=sample):
    if others is None:
        others, known = alone()
    return sampler(
        jax.random.key(seed),
        jnp.asarray(position, jnp.float32),
        jnp.int32(heading),
        jnp.float32(budget),
        free_map() if occupancy is None else occupancy,
        others,
        known,
    )


def as_np(c: candidates.Candidates):
    return jax.tree.map(np.asarray, c)


def test_shapes_and_dtypes():
    c = draw()
    assert c.position.shape == (L, 3) and c.position.dtype == jnp.float32
    assert c.heading.shape == (L,) and c.heading.dtype == jnp.int32
    assert c.cost.shape == (L,) and c.cost.dtype == jnp.float32
    assert c.valid.shape == (L,) and c.valid.dtype == jnp.bool_
    c = as_np(c)
    # index = slot * 4 + heading: positions repeat per slot, headings cycle.
    np.testing.assert_array_equal(c.heading, np.tile(np.arange(4), K))
    np.testing.assert_array_equal(c.position, np.repeat(c.position[::4], 4, axis=0))
    assert c.valid.sum() > 0


def test_slot_zero_is_current_position_turning_in_place():
    c = as_np(draw())
    np.testing.assert_array_equal(c.position[:4], np.tile(HERE, (4, 1)))
    # Turning is allowed, staying put with the same heading is not.
    np.testing.assert_array_equal(c.valid[:4], np.arange(4) != H0)
    np.testing.assert_allclose(c.cost[:4], TURN * (np.arange(4) != H0))


@pytest.mark.parametrize("position", [HERE, np.zeros(3, np.float32), np.array([1, 0.5, 0.02])])
def test_valid_positions_inside_world_and_on_shell(position):
    position = np.asarray(position, np.float32)
    for seed in range(4):
        c = as_np(draw(seed, position=position))
        p = c.position[c.valid]
        assert len(p) > 0
        assert np.all((p >= 0) & (p <= 1))
        dist = np.linalg.norm(p - position, axis=-1)
        at_start = dist == 0
        lo, hi = CAND.shell
        assert np.all(at_start | ((dist >= lo - 1e-5) & (dist <= hi + 1e-5)))
        # Valid slots come first, padding after: kept positions are compacted.
        slot_valid = c.valid.reshape(K, 4).any(axis=1)
        assert not np.any(slot_valid[1:] & ~slot_valid[:-1])


def test_padding_sits_at_current_position_and_is_masked():
    # In a corner most draws fall outside the cube, so some slots must be padding.
    corner = np.zeros(3, np.float32)
    c = as_np(draw(position=corner))
    pad = ~c.valid.reshape(K, 4).any(axis=1)
    assert pad.any()
    np.testing.assert_array_equal(c.position.reshape(K, 4, 3)[pad], 0.0)
    assert np.all(np.isfinite(c.cost))


def _occupied_runs(start, end, occupancy, steps=4000):
    """Independent check: lengths of the stretches of the segment inside OCCUPIED voxels."""
    t = np.linspace(0.0, 1.0, steps)
    points = start + t[:, None] * (end - start)
    vox = np.clip(np.floor(points * G), 0, G - 1).astype(int)
    inside = occupancy[vox[:, 0], vox[:, 1], vox[:, 2]] == geometry.OCCUPIED
    step = np.linalg.norm(end - start) / (steps - 1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(int), [0]])))
    starts, stops = edges[::2], edges[1::2]  # each run is inside[starts:stops]
    return float(np.max(stops - starts, initial=0) * step)


def test_wall_in_own_map_blocks_candidates_behind_it():
    wall_x = 27  # the robot at x = 0.5 sits in voxel 25; the wall is 0.04-0.06 ahead
    occ = np.zeros((G, G, G), np.int8)
    occ[wall_x] = geometry.OCCUPIED
    for seed in range(4):
        c = as_np(draw(seed, occupancy=jnp.asarray(occ)))
        p = c.position[c.valid]
        assert len(p) > 0
        assert np.all(p[:, 0] < wall_x / G), "a candidate lies behind the wall"
        for end in p:
            assert _occupied_runs(HERE, end, occ) == 0.0

    # The same wall merely unknown to the robot: flights only go through known-free space,
    # so it blocks as well; only the unsafe reference (`optimistic`) flies through it.
    occ[wall_x] = geometry.UNKNOWN
    behind = 0
    for seed in range(4):
        c = as_np(draw(seed, occupancy=jnp.asarray(occ)))
        assert np.all(c.position[c.valid][:, 0] < wall_x / G)
        c = as_np(draw(seed, occupancy=jnp.asarray(occ), sampler=sample_optimistic))
        behind += np.sum(c.position[c.valid][:, 0] > (wall_x + 1) / G)
    assert behind > 0


def test_scattered_obstacles_never_crossed_by_a_valid_path():
    # The exact traversal: no valid flight touches an occupied voxel at all.
    rng = np.random.default_rng(0)
    occ = np.zeros((G, G, G), np.int8)
    for corner in rng.integers(15, 34, size=(60, 3)):
        x, y, z = corner
        occ[x : x + 2, y : y + 2, z : z + 2] = geometry.OCCUPIED
    occ[24:27, 24:27, 24:27] = geometry.FREE  # the robot's own surroundings
    changed = 0
    for seed in range(4):
        c = as_np(draw(seed, occupancy=jnp.asarray(occ)))
        for end in c.position[c.valid]:
            assert _occupied_runs(HERE, end, occ) == 0.0
        free = as_np(draw(seed))
        changed += not np.array_equal(free.position, c.position)
    assert changed, "the obstacles should have rejected some draws"


def test_known_robots_are_kept_at_distance_unknown_ones_ignored():
    near = HERE + np.array([0.2, 0.0, 0.0], np.float32)  # on the sampling shell
    far_side = HERE - np.array([0.2, 0.0, 0.0], np.float32)
    others = jnp.asarray(np.stack([HERE, near, far_side]))
    dc = 0.1
    sample_dc = jax.jit(functools.partial(
        candidates.sample, cand=CAND, safety=SAFE, turn_cost=TURN,
        collision_distance=dc, size=G))

    def run(seed, known):
        return as_np(sample_dc(
            jax.random.key(seed), jnp.asarray(HERE), jnp.int32(H0), jnp.float32(10.0),
            free_map(), others, jnp.asarray(known),
        ))

    ignored_close = 0
    for seed in range(8):
        c = run(seed, [False, True, False])
        p = c.position[c.valid]
        assert np.all(np.linalg.norm(p - near, axis=-1) > dc)
        ignored_close += np.sum(np.linalg.norm(p - far_side, axis=-1) <= dc)
        # Unknown robots (and the robot itself, row 0) change nothing at all.
        unknown = run(seed, [False, False, False])
        baseline = as_np(sample_dc(
            jax.random.key(seed), jnp.asarray(HERE), jnp.int32(H0), jnp.float32(10.0),
            free_map(), jnp.full((3, 3), 0.95, jnp.float32), jnp.ones((3,), bool),
        ))
        jax.tree.map(np.testing.assert_array_equal, unknown, baseline)
    assert ignored_close > 0, "the unknown robot's surroundings should stay reachable"


def test_robots_within_d_c_are_offered_nothing_or_with_escape_only_flights_apart():
    """Two robots 0.03 apart (closer than d_c, as after a meeting out of radio range): the
    rule offers neither robot anything, so the env would retire both; with safety.escape
    each may turn in place or fly what takes it no closer to the other."""
    close = HERE + np.array([0.03, 0.0, 0.0], np.float32)
    others, known = jnp.asarray(np.stack([HERE, close])), jnp.asarray([False, True])
    stuck = as_np(draw(3, others=others, known=known))
    assert not stuck.valid.any()
    parting = jax.jit(functools.partial(
        candidates.sample, cand=CAND, safety=SafetyConfig(escape=True), turn_cost=TURN,
        collision_distance=DC, size=G))
    c = as_np(draw(3, others=others, known=known, sampler=parting))
    turns = np.arange(4) != H0
    np.testing.assert_array_equal(c.valid[:4], turns)  # slot 0: turning in place
    flights = c.position[4:][c.valid[4:]]
    assert len(flights) > 10
    # Every flight offered leaves the other robot behind: it heads away from it.
    assert np.all((flights - HERE) @ (HERE - close) >= 0)
    # The far robot unheard, both rules offer the same.
    alone_rule = as_np(draw(3, others=others, known=jnp.asarray([False, False])))
    alone_escape = as_np(draw(3, others=others, known=jnp.asarray([False, False]),
                              sampler=parting))
    jax.tree.map(np.testing.assert_array_equal, alone_rule, alone_escape)


def test_cost_is_distance_plus_turn_cost():
    for seed in range(3):
        c = as_np(draw(seed))
        dist = np.linalg.norm(c.position - HERE, axis=-1)
        expected = dist + TURN * (c.heading != H0)
        np.testing.assert_allclose(c.cost, expected, rtol=1e-5, atol=1e-6)


def test_budget_is_respected():
    lo, hi = CAND.shell
    for budget in [0.2, 0.23, 1.0]:
        c = as_np(draw(budget=budget))
        assert np.all(c.cost[c.valid] <= budget)
    # 0.2 lies inside the shell: nearer draws may go straight, but none may also turn.
    c = as_np(draw(budget=0.2))
    moves = c.valid & np.any(c.position != HERE, axis=-1)
    assert moves.any() and np.all(c.heading[moves] == H0)
    # Too little to move, enough to turn: only the three turns in place remain.
    c = as_np(draw(budget=0.1))
    assert c.valid.sum() == 3
    np.testing.assert_array_equal(c.position[c.valid], np.tile(HERE, (3, 1)))
    # Nothing left: nothing valid, and nothing NaN.
    for budget in [0.0, 0.01]:
        c = as_np(draw(budget=budget))
        assert not c.valid.any()
        assert np.all(np.isfinite(c.position)) and np.all(np.isfinite(c.cost))


def test_current_pose_is_never_a_candidate():
    for heading in range(4):
        c = as_np(draw(heading=heading))
        same = np.all(c.position == HERE, axis=-1) & (c.heading == heading)
        assert same.any() and not np.any(c.valid & same)


def test_deterministic_per_key():
    a, b, other = as_np(draw(7)), as_np(draw(7)), as_np(draw(8))
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert not np.array_equal(a.position, other.position)


def test_vmap_over_envs_and_robots_matches_single_calls():
    envs, n = 2, 3
    keys = jax.random.split(jax.random.key(1), (envs, n))
    rng = np.random.default_rng(1)
    positions = jnp.asarray(rng.uniform(0.2, 0.8, (envs, n, 3)), jnp.float32)
    headings = jnp.asarray(rng.integers(0, 4, (envs, n)), jnp.int32)
    budgets = jnp.asarray([[10.0, 0.1, 0.5], [0.0, 3.0, 10.0]], jnp.float32)
    occupancy = jnp.zeros((envs, G, G, G), jnp.int8)
    known = jnp.broadcast_to(~jnp.eye(n, dtype=bool), (envs, n, n))

    per_robot = jax.vmap(sample, in_axes=(0, 0, 0, 0, None, None, 0))
    per_env = jax.jit(jax.vmap(per_robot, in_axes=(0, 0, 0, 0, 0, 0, 0)))
    out = per_env(keys, positions, headings, budgets, occupancy, positions, known)
    chex.assert_shape(out.position, (envs, n, L, 3))
    chex.assert_shape([out.heading, out.cost, out.valid], (envs, n, L))
    for e in range(envs):
        for i in range(n):
            single = sample(keys[e, i], positions[e, i], headings[e, i], budgets[e, i],
                            occupancy[e], positions[e], known[e, i])
            one = jax.tree.map(lambda x: x[e, i], out)
            jax.tree.map(functools.partial(np.testing.assert_allclose, atol=1e-6), one, single)


def test_traced_once():
    """Turn cost and d_c are traced too (DynamicParams): new values do not retrace."""
    @jax.jit
    @chex.assert_max_traces(n=1)
    def traced(key, position, heading, budget, occupancy, others, known, turn_cost, dc):
        return candidates.sample(key, position, heading, budget, occupancy, others, known,
                                 CAND, SAFE, turn_cost, dc, G)

    others, known = alone()
    for seed, budget, heading, turn, dc in [(0, 10.0, 1, TURN, DC), (1, 0.3, 2, 0.1, 0.02),
                                            (2, 0.0, 0, 0.0, 0.0)]:
        c = traced(jax.random.key(seed), jnp.asarray(HERE), jnp.int32(heading),
                   jnp.float32(budget), free_map(), others, known, jnp.float32(turn),
                   jnp.float32(dc))
        np.testing.assert_allclose(c.cost[:4], turn * (np.arange(4) != heading), atol=1e-7)
