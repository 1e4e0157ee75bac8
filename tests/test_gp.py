"""The incremental GP against a dense float64 NumPy/SciPy GP on random data."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.distance import cdist

from jaxmripp.sim import gp
from jaxmripp.sim.gp import evict
from jaxmripp.config import GPConfig
from jaxmripp.sim.geometry import HEADING_ANGLES

RTOL, ATOL = 1e-3, 1e-4  # relative, with an absolute floor (values and variances are O(1))


def reference_kernel(a, b, cfg):
    """Matern-1/2 on poses embedded as (x, y, z, hs cos(theta), hs sin(theta)), float64."""

    def embed(p):
        p = np.asarray(p, np.float64)
        hs = cfg.heading_scale
        return np.concatenate([p[:, :3], hs * np.cos(p[:, 3:]), hs * np.sin(p[:, 3:])], axis=1)

    return cfg.variance * np.exp(-cdist(embed(a), embed(b)) / cfg.length_scale)


def reference_posterior(inputs, targets, queries, cfg):
    """Dense posterior mean and latent variance at queries, float64."""
    if len(inputs) == 0:
        return np.zeros(len(queries)), np.full(len(queries), cfg.variance)
    factor = cho_factor(reference_kernel(inputs, inputs, cfg) + cfg.noise * np.eye(len(inputs)))
    cross = reference_kernel(inputs, queries, cfg)
    mean = cross.T @ cho_solve(factor, np.asarray(targets, np.float64))
    variance = cfg.variance - np.sum(cross * cho_solve(factor, cross), axis=0)
    return mean, variance


def random_poses(rng, n):
    headings = HEADING_ANGLES[rng.integers(0, len(HEADING_ANGLES), n)]
    return np.concatenate([rng.uniform(0, 1, (n, 3)), headings[:, None]], 1).astype(np.float32)


_add = jax.jit(gp.add, static_argnames="cfg")
_predict = jax.jit(gp.predict, static_argnames="cfg")
_add_many = jax.jit(gp.add_many, static_argnames="cfg")


def add(state, pose, value, cfg, eval_poses, enabled=True):
    return _add(state, pose, np.float32(value), cfg, eval_poses, np.bool_(enabled))


def assert_matches_reference(state, inputs, targets, queries, cfg, eval_poses):
    mean, variance = _predict(state, queries, cfg)
    ref_mean, ref_variance = reference_posterior(inputs, targets, queries, cfg)
    np.testing.assert_allclose(mean, ref_mean, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(variance, ref_variance, rtol=RTOL, atol=ATOL)
    _, ref_eval_variance = reference_posterior(inputs, targets, eval_poses, cfg)
    np.testing.assert_allclose(gp.covariance_trace(state), ref_eval_variance.sum(), rtol=RTOL)


def test_kernel_matches_reference_and_wraps_headings():
    cfg = GPConfig()
    a, b = random_poses(np.random.default_rng(0), 7), random_poses(np.random.default_rng(1), 5)
    np.testing.assert_allclose(gp.kernel(a, b, cfg), reference_kernel(a, b, cfg), rtol=1e-5)
    origin, headings = np.zeros((1, 4), np.float32), np.zeros((2, 4), np.float32)
    headings[:, 3] = [np.pi / 2, 3 * np.pi / 2]  # both a quarter turn away from heading 0
    left, right = np.asarray(gp.kernel(origin, headings, cfg))[0]
    assert left == pytest.approx(right, rel=1e-6) and left < cfg.variance


@pytest.mark.parametrize("length_scale", [0.2, 1.0, 3.0])
def test_kernel_is_positive_semidefinite(length_scale):
    # The wrapped arc length in place of the chord fails this for length_scale >= 0.5.
    cfg = GPConfig(length_scale=length_scale, heading_scale=0.3)
    poses = random_poses(np.random.default_rng(2), 64)
    gram = np.asarray(gp.kernel(poses, poses, cfg), np.float64)
    assert np.linalg.eigvalsh(gram).min() > -1e-5


def test_evaluation_poses():
    cfg = GPConfig(eval_grid=3)
    poses = np.asarray(gp.evaluation_poses(cfg))
    assert poses.shape == (4 * 27, 4)
    np.testing.assert_allclose(np.unique(poses[:, :3]), [1 / 6, 1 / 2, 5 / 6], rtol=1e-6)
    np.testing.assert_array_equal(poses[:4, 3], HEADING_ANGLES)
    assert len(np.unique(poses, axis=0)) == len(poses)
    assert float(gp.empty(cfg, poses).trace) == 4 * 27 * cfg.variance


@pytest.mark.parametrize("capacity", [16, 64])
def test_sequence_matches_dense_reference(capacity):
    """Checks after 1, H/2, H and H + 5 enabled adds, with disabled adds interleaved."""
    cfg = GPConfig(capacity=capacity)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(capacity)
    queries = random_poses(rng, 40)
    checkpoints = {1, capacity // 2, capacity, capacity + 5}
    state, inputs, targets = gp.empty(cfg, eval_poses), [], []
    assert_matches_reference(state, inputs, targets, queries, cfg, eval_poses)
    while len(inputs) < max(checkpoints):
        pose, value = random_poses(rng, 1)[0], rng.normal()
        enabled = rng.uniform() < 0.7
        state = add(state, pose, value, cfg, eval_poses, enabled)
        if not enabled:
            continue
        inputs.append(pose)
        targets.append(value)
        if len(inputs) in checkpoints:
            recent = slice(-capacity, None)  # full GPs keep the H most recent points
            assert_matches_reference(
                state, inputs[recent], targets[recent], queries, cfg, eval_poses
            )
    assert int(state.count) == len(inputs)
    assert sorted(np.asarray(state.stamp)) == list(range(len(inputs) - capacity, len(inputs)))


def test_long_run_with_duplicates_stays_accurate():
    """Many evictions, repeated and near-identical poses: no drift, NaN or negative variance."""
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(3)
    base = random_poses(rng, 6)
    poses = base[rng.integers(0, 6, 200)]
    poses[::3, :3] += rng.normal(0, 1e-4, (len(poses[::3]), 3)).astype(np.float32)
    values = rng.normal(size=200).astype(np.float32)
    state = _add_many(gp.empty(cfg, eval_poses), poses, values, cfg, eval_poses)
    queries = np.concatenate([base, random_poses(rng, 20)])
    assert_matches_reference(state, poses[-16:], values[-16:], queries, cfg, eval_poses)
    _, variance = _predict(state, queries, cfg)
    assert np.all(np.isfinite(variance)) and np.all((variance >= 0) & (variance <= cfg.variance))
    # The mean's weights are updated, never recomputed: they still equal R^T R y.
    root = np.asarray(state.root, np.float64)
    weights = root.T @ (root @ np.asarray(state.targets, np.float64))
    np.testing.assert_allclose(state.weights, weights, rtol=0, atol=1e-5 * np.abs(weights).max())


@pytest.mark.parametrize("points", [5, 19])  # filling, and full (the eviction path)
def test_disabled_add_leaves_state_bit_identical(points):
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(4)
    poses, values = random_poses(rng, points), rng.normal(size=points)
    state = _add_many(gp.empty(cfg, eval_poses), poses, values, cfg, eval_poses)
    after = add(state, random_poses(rng, 1)[0], 3.0, cfg, eval_poses, enabled=False)
    chex.assert_trees_all_equal(after, state)


def test_padded_slots_do_not_change_results():
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(5)
    state = _add_many(gp.empty(cfg, eval_poses), random_poses(rng, 7), rng.normal(size=7), cfg,
                      eval_poses)
    free = ~np.asarray(state.valid)
    garbage = state.replace(
        inputs=jnp.where(free[:, None], 1e3 * rng.normal(size=(16, 4)), state.inputs),
        features=jnp.where(free, 1e3 * rng.normal(size=(5, 16)), state.features),
        targets=jnp.where(free, 1e3 * rng.normal(size=16), state.targets),
        eval_cross=jnp.where(free[:, None], 1e3, state.eval_cross),
    )
    queries, pose = random_poses(rng, 30), random_poses(rng, 1)[0]
    after = [add(s, pose, 1.0, cfg, eval_poses) for s in (state, garbage)]
    for clean, dirty in [(state, garbage), after]:
        chex.assert_trees_all_equal(_predict(clean, queries, cfg), _predict(dirty, queries, cfg))
        assert gp.covariance_trace(clean) == gp.covariance_trace(dirty)


def test_add_many_equals_sequential_adds():
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(6)
    poses, values, enabled = random_poses(rng, 20), rng.normal(size=20), rng.uniform(size=20) < 0.8
    state = gp.empty(cfg, eval_poses)
    for p, v, e in zip(poses, values, enabled):
        state = add(state, p, v, cfg, eval_poses, e)
    many = _add_many(gp.empty(cfg, eval_poses), poses, values, cfg, eval_poses, enabled)
    chex.assert_trees_all_close(many, state, rtol=1e-6, atol=1e-6)


def test_vmap_over_a_batch_of_gps_matches_single_gps():
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(7)
    batch, steps = 3, 20
    poses = random_poses(rng, batch * steps).reshape(batch, steps, 4)
    values, enabled = rng.normal(size=(batch, steps)), rng.uniform(size=(batch, steps)) < 0.8
    queries = random_poses(rng, 10)
    states = jax.tree.map(lambda x: jnp.stack([x] * batch), gp.empty(cfg, eval_poses))
    add_batch = jax.jit(jax.vmap(lambda s, p, v, e: gp.add(s, p, v, cfg, eval_poses, e)))
    for t in range(steps):
        states = add_batch(states, poses[:, t], values[:, t], enabled[:, t])
    means, variances = jax.jit(jax.vmap(lambda s: gp.predict(s, queries, cfg)))(states)
    for i in range(batch):
        single = gp.empty(cfg, eval_poses)
        single = _add_many(single, poses[i], values[i], cfg, eval_poses, enabled[i])
        mean, variance = _predict(single, queries, cfg)
        np.testing.assert_allclose(means[i], mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(variances[i], variance, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(states.trace[i], single.trace, rtol=1e-6)


def test_add_and_predict_are_traced_once():
    cfg = GPConfig(capacity=8)
    eval_poses = gp.evaluation_poses(cfg)
    add_once = jax.jit(chex.assert_max_traces(gp.add, n=1), static_argnames="cfg")
    predict_once = jax.jit(chex.assert_max_traces(gp.predict, n=1), static_argnames="cfg")
    rng = np.random.default_rng(8)
    state = gp.empty(cfg, eval_poses)
    for i in range(15):  # fills, evicts and toggles enabled under one trace
        pose, value, enabled = random_poses(rng, 1)[0], np.float32(rng.normal()), np.bool_(i % 3)
        state = add_once(state, pose, value, cfg, eval_poses, enabled)
        predict_once(state, random_poses(rng, 5), cfg)
    assert int(state.count) == 10


_add_block = jax.jit(chex.assert_max_traces(gp.add_block, n=3), static_argnames="cfg")
_add_block_first_trace = jax.jit(gp.add_block_first_trace, static_argnames="cfg")


@pytest.mark.parametrize("filled", [5, 14, 30])  # filling, filling up mid-block, evicting
def test_block_equals_sequential_adds_and_the_dense_reference(filled):
    """One block of K points gives the state K single adds give (masked points skipped)."""
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(10 + filled)
    poses, values = random_poses(rng, filled), rng.normal(size=filled).astype(np.float32)
    state = gp.empty(cfg, eval_poses)
    for p, v in zip(poses, values):
        state = add(state, p, v, cfg, eval_poses)
    queries = random_poses(rng, 30)
    for enabled in ([True, True, True, True], [False, True, False, True], [True, False, True]):
        k = len(enabled)
        block_poses, block_values = random_poses(rng, k), rng.normal(size=k).astype(np.float32)
        sequential = state
        for p, v, e in zip(block_poses, block_values, enabled):
            sequential = add(sequential, p, v, cfg, eval_poses, e)
        block = _add_block(state, block_poses, block_values, cfg, eval_poses, np.array(enabled))
        # The first point's trace is what a lone add of it leaves, also when the block's
        # later points evict (filled = 14: some, 30: all of them).
        first = add(state, block_poses[0], block_values[0], cfg, eval_poses, enabled[0])
        tracked, first_trace = _add_block_first_trace(state, block_poses, block_values, cfg,
                                                      eval_poses, np.array(enabled))
        np.testing.assert_allclose(first_trace, first.trace, rtol=1e-5)
        np.testing.assert_allclose(tracked.trace, block.trace, rtol=1e-6)
        chex.assert_trees_all_equal(
            (block.valid, block.stamp, block.count, block.inputs, block.targets),
            (sequential.valid, sequential.stamp, sequential.count, sequential.inputs,
             sequential.targets))
        chex.assert_trees_all_close(_predict(block, queries, cfg),
                                    _predict(sequential, queries, cfg), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(block.trace, sequential.trace, rtol=1e-5)
        np.testing.assert_allclose(block.weights, sequential.weights, rtol=1e-4, atol=1e-4)
        valid = np.asarray(block.valid)
        assert_matches_reference(block, np.asarray(block.inputs)[valid],
                                 np.asarray(block.targets)[valid], queries, cfg, eval_poses)


def test_disabled_block_leaves_state_bit_identical():
    cfg = GPConfig(capacity=16)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(11)
    state = _add_many(gp.empty(cfg, eval_poses), random_poses(rng, 19), rng.normal(size=19),
                      cfg, eval_poses)
    after = _add_block(state, random_poses(rng, 3), np.ones(3, np.float32), cfg, eval_poses,
                       np.zeros(3, bool))
    chex.assert_trees_all_equal(after, state)


def test_block_eviction_reflections_triangularise_the_evicted_columns():
    """The evicting step of a block: Q = I - V T V^T is orthogonal, Q R_E vanishes outside
    the rows E it is mapped into, and T_E^-1 T_E^-T = A_EE^-1; disabled points get no slot."""
    cfg = GPConfig(capacity=8)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(12)
    state = _add_many(gp.empty(cfg, eval_poses), random_poses(rng, 10), rng.normal(size=10),
                      cfg, eval_poses)
    slots = evict.block_slots(state, jnp.array([True, False, True, True]), cfg.capacity)
    refl = evict.reflect_evicted(state.root, slots, cfg.capacity, 4)
    assert list(np.asarray(slots.slots)) == [2, cfg.capacity, 3, 4]  # count = 10, H = 8
    evicting = np.asarray(slots.evicting)
    assert list(evicting) == [True, False, True, True]
    v, t = np.asarray(refl.v_mat, np.float64), np.asarray(refl.t_mat, np.float64)
    q = np.eye(cfg.capacity) - v @ t @ v.T
    np.testing.assert_allclose(q.T @ q, np.eye(cfg.capacity), atol=1e-5)
    r_e = np.asarray(refl.evicted_cols, np.float64)
    outside = np.ones(cfg.capacity, bool)
    outside[[2, 3, 4]] = False
    np.testing.assert_allclose((q @ r_e)[outside], 0.0, atol=1e-5 * np.abs(r_e).max())
    a_ee = (r_e.T @ r_e)[np.ix_(evicting, evicting)]
    t_e_inv = np.asarray(refl.t_e_inv, np.float64)
    np.testing.assert_allclose(t_e_inv[np.ix_(evicting, evicting)]
                               @ t_e_inv[np.ix_(evicting, evicting)].T @ a_ee,
                               np.eye(3), atol=1e-3)
    np.testing.assert_array_equal(t_e_inv[1], np.eye(4)[1])  # identity for the disabled point


def test_block_larger_than_the_capacity_is_refused():
    cfg = GPConfig(capacity=4)
    eval_poses = gp.evaluation_poses(cfg)
    with pytest.raises(ValueError, match="capacity 4"):
        gp.add_block(gp.empty(cfg, eval_poses), np.zeros((5, 4), np.float32),
                     np.zeros(5, np.float32), cfg, eval_poses)
