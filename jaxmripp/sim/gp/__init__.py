"""Fixed-capacity Gaussian processes over poses, updated incrementally.

A GP holds at most H observations in a ring buffer together with a square root R of the
inverse kernel matrix, R^T R = (K + noise I)^-1 over its valid slots (for points added in
order, R = L^-1 with L the Cholesky factor). Rows and columns of R for free slots are
exactly zero, so padding drops out of every matmul. Adding a point appends one row to R,
evicting the oldest point applies one Householder reflection: O(H^2) each, no
factorisation and no sequential loops on the hot path (`single.add`). The mean's weights
A y follow both steps in O(H), so prediction is one matmul and one matrix-vector product
rather than two more reads of R for R^T (R y). Updated weights drift a little more than
recomputed ones: after 3,000 adds of six near-duplicate poses at H = 64 the mean is off
by about 1e-3 instead of 2e-4 (posterior means are O(1)); on distinct poses, 3e-6.
Variances are prior minus a sum of squares, which keeps float32 as accurate as a fresh
Cholesky solve; an explicit inverse (entries up to 1/noise, variance = prior - k^T A k)
loses two more digits on near-duplicate poses.

Several points can go in as one block (`block.add_block`): K Householder reflections in
compact WY form evict, and a K-row border inserts, with R read three times and written
once for the whole block.

The reward needs the trace of the posterior covariance over a fixed set E of M poses.
Each update changes every posterior variance on E by a rank-one term, computed from the
cached cross-covariances C = k(inputs, E) in one read of C; the new point writes one row
of C. The trace is thus kept up to date in O(H^2 + H M) per point, instead of O(H^2 M)
to recompute it, and C (the largest array, H x M) is never rewritten as a whole.

The kernel (Matern-1/2 over poses, the heading placed on a circle) is in `state`.
Everything is float32; noise >= 1e-6 (validated in config) bounds the condition number
of K + noise I by 1 + H variance / noise, and variances are clamped to [0, variance].
All functions act on one GP; batch them with `jax.vmap` (eval poses unbatched) and pass
the `GPConfig` as a static argument.

Modules: `state` (GPState, kernel, evaluation set), `linalg` (small dense helpers),
`single` (one-point add), `evict` and `block` (block add, add_many), `predict`.
"""

from jaxmripp.sim.gp.block import BLOCK, add_block, add_block_first_trace, add_many
from jaxmripp.sim.gp.predict import cross_covariance, predict, predict_projected
from jaxmripp.sim.gp.single import add
from jaxmripp.sim.gp.state import (
    GPState,
    covariance_trace,
    empty,
    evaluation_poses,
    feature_kernel,
    kernel,
    pose_features,
)

__all__ = [
    "BLOCK",
    "GPState",
    "add",
    "add_block",
    "add_block_first_trace",
    "add_many",
    "covariance_trace",
    "cross_covariance",
    "empty",
    "evaluation_poses",
    "feature_kernel",
    "kernel",
    "pose_features",
    "predict",
    "predict_projected",
]
