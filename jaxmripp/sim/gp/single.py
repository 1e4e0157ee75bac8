"""One observation in: `add`, an O(H^2 + H M) update of the factor, weights and trace."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxmripp.config import GPConfig
from jaxmripp.sim.gp.linalg import float32_matmuls, matvec, vecmat
from jaxmripp.sim.gp.state import GPState, feature_kernel, materialised_features, pose_features


class _Eviction(NamedTuple):
    """The Householder reflection that evicts slot j (all zero-effect while j is free)."""

    a: jax.Array  # (H,) A e_j = R^T r, r = R[:, j]; zero while j is free
    a_jj: jax.Array  # () |r|^2, or 1 while j is free
    v: jax.Array  # (H,) r + sign(r_j) |r| e_j
    c: jax.Array  # () 2 / |v|^2, or 2 while j is free
    w: jax.Array  # (H,) R^T v


def _evict(root: jax.Array, slot: jax.Array, at_slot: jax.Array,
           occupied: jax.Array) -> _Eviction:
    """The reflection Q = I - c v v^T mapping column j of R, r, onto e_j.

    v = r + sign(r_j) |r| e_j avoids cancellation. The reflected factor is R - c v w^T
    (w = R^T v = a + sign |r| R[j]) with row and column j zeroed; `add` expands its
    products around R rather than forming it, so R is read three times in all.
    """
    r = root[:, slot]
    a = vecmat(r, root)
    r_norm2 = jnp.sum(r**2)
    a_jj = jnp.where(occupied, r_norm2, 1.0)
    v_j = jnp.where(r[slot] < 0, -1.0, 1.0) * jnp.sqrt(r_norm2)
    v = r + v_j * at_slot
    c = 2.0 / jnp.where(occupied, jnp.sum(v**2), 1.0)
    w = a + v_j * root[slot]
    return _Eviction(a, a_jj, v, c, w)


def _border(root: jax.Array, k: jax.Array, ev: _Eviction, others: jax.Array,
            cfg: GPConfig) -> tuple[jax.Array, jax.Array]:
    """s and b = R'^T l, l = R' k, on the reflected R', expanded around R.

    s = k(x, x) + noise - |l|^2 is the predictive variance of y at x given the kept
    points, clamped to >= noise against float32 cancellation.
    """
    root_k = matvec(root, k)
    l = jnp.where(others, root_k - ev.c * ev.v * jnp.dot(ev.w, k), 0.0)
    s = jnp.maximum(cfg.variance + cfg.noise - jnp.sum(l**2), cfg.noise)
    b = jnp.where(others, vecmat(l, root) - ev.c * ev.w * jnp.dot(ev.v, l), 0.0)
    return s, b


def _new_root(root: jax.Array, ev: _Eviction, b: jax.Array, s: jax.Array,
              at_slot: jax.Array, others: jax.Array) -> jax.Array:
    """The reflected R with row j replaced by the border row (e_j - b) / sqrt(s)."""
    reflected = root - jnp.outer(ev.c * ev.v, ev.w)
    return jnp.where(
        at_slot[:, None],
        (at_slot - b) / jnp.sqrt(s),
        jnp.where(others[None, :], reflected, 0.0),  # exact zeros in column j
    )


def _new_weights(state: GPState, ev: _Eviction, b: jax.Array, s: jax.Array,
                 at_slot: jax.Array, value: jax.Array) -> jax.Array:
    """w - a (a^T y) / a_jj (evict, zeroes w_j), then + (e_j - b) innovation / s."""
    y = state.targets
    evicted_weights = state.weights - ev.a * (jnp.dot(ev.a, y) / ev.a_jj)  # a = 0 if j free
    innovation = value - jnp.dot(b, y)  # value minus the prior-to-insert mean at x
    return evicted_weights + (at_slot - b) * (innovation / s)


def _trace_update(state: GPState, ev: _Eviction, b: jax.Array, s: jax.Array,
                  slot: jax.Array, occupied: jax.Array, x_features: jax.Array,
                  eval_features: jax.Array, enabled: jax.Array | bool,
                  cfg: GPConfig) -> tuple[jax.Array, jax.Array]:
    """The new C (row j written when enabled) and the unclamped trace after the add.

    Writes the new row of C first, then one pass over C gives a^T C and b^T C together
    (b_j = 0 ignores row j; a^T C needs the evicted point's row, recomputed from its
    pose). Writing before reading lets XLA update C in place.
    """
    cross = feature_kernel(x_features, eval_features, cfg)[0]
    eval_cross = state.eval_cross.at[slot].set(
        jnp.where(enabled, cross, state.eval_cross[slot])
    )
    evicted = feature_kernel(state.features[:, slot, None], eval_features, cfg)[0]
    a_c, b_c = jnp.sum(jnp.stack([ev.a, b])[:, :, None] * eval_cross, axis=1)
    a_c = a_c + ev.a[slot] * (evicted - cross)
    rise = jnp.where(occupied, jnp.sum(a_c**2) / ev.a_jj, 0.0)
    return eval_cross, state.trace + rise - jnp.sum((cross - b_c) ** 2) / s


@float32_matmuls
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
    eval_features = materialised_features(eval_poses, cfg)
    slot = state.count % h
    at_slot = jnp.arange(h) == slot
    others = ~at_slot
    occupied = state.valid[slot]

    valid = state.valid & others
    k = jnp.where(valid, feature_kernel(x_features, state.features, cfg)[0], 0.0)
    ev = _evict(state.root, slot, at_slot, occupied)
    s, b = _border(state.root, k, ev, others, cfg)
    eval_cross, trace = _trace_update(state, ev, b, s, slot, occupied, x_features,
                                      eval_features, enabled, cfg)
    added = GPState(
        inputs=state.inputs.at[slot].set(x),
        features=state.features.at[:, slot].set(x_features[:, 0]),
        targets=state.targets.at[slot].set(value),
        weights=_new_weights(state, ev, b, s, at_slot, value),
        valid=valid | at_slot,
        root=_new_root(state.root, ev, b, s, at_slot, others),
        stamp=state.stamp.at[slot].set(state.count),
        count=state.count + 1,
        eval_cross=eval_cross,
        trace=jnp.clip(trace, 0.0, m * cfg.variance),  # float32 drift stays in range
    )
    current = state.replace(eval_cross=eval_cross)  # already masked: passes through
    return jax.tree.map(lambda new, old: jnp.where(enabled, new, old), added, current)
