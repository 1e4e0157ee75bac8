"""jaxmripp.spec.vectors: NumPy and JAX give the same bits, and the same bits as XLA:CPU's
reductions over (..., 3) vectors."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.spec import vectors


def test_dot_and_unit_are_the_same_bits_in_numpy_jax_and_xla_reductions():
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, (4096, 3)).astype(np.float32)
    v = rng.uniform(-1, 1, (4096, 3)).astype(np.float32)
    u[:5] = 0.0  # zero length: a zero unit vector
    ours = vectors.dot(vectors.components(u), vectors.components(v), np)
    assert ours.dtype == np.float32
    jax_dot = jax.jit(lambda a, b: vectors.dot(vectors.components(a), vectors.components(b), jnp))
    np.testing.assert_array_equal(ours, np.asarray(jax_dot(u, v)))
    np.testing.assert_array_equal(ours, np.asarray(jax.jit(
        lambda a, b: jnp.sum(a * b, axis=-1))(u, v)))
    # Plain left-to-right sums differ in some last bits: the order is part of the rule.
    assert np.any(ours != (u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1]) + u[:, 2] * v[:, 2])

    def unit(a, xp):
        d = vectors.components(a)
        return xp.stack(vectors.unit(d, xp.sqrt(vectors.dot(d, d, xp)), xp), axis=-1)

    ours = unit(u, np)
    np.testing.assert_array_equal(ours[:5], 0.0)
    np.testing.assert_array_equal(ours, np.asarray(jax.jit(lambda a: unit(a, jnp))(u)))

    @jax.jit
    def reference(a):  # a vector over its length, as XLA:CPU compiles it
        length = jnp.linalg.norm(a, axis=-1, keepdims=True)
        return jnp.where(length > 0, a / jnp.where(length > 0, length, 1.0), 0.0)

    np.testing.assert_array_equal(ours, np.asarray(reference(u)))
