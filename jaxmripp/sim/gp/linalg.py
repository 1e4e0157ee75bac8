"""Small dense helpers shaped for XLA:CPU under vmap over thousands of GPs.

Batched dots with one output column or a handful of rows run on XLA:CPU as a kernel per
batch element; the multiply-and-sum forms here fuse and vectorise instead. The blocks
`block.add_block_first_trace` factorises have a handful of points K, so its Cholesky
factor and triangular inverse are unrolled rather than LAPACK calls per matrix.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def float32_matmuls(fn):
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


def matvec(matrix: jax.Array, vector: jax.Array) -> jax.Array:
    """matrix (A, B) @ vector (B,) as a multiply and a row sum.

    Under vmap a matrix-vector product becomes a batched dot with one output column,
    which XLA:CPU runs as a slow per-batch loop; the multiply-reduce form fuses and
    vectorises.
    """
    return jnp.sum(matrix * vector, axis=-1)


def vecmat(vector: jax.Array, matrix: jax.Array) -> jax.Array:
    """vector (A,) @ matrix (A, B) as a multiply and a column sum (see `matvec`)."""
    return jnp.sum(vector[:, None] * matrix, axis=0)


def small_dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """a (P, K) @ b (K, Q) for a handful of points K, as K fused outer products.

    XLA:CPU runs each tiny batched dot as its own kernel; unrolled, they fuse with
    their neighbours.
    """
    return sum(a[:, i, None] * b[None, i, :] for i in range(a.shape[1]))


def gram(a: jax.Array, b: jax.Array) -> jax.Array:
    """a^T b for a (H, P), b (H, Q): a contraction over the slots."""
    return jnp.einsum("hp,hq->pq", a, b)


def lower_cholesky(matrix: jax.Array, floor: float) -> jax.Array:
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


def lower_inverse(lower: jax.Array) -> jax.Array:
    """Inverse of a small (K, K) lower-triangular matrix, unrolled forward substitution."""
    k = lower.shape[0]
    inverse = [[jnp.zeros((), lower.dtype)] * k for _ in range(k)]
    for i in range(k):
        inverse[i][i] = 1.0 / lower[i, i]
        for j in range(i):
            inverse[i][j] = -sum(lower[i, p] * inverse[p][j] for p in range(j, i)) / lower[i, i]
    return jnp.stack([jnp.stack(row) for row in inverse])
