"""Fixed-capacity Gaussian processes over poses, updated incrementally.

A GP holds at most H observations in a ring buffer together with a square root R of the
inverse kernel matrix, R^T R = (K + noise I)^-1 over its valid slots (for points added in
order, R = L^-1 with L the Cholesky factor). Rows and columns of R for free slots are
exactly zero, so padding drops out of every matmul. Adding a point appends one row to R,
evicting the oldest point applies one Householder reflection: O(H^2) each, no
factorisation and no sequential loops on the hot path (see `add`). The mean's weights
A y follow both steps in O(H), so prediction is one matmul and one matrix-vector product
(recomputing R^T (R y) read R twice more: a quarter of `predict`; recomputing them in
`add`'s passes over R made a GP step 30% slower). Updated weights drift a little more
than recomputed ones: after 3,000 adds of six near-duplicate poses at H = 64 the mean
is off by 1.3e-3 instead of 2e-4 (posterior means are O(1)); on distinct poses, 3e-6.
Variances are prior minus a sum of squares, which keeps float32 as accurate as a fresh
Cholesky solve; an explicit inverse (entries up to 1/noise, variance =
prior - k^T A k) lost two more digits on near-duplicate poses.

Several points can go in as one block (`add_block`): K Householder reflections in
compact WY form evict, and a K-row border inserts, with R read three times and written
once for the whole block. The environment feeds each GP its peers' poses this way (one
block a step instead of one add per radio round: a block of three took 48 ms against
63 ms for three adds on 3,072 GPs, `benchmarks/gp.py` on XLA:CPU).

The reward needs the trace of the posterior covariance over a fixed set E of M poses.
Each update changes every posterior variance on E by a rank-one term, computed from the
cached cross-covariances C = k(inputs, E) in one read of C; the new point writes one row
of C. The trace is thus kept up to date in O(H^2 + H M) per point, instead of O(H^2 M)
to recompute it, and C (the largest array, H x M) is never rewritten as a whole.

Kernel: Matern-1/2 over poses, k = variance exp(-d / length_scale), zero prior mean, with
d^2 = |dp|^2 + (heading_scale * 2 sin(dtheta / 2))^2: the Euclidean distance after
placing the heading on a circle of radius heading_scale, so k is positive definite
(Matern-1/2 is, in any dimension). The wrapped arc length |dtheta| in [0, pi] in place of
the chord is not: arc^2 is not conditionally negative definite on the circle, and with
length_scale >= 0.5 random pose sets give K with eigenvalues far below -noise (negative
variances). Chord and arc agree to first order: a quarter turn counts 1.41 heading_scale
instead of 1.57, a half turn 2 instead of 3.14.

Everything is float32; noise >= 1e-6 (validated in config) bounds the condition number
of K + noise I by 1 + H variance / noise, and variances are clamped to [0, variance].
All functions act on one GP; batch them with `jax.vmap` (eval poses unbatched) and pass
the `GPConfig` as a static argument.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxmripp.config import GPConfig
from jaxmripp.sim.geometry import HEADING_ANGLES


@struct.dataclass
class GPState:
    """One GP; H = GPConfig.capacity, M = number of evaluation poses."""

    inputs: jax.Array  # (H, 4) f32 poses (x, y, z, heading angle); zeros in free slots
    features: jax.Array  # (5, H) f32 `pose_features` of inputs, kept so no step redoes cos/sin
    targets: jax.Array  # (H,) f32 observed values; zeros in free slots
    weights: jax.Array  # (H,) f32 A y = R^T R targets, the mean's weights; zeros in free slots
    valid: jax.Array  # (H,) bool slot holds an observation
    root: jax.Array  # (H, H) f32 R, R^T R = (K + noise I)^-1 over valid slots, zero elsewhere
    stamp: jax.Array  # (H,) int32 insertion index of the slot's point, -1 when free
    count: jax.Array  # () int32 points ever added (enabled adds only)
    eval_cross: jax.Array  # (H, M) f32 k(inputs, eval_poses); rows of free slots unused
    trace: jax.Array  # () f32 posterior variance summed over the eval poses


def pose_features(poses: jax.Array, cfg: GPConfig) -> jax.Array:
    """(..., N, 4) poses -> (5, ..., N): x, y, z and the heading on a circle of radius hs.

    Coordinates come first so that each term of the distance in `kernel` is a contiguous
    (A, B) sweep, which XLA fuses and vectorises (a trailing size-5 axis does neither).
    XLA:CPU calls scalar libm for cos and sin, so the GP stores the features of its inputs
    (measured: recomputing them took a sixth of an add + predict step).
    """
    angle = poses[..., 3]
    x, y, z = poses[..., 0], poses[..., 1], poses[..., 2]
    hs = cfg.heading_scale
    return jnp.stack([x, y, z, hs * jnp.cos(angle), hs * jnp.sin(angle)])


def _float32_matmuls(fn):
    """Runs fn with full-precision float32 matmuls (a no-op on CPU).

    Variances are O(1) quantities minus sums of squares that reach the noise level;
    the TF32 or bfloat16 passes accelerators use for float32 by default would not
    resolve them.
    """

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


def _matvec(matrix: jax.Array, vector: jax.Array) -> jax.Array:
    """matrix (A, B) @ vector (B,) as a multiply and a row sum.

    Under vmap a matrix-vector product becomes a batched dot with one output column,
    which XLA:CPU runs as a slow per-batch loop (measured: the two in `predict` cost as
    much as its (L, H) x (H, H) matmul); the multiply-reduce form fuses and vectorises.
    """
    return jnp.sum(matrix * vector, axis=-1)


def _vecmat(vector: jax.Array, matrix: jax.Array) -> jax.Array:
    """vector (A,) @ matrix (A, B) as a multiply and a column sum (see `_matvec`)."""
    return jnp.sum(vector[:, None] * matrix, axis=0)


def kernel(a: jax.Array, b: jax.Array, cfg: GPConfig) -> jax.Array:
    """Matern-1/2 covariance between pose sets: (..., A, 4), (..., B, 4) -> (..., A, B)."""
    return feature_kernel(_materialised_features(a, cfg), _materialised_features(b, cfg), cfg)


def _materialised_features(poses: jax.Array, cfg: GPConfig) -> jax.Array:
    # The barrier keeps XLA from fusing cos and sin into the (A, B) loop of the kernel,
    # where they would be recomputed for every pair (measured 2-4x slower on CPU).
    return jax.lax.optimization_barrier(pose_features(poses, cfg))


def feature_kernel(fa: jax.Array, fb: jax.Array, cfg: GPConfig) -> jax.Array:
    """`kernel` on `pose_features`: (5, ..., A), (5, ..., B) -> (..., A, B)."""
    # Differences, not |a|^2 + |b|^2 - 2 a.b: near-duplicate poses must keep k ~ variance.
    dist2 = sum((fa[c][..., :, None] - fb[c][..., None, :]) ** 2 for c in range(len(fa)))
    return cfg.variance * jnp.exp(-jnp.sqrt(dist2) / cfg.length_scale)


def evaluation_poses(cfg: GPConfig) -> jax.Array:
    """The fixed trace evaluation set: (M, 4), M = 4 eval_grid^3.

    Positions are the cell centres of an eval_grid^3 grid over the unit cube (x slowest),
    each repeated for the four headings of `geometry.HEADING_ANGLES`.
    """
    centres = (np.arange(cfg.eval_grid, dtype=np.float32) + 0.5) / cfg.eval_grid
    grid = np.stack(np.meshgrid(centres, centres, centres, indexing="ij"), axis=-1)
    positions = np.repeat(grid.reshape(-1, 3), len(HEADING_ANGLES), axis=0)
    angles = np.tile(HEADING_ANGLES, len(grid.reshape(-1, 3)))[:, None]
    return jnp.asarray(np.concatenate([positions, angles], axis=1), dtype=jnp.float32)


def empty(cfg: GPConfig, eval_poses: jax.Array) -> GPState:
    """A GP with no observations: the trace is the prior one, M * variance."""
    h, m = cfg.capacity, eval_poses.shape[0]
    return GPState(
        inputs=jnp.zeros((h, 4), jnp.float32),
        features=jnp.zeros((5, h), jnp.float32),
        targets=jnp.zeros((h,), jnp.float32),
        weights=jnp.zeros((h,), jnp.float32),
        valid=jnp.zeros((h,), bool),
        root=jnp.zeros((h, h), jnp.float32),
        stamp=jnp.full((h,), -1, jnp.int32),
        count=jnp.zeros((), jnp.int32),
        eval_cross=jnp.zeros((h, m), jnp.float32),
        trace=jnp.asarray(m * cfg.variance, jnp.float32),
    )


@_float32_matmuls
def add(
    state: GPState,
    pose: jax.Array,
    value: jax.Array,
    cfg: GPConfig,
    eval_poses: jax.Array,
    enabled: jax.Array | bool = True,
) -> GPState:
    """Adds the observation (pose (4,), value ()); when the GP is full the oldest goes first.

    Points are written to slot j = count % H, which is free while count < H and
    otherwise holds the oldest point (the ring buffer evicts first-in, first-out).
    Rows of R are indexed by slot too; A = R^T R = (K + noise I)^-1, C = eval_cross.

    - evict j: a Householder reflection Q maps column j of R, r, onto e_j. Dropping row j
      of QR leaves R'^T R' = A - a a^T / a_jj (a = A e_j = R^T r, a_jj = |r|^2), the
      inverse over the remaining points. Each eval variance rises by (a^T C)_m^2 / a_jj.
      While slot j is free, r = 0 and this is skipped. The weights w = A y lose
      a (a^T y) / a_jj, which zeroes w_j.
    - insert at j: k = k(inputs, x) over valid slots, l = R k, s = k(x, x) + noise - |l|^2
      (the predictive variance of y at x, >= noise), b = R^T l = A k. The bordered
      inverse [[A + b b^T / s, -b / s], [-b^T / s, 1 / s]] is R'^T R' for R plus the row
      (e_j - b) / sqrt(s) (b_j = 0: column j of R is zero). Each eval variance drops by
      g_m^2 / s, g = k(x, E) - b^T C the posterior covariance between x and E. The
      weights gain (e_j - b) (value - b^T y) / s: the innovation over its variance.

    Both steps cost O(H^2 + H M). `enabled` may be a traced bool: when False the state is
    returned unchanged (bit for bit), so callers can add a fixed number of points per step.
    """
    h, m = cfg.capacity, eval_poses.shape[0]
    x = jnp.asarray(pose, jnp.float32)
    value = jnp.asarray(value, jnp.float32)
    x_features = pose_features(x[None], cfg)  # (5, 1)
    eval_features = _materialised_features(eval_poses, cfg)
    slot = state.count % h
    at_slot = jnp.arange(h) == slot
    others = ~at_slot
    occupied = state.valid[slot]

    # Evict the point in the slot: v = r + sign(r_j) |r| e_j avoids cancellation. The
    # reflected factor is R - c v w^T (c = 2 / |v|^2, w = R^T v = a + sign |r| R[j]), with
    # row and column j zeroed. It is never formed before the end: l and b below are
    # expanded around R so that R is read three times (R^T r with R k, R^T l, and the
    # final write) instead of once per product on the reflected copy.
    r = state.root[:, slot]
    valid = state.valid & others
    k = jnp.where(valid, feature_kernel(x_features, state.features, cfg)[0], 0.0)
    a, root_k = _vecmat(r, state.root), _matvec(state.root, k)
    r_norm2 = jnp.sum(r**2)
    a_jj = jnp.where(occupied, r_norm2, 1.0)
    v_j = jnp.where(r[slot] < 0, -1.0, 1.0) * jnp.sqrt(r_norm2)
    v = r + v_j * at_slot
    c = 2.0 / jnp.where(occupied, jnp.sum(v**2), 1.0)
    w = a + v_j * state.root[slot]

    # Insert the new point into the same slot: l = R' k, b = R'^T l on the reflected R'.
    l = jnp.where(others, root_k - c * v * jnp.dot(w, k), 0.0)
    s = jnp.maximum(cfg.variance + cfg.noise - jnp.sum(l**2), cfg.noise)
    b = jnp.where(others, _vecmat(l, state.root) - c * w * jnp.dot(v, l), 0.0)
    reflected = state.root - jnp.outer(c * v, w)

    y = state.targets
    evicted_weights = state.weights - a * (jnp.dot(a, y) / a_jj)  # a = 0 while j is free
    innovation = value - jnp.dot(b, y)  # value minus the prior-to-insert mean at x
    weights = evicted_weights + (at_slot - b) * (innovation / s)
    root = jnp.where(
        at_slot[:, None],
        (at_slot - b) / jnp.sqrt(s),
        jnp.where(others[None, :], reflected, 0.0),  # exact zeros in column j
    )

    # Write the new row of C first, then one pass over C gives both trace terms (a and b
    # stacked: measured 10% faster env steps than two passes over C). b_j = 0
    # ignores row j; a^T C needs the evicted point's row, recomputed from its pose. Writing
    # before reading lets XLA update C in place; read-then-write made it copy C twice.
    cross = feature_kernel(x_features, eval_features, cfg)[0]
    eval_cross = state.eval_cross.at[slot].set(
        jnp.where(enabled, cross, state.eval_cross[slot])
    )
    evicted = feature_kernel(state.features[:, slot, None], eval_features, cfg)[0]
    a_c, b_c = jnp.sum(jnp.stack([a, b])[:, :, None] * eval_cross, axis=1)
    a_c = a_c + a[slot] * (evicted - cross)
    rise = jnp.where(occupied, jnp.sum(a_c**2) / a_jj, 0.0)
    trace = state.trace + rise - jnp.sum((cross - b_c) ** 2) / s

    added = GPState(
        inputs=state.inputs.at[slot].set(x),
        features=state.features.at[:, slot].set(x_features[:, 0]),
        targets=state.targets.at[slot].set(value),
        weights=weights,
        valid=valid | at_slot,
        root=root,
        stamp=state.stamp.at[slot].set(state.count),
        count=state.count + 1,
        eval_cross=eval_cross,
        trace=jnp.clip(trace, 0.0, m * cfg.variance),  # float32 drift stays in range
    )
    current = state.replace(eval_cross=eval_cross)  # already masked: passes through
    return jax.tree.map(lambda new, old: jnp.where(enabled, new, old), added, current)


def _lower_cholesky(matrix: jax.Array, floor: float) -> jax.Array:
    """Cholesky factor of a small (K, K) SPD matrix, unrolled, pivots clamped to >= floor.

    K is a handful of points: an unrolled factorisation fuses, where XLA:CPU's batched
    Cholesky runs a LAPACK call per matrix. The clamp plays the part of `add`'s
    s >= noise: each pivot is a predictive variance of y given the points before it.
    """
    k = matrix.shape[0]
    factor = [[jnp.zeros((), matrix.dtype)] * k for _ in range(k)]
    for i in range(k):
        pivot = matrix[i, i] - sum(factor[i][p] ** 2 for p in range(i))
        factor[i][i] = jnp.sqrt(jnp.maximum(pivot, floor))
        for j in range(i + 1, k):
            off = matrix[j, i] - sum(factor[j][p] * factor[i][p] for p in range(i))
            factor[j][i] = off / factor[i][i]
    return jnp.stack([jnp.stack(row) for row in factor])


def _lower_inverse(lower: jax.Array) -> jax.Array:
    """Inverse of a small (K, K) lower-triangular matrix, unrolled forward substitution."""
    k = lower.shape[0]
    inverse = [[jnp.zeros((), lower.dtype)] * k for _ in range(k)]
    for i in range(k):
        inverse[i][i] = 1.0 / lower[i, i]
        for j in range(i):
            inverse[i][j] = -sum(lower[i, p] * inverse[p][j] for p in range(j, i)) / lower[i, i]
    return jnp.stack([jnp.stack(row) for row in inverse])


def _small_dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """a (P, K) @ b (K, Q) for a handful of points K, as K fused outer products.

    XLA:CPU runs each tiny batched dot as its own kernel (measured: (64, 3) x (3, 3) over
    3,072 GPs 14x slower as a dot than unrolled).
    """
    return sum(a[:, i, None] * b[None, i, :] for i in range(a.shape[1]))


def _gram(a: jax.Array, b: jax.Array) -> jax.Array:
    """a^T b for a (H, P), b (H, Q): a contraction over the slots."""
    return jnp.einsum("hp,hq->pq", a, b)


def add_block(
    state: GPState,
    poses: jax.Array,
    values: jax.Array,
    cfg: GPConfig,
    eval_poses: jax.Array,
    enabled: jax.Array | None = None,
) -> GPState:
    """Adds K observations (poses (K, 4), values (K,)) at once; see `add_block_first_trace`
    (XLA drops the first point's trace when it is not used)."""
    return add_block_first_trace(state, poses, values, cfg, eval_poses, enabled)[0]


@_float32_matmuls
def add_block_first_trace(
    state: GPState,
    poses: jax.Array,
    values: jax.Array,
    cfg: GPConfig,
    eval_poses: jax.Array,
    enabled: jax.Array | None = None,
) -> tuple[GPState, jax.Array]:
    """Adds K observations (poses (K, 4), values (K,)) at once, skipping disabled ones.

    Returns the new state and the trace a single `add` of the first point would have left
    (the state's trace when the first point is disabled): the environment feeds each
    robot's own pose and its peers' as one block and still gets the own pose's trace
    drop, its exploration reward, exactly.

    The result is the state K sequential `add`s would give (the same slots, stamps,
    first-in first-out evictions, posterior and trace, to float32 rounding) at about the
    cost of one add: R is read three times and written once per block, not per point.

    With J the slots the enabled points take (count, count + 1, ... mod H) and E those of
    them that hold a point now:
    - evict E: Householder reflections Q = I - V T V^T (compact WY form, built from the
      columns R_E alone) map R_E into rows E; dropping rows E of QR leaves the inverse
      over the remaining points. T_E, the reflected R_E in rows E, is upper triangular
      with T_E^T T_E = A_EE. The eval variances rise by |T_E^-T A_E^T C|^2 summed
      (A_E = R^T R_E, C = eval_cross) and the weights lose A_E A_EE^-1 w_E.
    - insert at J: with Kx = k(inputs, X) over the remaining points, L = R' Kx,
      S = k(X, X) + noise I - L^T L (the predictive covariance of y at X), S^-1 = W^T W
      and B = R'^T L = A' Kx, the new rows are W (E_J - B)^T. The eval variances drop by
      |W G|^2 summed, G = k(X, E) - B^T C, and the weights gain
      (E_J - B) S^-1 (values - B^T y).
    R is read for R Kx, for R^T [Q^T L, V, R_E] (one product) and for the final write.

    The first point's own trace change, from quantities the block has anyway (O(K M)):
    its eviction is row 0 of the rise (the evictions are taken in order), but its
    insertion above is conditioned on the kept points S only, while a lone add of it would
    also keep the block's later evictions F. The posterior of y_E given S is
    Sigma_EE = A_EE^-1 with cross-covariances A_EE^-1 A_E^T C to E, so conditioning x's
    predictive variance s and covariance g with E on F as well is one more Schur
    complement: s - c Sigma_FF^-1 c^T and g - c Sigma_FF^-1 G_F, c = k(x, F) - b^T k(S, F).
    """
    h, m, k = cfg.capacity, eval_poses.shape[0], poses.shape[0]
    if k > h:
        raise ValueError(f"add_block: got {k} points for a GP of capacity {h}; allowed: <= {h}")
    x = jnp.asarray(poses, jnp.float32)
    values = jnp.asarray(values, jnp.float32)
    enabled = jnp.ones((k,), bool) if enabled is None else jnp.asarray(enabled, bool)
    x_features = _materialised_features(x, cfg)  # (5, K)
    eval_features = _materialised_features(eval_poses, cfg)

    rank = jnp.cumsum(enabled) - 1
    slots = jnp.where(enabled, (state.count + rank) % h, h)  # h: no slot, writes dropped
    in_slot = jnp.arange(h)[:, None] == slots[None, :]  # (H, K) E_J; zero columns if disabled
    in_block = jnp.any(in_slot, axis=1)
    clipped = jnp.minimum(slots, h - 1)
    evicting = enabled & state.valid[clipped]  # (K,)
    remaining = state.valid & ~in_block  # the points the block keeps
    root = state.root

    # Householder reflections of R_E, one column at a time (O(K^2 H) on (H, K) data).
    evicted_cols = jnp.where(evicting[None, :], root[:, clipped], 0.0)  # R_E (H, K)
    cols, pivoted = evicted_cols, jnp.zeros((h,), bool)
    vs, taus = [], []
    for i in range(k):
        pivot = in_slot[:, i] & evicting[i]
        col = jnp.where(pivoted, 0.0, cols[:, i])
        sign = jnp.where(col[clipped[i]] < 0, -1.0, 1.0)
        v = col + sign * jnp.sqrt(jnp.sum(col**2)) * pivot
        v_norm2 = jnp.sum(v**2)
        tau = jnp.where(evicting[i] & (v_norm2 > 0), 2.0 / jnp.maximum(v_norm2, 1e-30), 0.0)
        cols = cols - tau * v[:, None] * _vecmat(v, cols)[None, :]
        vs.append(v)
        taus.append(tau)
        pivoted = pivoted | pivot
    v_mat = jnp.stack(vs, axis=1)  # (H, K)
    # Q = H_K ... H_1 = I - V T V^T with T lower triangular, row by row:
    # T_i = [[T_{i-1}, 0], [-tau_i v_i^T V_{<i} T_{i-1}, tau_i]].
    v_gram = _gram(v_mat, v_mat)
    t_rows = [jnp.zeros((k,)).at[0].set(taus[0])]
    for i in range(1, k):
        coupling = -taus[i] * _small_dot(v_gram[i, None, :i], jnp.stack(t_rows))[0]
        t_rows.append(coupling.at[i].set(taus[i]))
    t_mat = jnp.stack(t_rows)
    both_evicting = evicting[:, None] & evicting[None, :]
    t_e = jnp.where(both_evicting, cols[clipped], 0.0) + jnp.diag(jnp.where(evicting, 0.0, 1.0))
    t_e_inv = _lower_inverse(t_e.T).T  # identity rows / columns where nothing is evicted

    # Border: L = R' Kx over the remaining points, S, its Cholesky factor and W = Ls^-1.
    kx = feature_kernel(state.features, x_features, cfg)  # (H, K)
    kx = jnp.where(remaining[:, None] & enabled[None, :], kx, 0.0)
    root_kx = jnp.einsum("ij,jk->ik", root, kx)  # R Kx
    l_mat = root_kx - _small_dot(v_mat, _small_dot(t_mat, _gram(v_mat, root_kx)))  # Q R Kx
    l_mat = jnp.where(remaining[:, None], l_mat, 0.0)
    kxx = feature_kernel(x_features, x_features, cfg)
    s_mat = jnp.where(enabled[:, None] & enabled[None, :], kxx, 0.0) \
        + jnp.diag(jnp.where(enabled, cfg.noise, 1.0)) - _gram(l_mat, l_mat)
    w_mat = _lower_inverse(_lower_cholesky(s_mat, cfg.noise))  # W^T W = S^-1

    # One pass over R: R^T Q^T L (-> B), V^T R (-> QR) and A_E = R^T R_E, slot-major.
    z_mat = l_mat - _small_dot(v_mat, _small_dot(t_mat.T, _gram(v_mat, l_mat)))  # Q^T L
    rhs = jnp.concatenate([z_mat, v_mat, evicted_cols], axis=1).T  # (3K, H)
    projected = jnp.sum(rhs[:, :, None] * root[None], axis=1)  # (3K, H)
    b_mat = jnp.where(remaining[:, None], projected[:k].T, 0.0)  # (H, K) A' Kx
    a_e = projected[2 * k :].T  # (H, K), zero columns where nothing is evicted

    # The write: rank-K terms as outer products and row selects fuse into one pass (a
    # (H, K) x (K, H) dot would be materialised first).
    new_rows = _small_dot(w_mat, in_slot.T.astype(jnp.float32) - b_mat.T)  # (K, H)
    reflected = root - _small_dot(v_mat, _small_dot(t_mat, projected[k : 2 * k]))
    root = jnp.where(remaining[:, None] & remaining[None, :], reflected, 0.0)
    for i in range(k):
        root = jnp.where(in_slot[:, i, None], new_rows[i][None, :], root)

    # Weights: evict (w - A_E A_EE^-1 w_E), then insert ((E_J - B) S^-1 innovation).
    y = jnp.where(remaining, state.targets, 0.0)
    w_e = jnp.where(evicting, state.weights[clipped], 0.0)
    a_ee_inv_w = _small_dot(t_e_inv, _small_dot(t_e_inv.T, w_e[:, None]))
    evicted_weights = jnp.where(remaining, state.weights - _small_dot(a_e, a_ee_inv_w)[:, 0], 0.0)
    innovation = jnp.where(enabled, values - _gram(b_mat, y[:, None])[:, 0], 0.0)
    s_inv_innovation = _small_dot(w_mat.T, _small_dot(w_mat, innovation[:, None]))
    weights = evicted_weights + _small_dot(in_slot - b_mat, s_inv_innovation)[:, 0]

    # Trace: write the new rows of C, then one pass over C for A_E^T C and B^T C; the
    # evicted points' rows of C are recomputed from their poses.
    cross = feature_kernel(x_features, eval_features, cfg)  # (K, M)
    eval_cross = state.eval_cross.at[slots].set(cross, mode="drop")
    ab = jnp.concatenate([a_e, b_mat], axis=1).T  # (2K, H)
    a_c, b_c = jnp.split(jnp.sum(ab[:, :, None] * eval_cross[None], axis=1), 2)
    evicted_features = state.features[:, clipped]  # (5, K)
    evicted_cross = feature_kernel(evicted_features, eval_features, cfg)  # (K, M)
    a_at_slots = jnp.where(enabled[:, None], a_e[clipped], 0.0)  # (K, K) rows J of A_E
    a_c = a_c + _small_dot(a_at_slots.T, jnp.where(enabled[:, None], evicted_cross - cross, 0.0))
    rise = jnp.sum(_small_dot(t_e_inv.T, a_c) ** 2)
    gain = jnp.where(enabled[:, None], cross - b_c, 0.0)  # G, (K, M)
    drop = jnp.sum(_small_dot(w_mat, gain) ** 2)

    # The first point as a lone add would see it (see the docstring); T_E^-T is lower
    # triangular, so row 0 of the rise is its own eviction.
    later = evicting & (jnp.arange(k) > 0)  # F
    both_later = later[:, None] & later[None, :]
    sigma_ee = _small_dot(t_e_inv, t_e_inv.T)  # A_EE^-1
    w_f = _lower_inverse(_lower_cholesky(
        jnp.where(both_later, sigma_ee, 0.0) + jnp.diag(jnp.where(later, 0.0, 1.0)), cfg.noise))
    c_f = feature_kernel(x_features[:, :1], evicted_features, cfg)[0] \
        - _gram(b_mat[:, :1], feature_kernel(state.features, evicted_features, cfg))[0]
    u = _small_dot(w_f, jnp.where(later, c_f, 0.0)[:, None])  # (K, 1)
    g_f = _small_dot(w_f, jnp.where(later[:, None], _small_dot(sigma_ee, a_c), 0.0))
    s_first = jnp.maximum(s_mat[0, 0] - jnp.sum(u**2), cfg.noise)
    drop_first = jnp.sum((gain[0] - _small_dot(u.T, g_f)[0]) ** 2) / s_first
    rise_first = jnp.sum((t_e_inv[0, 0] * a_c[0]) ** 2)
    first_trace = jnp.where(enabled[0],
                            jnp.clip(state.trace + rise_first - drop_first, 0.0, m * cfg.variance),
                            state.trace)

    return GPState(
        inputs=state.inputs.at[slots].set(x, mode="drop"),
        features=state.features.at[:, slots].set(x_features, mode="drop"),
        targets=state.targets.at[slots].set(values, mode="drop"),
        weights=weights,
        valid=remaining | in_block,
        root=root,
        stamp=state.stamp.at[slots].set(state.count + rank, mode="drop"),
        count=state.count + jnp.sum(enabled),
        eval_cross=eval_cross,
        trace=jnp.clip(state.trace + rise - drop, 0.0, m * cfg.variance),
    ), first_trace


BLOCK = 4  # most points per `add_block` in `add_many` (its algebra is unrolled, O(K^3))


def add_many(
    state: GPState,
    poses: jax.Array,
    values: jax.Array,
    cfg: GPConfig,
    eval_poses: jax.Array,
    enabled: jax.Array | None = None,
) -> GPState:
    """Adds (P, 4) poses and (P,) values in order, skipping those with enabled (P,) False.

    The points go in as `add_block`s of at most BLOCK (padded with disabled points), so
    the unrolled block algebra stays small whatever P is.
    """
    count = values.shape[0]
    if count == 0:
        return state
    if enabled is None:
        enabled = jnp.ones((count,), bool)
    size = min(count, BLOCK)
    blocks = -(-count // size)
    pad = blocks * size - count
    chunk = lambda a, fill: jnp.concatenate(  # noqa: E731
        [a, jnp.full((pad, *a.shape[1:]), fill, a.dtype)]).reshape(blocks, size, *a.shape[1:])

    def body(carry, block):
        return add_block(carry, *block[:2], cfg, eval_poses, block[2]), None

    blocked = (chunk(jnp.asarray(poses, jnp.float32), 0.0),
               chunk(jnp.asarray(values, jnp.float32), 0.0), chunk(jnp.asarray(enabled), False))
    return jax.lax.scan(body, state, blocked)[0]


def cross_covariance(state: GPState, poses: jax.Array, cfg: GPConfig) -> jax.Array:
    """k(poses, inputs) over the valid slots, (L, H), from the stored input features."""
    query_features = _materialised_features(poses, cfg)
    return jnp.where(state.valid, feature_kernel(query_features, state.features, cfg), 0.0)


@_float32_matmuls
def predict_projected(
    state: GPState, poses: jax.Array, cfg: GPConfig
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`predict` plus its projections R k(inputs, pose), (L, H).

    The posterior covariance between poses p and q is k(p, q) - proj_p . proj_q, so
    callers that condition on further poses (tree search) reuse them. XLA drops the
    projections when they are not used.
    """
    k = cross_covariance(state, poses, cfg)
    proj = k @ state.root.T
    # Here, unlike in `add`, XLA's matrix-vector kernel beats the multiply-reduce of
    # `_matvec` (predict 25% faster).
    mean = jnp.einsum("lh,h->l", k, state.weights)
    variance = cfg.variance - jnp.sum(proj**2, axis=-1)
    return mean, jnp.clip(variance, 0.0, cfg.variance), proj


def predict(state: GPState, poses: jax.Array, cfg: GPConfig) -> tuple[jax.Array, jax.Array]:
    """Posterior mean (L,) and latent variance (L,) in [0, variance] at poses (L, 4)."""
    mean, variance, _ = predict_projected(state, poses, cfg)
    return mean, variance


def covariance_trace(state: GPState) -> jax.Array:
    """Trace of the posterior covariance over the evaluation poses, ()."""
    return state.trace
