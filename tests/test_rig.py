"""The RIG baseline (jaxmripp.evaluation.rig): jit / vmap on env states, feasibility, the
tree's invariants, the greedy limit (no rounds) and a hand-made case where planning past
the first move pays.

Two compilations: one vmapped env function (reset, then rig with the number of rounds
traced, and robot 0's tree) and one vmapped `grow` on a hand-made problem. The reset
states already hold each robot's first observation in its map and utility GP.
"""

from __future__ import annotations

import math
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config
from jaxmripp.evaluation import evaluate, rig
from jaxmripp.evaluation.tree_search import Context, scores
from jaxmripp.sim import comms, geometry, maps
from jaxmripp.sim import env as envmod

ROOT = Path(__file__).resolve().parents[1]
# truncate: lines must avoid voxels mapped occupied. Under the default known_free nearly
# every deeper edge leaves the little a reset map knows to be free, and the tree's
# invariants would be checked on a handful of nodes. The robots start at the (0, 0, 0)
# corner.
CFG = config.load(ROOT / "tests" / "smoke.yaml", ["safety.flight=truncate"])
PARAMS = evaluate.eval_params(CFG, 2.0)
DYN = evaluate.eval_dynamic(CFG, 2.0, radio_range=math.inf)
FAST = {"xla_backend_optimization_level": 0}
ENVS, ITERATIONS, DEPTH, WALL = 4, 64, 4, 3


@chex.assert_max_traces(n=1)
def _play(key, dyn, rounds):
    """A reset env with a wall added to the maps, rig's actions and robot 0's tree (no
    peers). The wall, the voxels with x index WALL mapped occupied, stands across the way
    from the robots' corner to the rest of the world, so the line rule has work to do."""
    key_reset, key_act, key_tree = jax.random.split(key, 3)
    obs, state = envmod.reset(key_reset, PARAMS, dyn)
    state = state.replace(team_map=maps.pack(state.occupancy.at[:, WALL].set(geometry.OCCUPIED),
                                             maps.buildings(state.team_map).at[WALL].set(True)))
    planner = rig.rig_planner(PARAMS, ITERATIONS, DEPTH, rounds=rounds)
    _, actions = planner.act(key_act, planner.init(PARAMS.n_robots), obs, state, dyn)
    n = PARAMS.n_robots
    tree = rig.robot_tree(key_tree, PARAMS, obs, state, dyn, 0, jnp.zeros((n, 4)),
                          jnp.zeros((n,), bool), ITERATIONS, DEPTH, rounds=rounds)
    return obs, state, actions, tree


@pytest.fixture(scope="module")
def played():
    play = jax.jit(jax.vmap(_play, in_axes=(0, None, None)), compiler_options=FAST)
    keys = jax.random.split(jax.random.PRNGKey(5), ENVS)
    out = {rounds: jax.tree.map(np.asarray, play(keys, DYN, rounds))
           for rounds in (0, ITERATIONS)}
    return out


def _env(tree, e):
    return jax.tree.map(lambda x: x[e], tree)


def test_actions_are_feasible_candidates(played):
    for obs, _, actions, _ in played.values():
        assert actions.shape == (ENVS, PARAMS.n_robots)
        assert np.all((actions >= 0) & (actions < obs.mask.shape[-1]))
        picked = np.take_along_axis(obs.mask, actions[..., None], -1)[..., 0]
        assert np.all(picked | ~obs.mask.any(-1))


def test_without_rounds_rig_is_sequential_greedy(played):
    """An independent reference: argmax of the hallucinated-GP score over the candidates,
    robot 1 conditioned on the pose robot 0 chose (the radio reaches everywhere)."""
    obs, state, actions, tree = played[0]
    score = jax.jit(scores, static_argnums=(4, 5))
    assert not tree.valid[:, obs.mask.shape[-1]:].any()
    for e in range(ENVS):
        o, s = _env(obs, e), _env(state, e)
        hears = np.asarray(comms.contacts(jnp.asarray(s.position), DYN.radio_range))
        peer_pose = np.zeros((PARAMS.n_robots, 4), np.float32)
        peer_valid = np.zeros(PARAMS.n_robots, bool)
        for i in range(PARAMS.n_robots):
            c = _env(s.candidates, i)
            ctx = Context(utility=_env(s.utility_gp, i), occupancy=s.occupancy[i],
                          offset=c.position - s.position[i], heading=c.heading,
                          slot_kept=c.valid, peer_pose=jnp.asarray(peer_pose),
                          peer_valid=jnp.asarray(peer_valid & hears[i]),
                          turn_cost=DYN.turn_cost)
            poses = geometry.pose(jnp.asarray(c.position), jnp.asarray(c.heading))
            r = np.asarray(score(ctx, poses, jnp.zeros((DEPTH, 4)), jnp.zeros(DEPTH, bool),
                                  PARAMS.gp, 0.3))
            a = actions[e, i]
            if o.mask[i].any():
                assert o.mask[i, a] and r[a] >= r[o.mask[i]].max() - 2e-4, (e, i, a, r)
            peer_pose[i], peer_valid[i] = np.asarray(poses[a]), o.mask[i].any()


def _segment_clear(occupancy, start, end, samples=400):
    """Brute force: no point along the segment lies in a voxel mapped occupied."""
    t = (np.arange(samples) + 0.5) / samples
    points = start[None] + t[:, None] * (end - start)[None]
    voxel = np.clip(np.floor(points * PARAMS.size), 0, PARAMS.size - 1).astype(int)
    codes = occupancy[voxel[:, 0], voxel[:, 1], voxel[:, 2]]
    assert PARAMS.safety.flight == "truncate"
    return np.all(codes != geometry.OCCUPIED)


def test_tree_nodes_respect_budget_reach_and_line_rule(played):
    obs, state, _, tree = played[ITERATIONS]
    n_cand = obs.mask.shape[-1]
    reach = PARAMS.candidates.shell[1]
    grown = 0
    for e in range(ENVS):
        t, s = _env(tree, e), _env(state, e)
        np.testing.assert_array_equal(t.valid[:n_cand], obs.mask[e, 0])
        for k in np.flatnonzero(t.valid):
            d = t.depth[k]
            assert 1 <= d <= DEPTH and t.path_valid[k, :d].all() and not t.path_valid[k, d:].any()
            assert obs.mask[e, 0, t.root_action[k]]
            c = s.candidates
            np.testing.assert_allclose(t.path[k, 0, :3], c.position[0, t.root_action[k]])
            np.testing.assert_allclose(t.path[k, d - 1, :3], t.position[k])
            assert np.all((t.position[k] >= 0) & (t.position[k] <= 1))
            spent = c.cost[0, t.root_action[k]]
            for j in range(1, d):
                a, b = t.path[k, j - 1], t.path[k, j]
                step = np.linalg.norm(b[:3] - a[:3])
                assert step <= reach + 1e-5
                assert _segment_clear(s.occupancy[0], a[:3], b[:3]), (e, k, j)
                spent += step + DYN.turn_cost * (a[3] != b[3])
            np.testing.assert_allclose(t.cost[k], spent, rtol=1e-5, atol=1e-5)
            assert t.cost[k] <= s.budget_left[0] + 1e-5
            np.testing.assert_allclose(t.budget[k], s.budget_left[0] - t.cost[k], atol=1e-5)
        grown += t.valid[n_cand:].sum()
    assert grown >= ENVS * 10, f"{grown} nodes beyond the candidates: too few to check"


# ---------------------------------------------------------------------------------------
# A hand-made problem: A is the best first move, B leads to a rich region A cannot reach


def _hand_score(poses, path, path_valid):
    """1 per pose beyond x = 0.55 not within 0.05 of a pose on the path; A = 0.5, B = 0.4."""
    x = poses[:, :3]
    seen = jnp.any(path_valid[None] & (jnp.linalg.norm(
        x[:, None] - path[None, :, :3], axis=-1) < 0.05), axis=-1)
    rich = jnp.where((x[:, 0] > 0.55) & ~seen, 1.0, 0.0)
    at = lambda p: jnp.linalg.norm(x - jnp.asarray(p), axis=-1) < 1e-3  # noqa: E731
    return rich + 0.5 * at([0.1, 0.5, 0.5]) + 0.4 * at([0.45, 0.5, 0.5])


CANDIDATES = jnp.asarray([[0.1, 0.5, 0.5], [0.45, 0.5, 0.5], [0.85, 0.5, 0.5]], jnp.float32)


@jax.jit
@jax.vmap
def _hand_tree(key, mask, rounds):
    # budget 0.5, first moves cost 0.1: from A (x = 0.1) the robot reaches x <= 0.5 only
    tree = rig.grow(key, jnp.asarray([0.3, 0.5, 0.5]), jnp.float32(0.5), jnp.int32(0),
                    CANDIDATES, jnp.zeros(3, jnp.int32),
                    jnp.full(3, 0.1), mask, _hand_score, lambda a, b: jnp.bool_(True),
                    jnp.float32(0.02), 0.3, ITERATIONS, DEPTH, rounds=rounds)
    return tree, rig.best_action(jax.random.fold_in(key, 7), tree, mask)


def test_rig_plans_past_the_best_first_move():
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    masks = jnp.asarray([[True, True, False]] * 6 + [[False] * 3] * 2)  # C is infeasible
    rounds = jnp.asarray([ITERATIONS] * 5 + [0] + [ITERATIONS] * 2)
    tree, actions = jax.tree.map(np.asarray, _hand_tree(keys, masks, rounds))
    assert actions[:5].tolist() == [1] * 5  # B, for its subtree, on every key
    assert actions[5] == 0  # no rounds: the greedy first move A
    assert actions[6:].tolist() == [0, 0] and not tree.valid[6:].any()  # nothing feasible
    for k in range(5):  # A's subtree never gets past x = 0.5 (its budget)
        from_a = tree.valid[k] & (tree.root_action[k] == 0)
        assert np.all(tree.position[k][from_a, 0] <= 0.5 + 1e-5)
        assert np.all(tree.cost[k][tree.valid[k]] <= 0.5 + 1e-5)
