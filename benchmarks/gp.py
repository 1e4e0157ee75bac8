"""GP feature step throughput: incremental updates against refactorising every step.

One step per GP = add one observation + predict mean and variance at L = 80 candidates +
the posterior covariance trace over the default evaluation set, for 1024 environments x
3 robots = 3,072 GPs at H = 64, filled to half capacity first, vmapped and jitted with
the state donated. The refactorising baseline does the same work from the same ring
buffer with a Cholesky factorisation and one triangular solve per GP and step. Both run in
this process, so their ratio is meaningful on a shared, noisy machine.

`gp.block_speedup_vs_adds` times the environment's radio rounds: three points added as
one `gp.add_block` against three single adds, on the same GPs in the same run.

Usage (from the repository root): python benchmarks/gp.py [--eval-grid 4]
"""

from __future__ import annotations

import itertools
import statistics
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import ArgumentParser, emit, entry_point, median_seconds  # noqa: E402

from jaxmripp.sim import gp  # noqa: E402
from jaxmripp.config import GPConfig  # noqa: E402
from jaxmripp.sim.geometry import HEADING_ANGLES  # noqa: E402

GPS, CANDIDATES, STEPS, ROUNDS = 1024 * 3, 80, 8, 7
BLOCK_POINTS = 3  # radio rounds per step for N = 3 robots (sim.feeding.feed_gps)


def random_poses(rng, *shape):
    headings = HEADING_ANGLES[rng.integers(0, len(HEADING_ANGLES), shape)]
    positions = rng.uniform(0, 1, (*shape, 3))
    return np.concatenate([positions, headings[..., None]], -1).astype(np.float32)


def incremental_step(states, poses, values, queries, eval_poses, cfg):
    states = jax.vmap(lambda s, p, v: gp.add(s, p, v, cfg, eval_poses))(states, poses, values)
    mean, variance = jax.vmap(lambda s, q: gp.predict(s, q, cfg))(states, queries)
    return states, (mean, variance, jax.vmap(gp.covariance_trace)(states))


def block_step(states, poses, values, eval_poses, cfg):
    states = jax.vmap(lambda s, p, v: gp.add_block(s, p, v, cfg, eval_poses))(states, poses, values)
    return states, states.trace


def adds_step(states, poses, values, eval_poses, cfg):
    def one(state, pose_values):
        return jax.lax.scan(
            lambda s, pv: (gp.add(s, pv[0], pv[1], cfg, eval_poses), None), state, pose_values)[0]

    states = jax.vmap(one)(states, (poses, values))
    return states, states.trace


def _refactor_one(buffer, pose, value, queries, eval_poses, cfg):
    """Writes the point into the ring buffer, then factorises K + noise I from scratch.

    The buffer keeps the kernel features of its inputs, as the incremental GP does.
    """
    features, targets, valid, count = buffer
    slot = count % cfg.capacity
    features = features.at[:, slot].set(gp.pose_features(pose, cfg))
    targets, valid = targets.at[slot].set(value), valid.at[slot].set(True)
    both_valid = valid[:, None] & valid[None, :]
    gram = jnp.where(both_valid, gp.feature_kernel(features, features, cfg), 0.0)
    chol = jnp.linalg.cholesky(gram + jnp.diag(jnp.where(valid, cfg.noise, 1.0)))
    # Materialised, as in gp.kernel, so XLA does not redo cos and sin for every pair.
    points = jax.lax.optimization_barrier(
        gp.pose_features(jnp.concatenate([queries, eval_poses]), cfg))
    rhs = jnp.concatenate([gp.feature_kernel(features, points, cfg), targets[:, None]], axis=1)
    solved = solve_triangular(chol, jnp.where(valid[:, None], rhs, 0.0), lower=True)
    at_queries, at_eval = solved[:, : len(queries)], solved[:, len(queries) : -1]
    mean = jnp.sum(at_queries * solved[:, -1:], axis=0)  # no batched matvec: see gp.linalg.matvec
    variance = jnp.clip(cfg.variance - jnp.sum(at_queries**2, axis=0), 0.0, cfg.variance)
    trace = len(eval_poses) * cfg.variance - jnp.sum(at_eval**2)
    return (features, targets, valid, count + 1), (mean, variance, trace)


def refactor_step(buffers, poses, values, queries, eval_poses, cfg):
    one = lambda b, p, v, q: _refactor_one(b, p, v, q, eval_poses, cfg)  # noqa: E731
    return jax.vmap(one)(buffers, poses, values, queries)


def runner(step, state, inputs, eval_poses, cfg):
    """A no-argument step that feeds its donated state back in, and its first outputs."""
    step = jax.jit(step, static_argnames="cfg", donate_argnums=0)
    holder, cycle = {"state": state}, itertools.cycle(inputs)

    def run():
        holder["state"], out = step(holder["state"], *next(cycle), eval_poses, cfg)
        return out

    return run, jax.device_get(run())


@entry_point
def main():
    parser = ArgumentParser(description=__doc__)
    parser.add_argument("--eval-grid", type=int, default=GPConfig().eval_grid,
                        help="trace evaluation set: eval_grid^3 positions x 4 headings")
    cfg = GPConfig(eval_grid=parser.parse_args().eval_grid)
    eval_poses = gp.evaluation_poses(cfg)
    rng = np.random.default_rng(0)

    def observations(*shape):
        return random_poses(rng, *shape), rng.normal(size=shape).astype(np.float32)

    empty = gp.empty(cfg, eval_poses)
    empty = jax.tree.map(lambda x: jnp.broadcast_to(x, (GPS, *x.shape)), empty)
    fill = jax.jit(jax.vmap(lambda s, p, v: gp.add_many(s, p, v, cfg, eval_poses)))
    states = fill(empty, *observations(GPS, cfg.capacity // 2))
    buffers = jax.tree.map(jnp.copy, (states.features, states.targets, states.valid, states.count))
    block_states, adds_states = jax.tree.map(jnp.copy, states), jax.tree.map(jnp.copy, states)
    inputs = [(*observations(GPS), random_poses(rng, GPS, CANDIDATES)) for _ in range(STEPS)]

    run_inc, out_inc = runner(incremental_step, states, inputs, eval_poses, cfg)
    run_ref, out_ref = runner(refactor_step, buffers, inputs, eval_poses, cfg)
    for a, b in zip(out_inc, out_ref):  # the same work: the first steps agree
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3)

    # Alternate short rounds so that both see the same load on a shared machine.
    rounds = [(median_seconds(run_inc, 3), median_seconds(run_ref, 3)) for _ in range(ROUNDS)]
    incremental = statistics.median(inc for inc, _ in rounds)
    refactor = statistics.median(ref for _, ref in rounds)
    speedup = statistics.median(ref / inc for inc, ref in rounds)

    shape = dict(gps=GPS, capacity=cfg.capacity, candidates=CANDIDATES, eval_poses=len(eval_poses))
    emit("gp.step_per_s", GPS / incremental, "GP steps/s", **shape, ms_per_batch=1e3 * incremental)
    emit("gp.speedup_vs_refactor", speedup, "x", **shape, refactor_step_per_s=GPS / refactor)

    # The environment's radio rounds: BLOCK_POINTS points as one block vs one add each.
    block_inputs = [observations(GPS, BLOCK_POINTS) for _ in range(STEPS)]
    run_block, _ = runner(block_step, block_states, block_inputs, eval_poses, cfg)
    run_adds, _ = runner(adds_step, adds_states, block_inputs, eval_poses, cfg)
    rounds = [(median_seconds(run_block, 3), median_seconds(run_adds, 3)) for _ in range(ROUNDS)]
    emit("gp.block_speedup_vs_adds", statistics.median(a / b for b, a in rounds), "x",
         gps=GPS, capacity=cfg.capacity, points=BLOCK_POINTS,
         block_ms=1e3 * statistics.median(b for b, _ in rounds),
         adds_ms=1e3 * statistics.median(a for _, a in rounds))


if __name__ == "__main__":
    sys.exit(main())
