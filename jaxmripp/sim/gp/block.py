"""Several observations in at once: `add_block`, `add_block_first_trace` and `add_many`.

K points go in as one block: K Householder reflections in compact WY form evict, and a
K-row border inserts, with R read three times and written once for the whole block
rather than per point. The environment feeds each GP its own and its peers' poses this
way, one block a step. The steps of `add_block_first_trace` are the private functions
below and, for the slots and the evicting reflections, `evict`; their names follow its
docstring (E_J, V, T, L, S, W, B, A_E, G).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import GPConfig
from jaxmripp.sim.gp.evict import Reflections, Slots, block_slots, reflect_evicted
from jaxmripp.sim.gp.linalg import (
    float32_matmuls, gram, lower_cholesky, lower_inverse, small_dot,
)
from jaxmripp.sim.gp.state import GPState, feature_kernel, materialised_features

BLOCK = 4  # most points per `add_block` in `add_many` (its algebra is unrolled, O(K^3))


def _border(
    state: GPState, x_features: jax.Array, enabled: jax.Array, sl: Slots,
    refl: Reflections, cfg: GPConfig,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """L = Q R Kx over the kept points, S = k(X, X) + noise I - L^T L and W = chol(S)^-1.

    S is the predictive covariance of y at the block's poses given the kept points;
    W^T W = S^-1. Disabled points get identity rows and columns in S.
    """
    kx = feature_kernel(state.features, x_features, cfg)  # (H, K)
    kx = jnp.where(sl.remaining[:, None] & enabled[None, :], kx, 0.0)
    root_kx = jnp.einsum("ij,jk->ik", state.root, kx)  # R Kx
    v_mat, t_mat = refl.v_mat, refl.t_mat
    l_mat = root_kx - small_dot(v_mat, small_dot(t_mat, gram(v_mat, root_kx)))  # Q R Kx
    l_mat = jnp.where(sl.remaining[:, None], l_mat, 0.0)
    kxx = feature_kernel(x_features, x_features, cfg)
    s_mat = jnp.where(enabled[:, None] & enabled[None, :], kxx, 0.0) \
        + jnp.diag(jnp.where(enabled, cfg.noise, 1.0)) - gram(l_mat, l_mat)
    w_mat = lower_inverse(lower_cholesky(s_mat, cfg.noise))
    return l_mat, s_mat, w_mat


def _project_root(
    root: jax.Array, l_mat: jax.Array, sl: Slots, refl: Reflections, k: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One pass over R for R^T [Q^T L, V, R_E], slot-major: B = A' Kx, V^T R and A_E.

    A_E = R^T R_E (zero columns where nothing is evicted).
    """
    v_mat, t_mat = refl.v_mat, refl.t_mat
    z_mat = l_mat - small_dot(v_mat, small_dot(t_mat.T, gram(v_mat, l_mat)))  # Q^T L
    rhs = jnp.concatenate([z_mat, v_mat, refl.evicted_cols], axis=1).T  # (3K, H)
    projected = jnp.sum(rhs[:, :, None] * root[None], axis=1)  # (3K, H)
    b_mat = jnp.where(sl.remaining[:, None], projected[:k].T, 0.0)
    return b_mat, projected[2 * k:].T, projected[k: 2 * k]


def _write_root(
    root: jax.Array, w_mat: jax.Array, b_mat: jax.Array, v_root: jax.Array, sl: Slots,
    refl: Reflections, k: int,
) -> jax.Array:
    """The new R: QR on the kept points and the rows W (E_J - B)^T in slots J.

    The rank-K terms as outer products and row selects fuse into one pass over R (a
    (H, K) x (K, H) dot would be materialised first).
    """
    new_rows = small_dot(w_mat, sl.in_slot.T.astype(jnp.float32) - b_mat.T)  # (K, H)
    reflected = root - small_dot(refl.v_mat, small_dot(refl.t_mat, v_root))
    root = jnp.where(sl.remaining[:, None] & sl.remaining[None, :], reflected, 0.0)
    for i in range(k):
        root = jnp.where(sl.in_slot[:, i, None], new_rows[i][None, :], root)
    return root


def _block_weights(
    state: GPState, values: jax.Array, enabled: jax.Array, b_mat: jax.Array,
    a_e: jax.Array, w_mat: jax.Array, sl: Slots, refl: Reflections,
) -> jax.Array:
    """Evict (w - A_E A_EE^-1 w_E), then insert ((E_J - B) S^-1 innovation)."""
    y = jnp.where(sl.remaining, state.targets, 0.0)
    w_e = jnp.where(sl.evicting, state.weights[sl.clipped], 0.0)
    a_ee_inv_w = small_dot(refl.t_e_inv, small_dot(refl.t_e_inv.T, w_e[:, None]))
    evicted_weights = jnp.where(sl.remaining,
                                state.weights - small_dot(a_e, a_ee_inv_w)[:, 0], 0.0)
    innovation = jnp.where(enabled, values - gram(b_mat, y[:, None])[:, 0], 0.0)
    s_inv_innovation = small_dot(w_mat.T, small_dot(w_mat, innovation[:, None]))
    return evicted_weights + small_dot(sl.in_slot - b_mat, s_inv_innovation)[:, 0]


def _trace_projections(
    state: GPState, x_features: jax.Array, eval_features: jax.Array,
    evicted_features: jax.Array, enabled: jax.Array, b_mat: jax.Array, a_e: jax.Array,
    sl: Slots, cfg: GPConfig,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The new C, A_E^T C against the old C and G = k(X, E) - B^T C: (H, M), (K, M), (K, M).

    Writes the new rows of C first, then one pass over C gives A_E^T C and B^T C; the
    evicted points' rows of C, overwritten by then, are recomputed from their poses.
    """
    cross = feature_kernel(x_features, eval_features, cfg)  # (K, M)
    eval_cross = state.eval_cross.at[sl.slots].set(cross, mode="drop")
    ab = jnp.concatenate([a_e, b_mat], axis=1).T  # (2K, H)
    a_c, b_c = jnp.split(jnp.sum(ab[:, :, None] * eval_cross[None], axis=1), 2)
    evicted_cross = feature_kernel(evicted_features, eval_features, cfg)  # (K, M)
    a_at_slots = jnp.where(enabled[:, None], a_e[sl.clipped], 0.0)  # (K, K) rows J of A_E
    a_c = a_c + small_dot(a_at_slots.T, jnp.where(enabled[:, None], evicted_cross - cross, 0.0))
    gain = jnp.where(enabled[:, None], cross - b_c, 0.0)
    return eval_cross, a_c, gain


def _first_trace(
    state: GPState, x_features: jax.Array, evicted_features: jax.Array,
    enabled: jax.Array, s_mat: jax.Array, b_mat: jax.Array, a_c: jax.Array,
    gain: jax.Array, sl: Slots, refl: Reflections, m: int, cfg: GPConfig,
) -> jax.Array:
    """The trace a lone `add` of the first point would leave (see `add_block_first_trace`).

    T_E^-T is lower triangular, so row 0 of the rise is the first point's own eviction.
    Its insertion is conditioned on the later evictions F as well, one more Schur
    complement with Sigma_EE = A_EE^-1.
    """
    k = sl.evicting.shape[0]
    t_e_inv = refl.t_e_inv
    later = sl.evicting & (jnp.arange(k) > 0)  # F
    both_later = later[:, None] & later[None, :]
    sigma_ee = small_dot(t_e_inv, t_e_inv.T)  # A_EE^-1
    w_f = lower_inverse(lower_cholesky(
        jnp.where(both_later, sigma_ee, 0.0) + jnp.diag(jnp.where(later, 0.0, 1.0)), cfg.noise))
    c_f = feature_kernel(x_features[:, :1], evicted_features, cfg)[0] \
        - gram(b_mat[:, :1], feature_kernel(state.features, evicted_features, cfg))[0]
    u = small_dot(w_f, jnp.where(later, c_f, 0.0)[:, None])  # (K, 1)
    g_f = small_dot(w_f, jnp.where(later[:, None], small_dot(sigma_ee, a_c), 0.0))
    s_first = jnp.maximum(s_mat[0, 0] - jnp.sum(u**2), cfg.noise)
    drop_first = jnp.sum((gain[0] - small_dot(u.T, g_f)[0]) ** 2) / s_first
    rise_first = jnp.sum((t_e_inv[0, 0] * a_c[0]) ** 2)
    return jnp.where(enabled[0],
                     jnp.clip(state.trace + rise_first - drop_first, 0.0, m * cfg.variance),
                     state.trace)


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


@float32_matmuls
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
    x_features = materialised_features(x, cfg)  # (5, K)
    eval_features = materialised_features(eval_poses, cfg)

    sl = block_slots(state, enabled, h)
    refl = reflect_evicted(state.root, sl, h, k)
    l_mat, s_mat, w_mat = _border(state, x_features, enabled, sl, refl, cfg)
    b_mat, a_e, v_root = _project_root(state.root, l_mat, sl, refl, k)
    evicted_features = state.features[:, sl.clipped]  # (5, K)
    eval_cross, a_c, gain = _trace_projections(
        state, x_features, eval_features, evicted_features, enabled, b_mat, a_e, sl, cfg)
    rise = jnp.sum(small_dot(refl.t_e_inv.T, a_c) ** 2)
    drop = jnp.sum(small_dot(w_mat, gain) ** 2)
    first_trace = _first_trace(state, x_features, evicted_features, enabled, s_mat, b_mat,
                               a_c, gain, sl, refl, m, cfg)

    return GPState(
        inputs=state.inputs.at[sl.slots].set(x, mode="drop"),
        features=state.features.at[:, sl.slots].set(x_features, mode="drop"),
        targets=state.targets.at[sl.slots].set(values, mode="drop"),
        weights=_block_weights(state, values, enabled, b_mat, a_e, w_mat, sl, refl),
        valid=sl.remaining | sl.in_block,
        root=_write_root(state.root, w_mat, b_mat, v_root, sl, refl, k),
        stamp=state.stamp.at[sl.slots].set(state.count + sl.rank, mode="drop"),
        count=state.count + jnp.sum(enabled),
        eval_cross=eval_cross,
        trace=jnp.clip(state.trace + rise - drop, 0.0, m * cfg.variance),
    ), first_trace


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
