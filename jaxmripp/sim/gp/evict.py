"""Where a block's points go and the Householder reflections that evict (compact WY).

`block.add_block_first_trace` evicts the points in the block's slots E with reflections
Q = I - V T V^T built from the columns R_E of the factor alone (O(K^2 H)), so R itself
is only read once more, together with the border (`block._project_root`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxmripp.sim.gp.linalg import gram, lower_inverse, small_dot, vecmat
from jaxmripp.sim.gp.state import GPState


class Slots(NamedTuple):
    """Where the block's points go; K = block size, H = capacity."""

    slots: jax.Array  # (K,) int slot J of each point; H (writes dropped) where disabled
    rank: jax.Array  # (K,) int position of each point among the enabled ones
    in_slot: jax.Array  # (H, K) bool E_J: column i marks point i's slot, zero if disabled
    in_block: jax.Array  # (H,) bool a slot the block writes
    clipped: jax.Array  # (K,) int slots clipped to H - 1, safe to gather with
    evicting: jax.Array  # (K,) bool the point evicts one (its slot holds a point now): E
    remaining: jax.Array  # (H,) bool the points the block keeps


class Reflections(NamedTuple):
    """The evictions Q = I - V T V^T and the evicted points' triangle."""

    evicted_cols: jax.Array  # (H, K) R_E, zero columns where nothing is evicted
    v_mat: jax.Array  # (H, K) V, the Householder vectors
    t_mat: jax.Array  # (K, K) T, lower triangular
    t_e_inv: jax.Array  # (K, K) T_E^-1, identity rows / columns where nothing is evicted


def block_slots(state: GPState, enabled: jax.Array, h: int) -> Slots:
    """The slots J the enabled points take (count, count + 1, ... mod H) and E in them.

    Disabled points get the out-of-range slot H, so every scatter drops their writes and
    every mask built from E_J leaves them out.
    """
    rank = jnp.cumsum(enabled) - 1
    slots = jnp.where(enabled, (state.count + rank) % h, h)
    in_slot = jnp.arange(h)[:, None] == slots[None, :]
    in_block = jnp.any(in_slot, axis=1)
    clipped = jnp.minimum(slots, h - 1)
    evicting = enabled & state.valid[clipped]
    remaining = state.valid & ~in_block
    return Slots(slots, rank, in_slot, in_block, clipped, evicting, remaining)


def _householder_vectors(
    evicted_cols: jax.Array, sl: Slots, h: int, k: int
) -> tuple[jax.Array, list[jax.Array], list[jax.Array]]:
    """Householder reflections of R_E, one column at a time (O(K^2 H) on (H, K) data).

    Reflection i maps what is left of column i (rows already pivoted zeroed) onto its
    slot's row, with the sign chosen against cancellation; a point that evicts nothing
    gets tau = 0, the identity. Returns the reflected R_E, the vectors v_i and the tau_i.
    """
    cols, pivoted = evicted_cols, jnp.zeros((h,), bool)
    vs, taus = [], []
    for i in range(k):
        pivot = sl.in_slot[:, i] & sl.evicting[i]
        col = jnp.where(pivoted, 0.0, cols[:, i])
        sign = jnp.where(col[sl.clipped[i]] < 0, -1.0, 1.0)
        v = col + sign * jnp.sqrt(jnp.sum(col**2)) * pivot
        v_norm2 = jnp.sum(v**2)
        tau = jnp.where(sl.evicting[i] & (v_norm2 > 0), 2.0 / jnp.maximum(v_norm2, 1e-30), 0.0)
        cols = cols - tau * v[:, None] * vecmat(v, cols)[None, :]
        vs.append(v)
        taus.append(tau)
        pivoted = pivoted | pivot
    return cols, vs, taus


def _wy_triangle(v_mat: jax.Array, taus: list[jax.Array], k: int) -> jax.Array:
    """T with H_K ... H_1 = I - V T V^T (compact WY form), lower triangular, row by row.

    T_i = [[T_{i-1}, 0], [-tau_i v_i^T V_{<i} T_{i-1}, tau_i]].
    """
    v_gram = gram(v_mat, v_mat)
    t_rows = [jnp.zeros((k,)).at[0].set(taus[0])]
    for i in range(1, k):
        coupling = -taus[i] * small_dot(v_gram[i, None, :i], jnp.stack(t_rows))[0]
        t_rows.append(coupling.at[i].set(taus[i]))
    return jnp.stack(t_rows)


def reflect_evicted(root: jax.Array, sl: Slots, h: int, k: int) -> Reflections:
    """Q and T_E^-1, from the evicted columns R_E of R alone.

    T_E, the reflected R_E in rows E, is upper triangular with T_E^T T_E = A_EE; rows and
    columns of points that evict nothing are set to the identity so it stays invertible.
    """
    evicted_cols = jnp.where(sl.evicting[None, :], root[:, sl.clipped], 0.0)
    cols, vs, taus = _householder_vectors(evicted_cols, sl, h, k)
    v_mat = jnp.stack(vs, axis=1)
    t_mat = _wy_triangle(v_mat, taus, k)
    both_evicting = sl.evicting[:, None] & sl.evicting[None, :]
    t_e = (jnp.where(both_evicting, cols[sl.clipped], 0.0)
           + jnp.diag(jnp.where(sl.evicting, 0.0, 1.0)))
    t_e_inv = lower_inverse(t_e.T).T
    return Reflections(evicted_cols, v_mat, t_mat, t_e_inv)
