"""Float32 arithmetic on 3-vectors that NumPy and JAX evaluate to the same bits.

The vectors are component triples (x, y, z arrays): XLA:CPU does not vectorise a
reduction over a trailing axis of 3, where elementwise arithmetic on components fuses
into one loop. Every rounding step is explicit, so neither XLA's fusion (which would
contract a product into a following sum, or a division by a broadcast length into a
multiplication) nor NumPy changes the result: products and reciprocals are rounded on
their own, and three terms are summed as (x + z) + y, the order XLA:CPU uses for a
reduction over (..., 3), so these forms also give what such reductions give. `xp` is
numpy or jax.numpy.
"""

from __future__ import annotations


def rounded(x, xp):
    """x, rounded to float32 on its own: a select on NaN, which XLA does not fold into
    the arithmetic around it."""
    return xp.where(xp.isnan(x), 0.0, x)


def components(v) -> list:
    """(..., 3) array -> [x, y, z], each (...,)."""
    return [v[..., k] for k in range(3)]


def dot(u, v, xp):
    """Dot product of component triples u, v."""
    x, y, z = (rounded(a * b, xp) for a, b in zip(u, v))
    return (x + z) + y


def unit(d, length, xp) -> list:
    """The components d divided by their length (0 where the length is 0), as d times the
    rounded reciprocal."""
    inverse = rounded(1.0 / xp.where(length > 0, length, 1.0), xp)
    return [xp.where(length > 0, c * inverse, 0.0) for c in d]
