"""Posterior mean and variance at query poses: one (L, H) x (H, H) matmul and a dot."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.config import GPConfig
from jaxmripp.sim.gp.linalg import float32_matmuls
from jaxmripp.sim.gp.state import GPState, feature_kernel, materialised_features


def cross_covariance(state: GPState, poses: jax.Array, cfg: GPConfig) -> jax.Array:
    """k(poses, inputs) over the valid slots, (L, H), from the stored input features."""
    query_features = materialised_features(poses, cfg)
    return jnp.where(state.valid, feature_kernel(query_features, state.features, cfg), 0.0)


@float32_matmuls
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
    # `linalg.matvec`: the (L, H) operand is already materialised for the matmul above.
    mean = jnp.einsum("lh,h->l", k, state.weights)
    variance = cfg.variance - jnp.sum(proj**2, axis=-1)
    return mean, jnp.clip(variance, 0.0, cfg.variance), proj


def predict(state: GPState, poses: jax.Array, cfg: GPConfig) -> tuple[jax.Array, jax.Array]:
    """Posterior mean (L,) and latent variance (L,) in [0, variance] at poses (L, 4)."""
    mean, variance, _ = predict_projected(state, poses, cfg)
    return mean, variance
