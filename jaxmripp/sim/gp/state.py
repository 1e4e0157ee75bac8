"""The GP's state, its kernel over poses and the fixed trace evaluation set.

Kernel: Matern-1/2 over poses, k = variance exp(-d / length_scale), zero prior mean, with
d^2 = |dp|^2 + (heading_scale * 2 sin(dtheta / 2))^2: the Euclidean distance after
placing the heading on a circle of radius heading_scale, so k is positive definite
(Matern-1/2 is, in any dimension). The wrapped arc length |dtheta| in [0, pi] in place of
the chord is not: arc^2 is not conditionally negative definite on the circle, and with
length_scale >= 0.5 random pose sets give K with eigenvalues far below -noise (negative
variances). Chord and arc agree to first order: a quarter turn counts 1.41 heading_scale
instead of 1.57, a half turn 2 instead of 3.14.
"""

from __future__ import annotations

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
    rather than recomputing them every step.
    """
    angle = poses[..., 3]
    x, y, z = poses[..., 0], poses[..., 1], poses[..., 2]
    hs = cfg.heading_scale
    return jnp.stack([x, y, z, hs * jnp.cos(angle), hs * jnp.sin(angle)])


def materialised_features(poses: jax.Array, cfg: GPConfig) -> jax.Array:
    """`pose_features` behind an optimisation barrier.

    The barrier keeps XLA from fusing cos and sin into the (A, B) loop of the kernel,
    where they would be recomputed for every pair.
    """
    return jax.lax.optimization_barrier(pose_features(poses, cfg))


def kernel(a: jax.Array, b: jax.Array, cfg: GPConfig) -> jax.Array:
    """Matern-1/2 covariance between pose sets: (..., A, 4), (..., B, 4) -> (..., A, B)."""
    return feature_kernel(materialised_features(a, cfg), materialised_features(b, cfg), cfg)


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


def covariance_trace(state: GPState) -> jax.Array:
    """Trace of the posterior covariance over the evaluation poses, ()."""
    return state.trace
