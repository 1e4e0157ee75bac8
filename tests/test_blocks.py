"""Blocks of a batch (jaxmripp.parallel.blocks) against the same work done by hand, and
the network's softmax against jax.nn.softmax. That blocked training gives the same
parameters on 1 and 2 devices and processes is tested in test_train.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.learn.policy import softmax
from jaxmripp.parallel.blocks import blocks_per_device, map_blocks, sum_blocks


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(3)
    return (rng.normal(size=(12, 5, 3)).astype(np.float32),
            rng.normal(size=(12, 5)).astype(np.float32))


def _block_sum(block, scale):
    x, y = block
    return {"x": (x * scale).sum(axis=0), "xy": (x.sum(-1) * y).sum()}


@pytest.mark.parametrize("blocks", [0, 1, 3, 4])
def test_sum_blocks_equals_the_sum_over_the_whole_batch(batch, blocks):
    scale = np.float32(0.5)
    got = jax.jit(lambda b: sum_blocks(_block_sum, b, scale, blocks, None))(batch)
    dense = {"x": batch[0].sum(axis=0) * scale, "xy": (batch[0].sum(-1) * batch[1]).sum()}
    for key in dense:
        np.testing.assert_allclose(np.asarray(got[key]), dense[key], rtol=1e-5, atol=1e-5)


def test_sum_blocks_adds_in_block_order():
    # float32: ((1e8 + 1) - 1e8) + 1 = 1 in block order; pairs (1e8 + 1) + (-1e8 + 1)
    # give 0 and the exact sum is 2.
    values = np.array([1e8, 1.0, -1e8, 1.0], np.float32)
    got = jax.jit(lambda v: sum_blocks(lambda block, _: block.sum(), v, None, 4, None))(values)
    assert float(got) == 1.0


@pytest.mark.parametrize("blocks", [0, 2, 6])
def test_map_blocks_keeps_every_item_in_place(batch, blocks):
    fn = lambda block, shift: (block[0].sum(-1) + block[1] * shift, block[1][:, 0] - shift)
    got = jax.jit(lambda b: map_blocks(fn, b, np.float32(2.0), blocks, None))(batch)
    expected = fn(batch, np.float32(2.0))
    for g, e in zip(got, expected):
        assert g.shape == e.shape
        np.testing.assert_allclose(np.asarray(g), np.asarray(e), rtol=1e-6, atol=1e-6)


def test_blocks_per_device():
    assert blocks_per_device(0, None) == 1
    assert blocks_per_device(4, None) == 4


def test_softmax_matches_jax_and_handles_a_fully_masked_row():
    x = jax.random.normal(jax.random.PRNGKey(0), (4, 7)) * 5
    x = x.at[1].set(jnp.finfo(jnp.float32).min)  # every key masked: uniform, finite
    got = np.asarray(softmax(x))
    np.testing.assert_allclose(got, np.asarray(jax.nn.softmax(x, axis=-1)), rtol=1e-6,
                               atol=1e-7)
    np.testing.assert_allclose(got[1], np.full(7, 1 / 7), rtol=1e-6)
    np.testing.assert_allclose(got.sum(-1), 1.0, rtol=1e-6)
    grad = jax.grad(lambda x: (softmax(x) * jnp.arange(7.0)).sum())(x[0])
    expected = jax.grad(lambda x: (jax.nn.softmax(x) * jnp.arange(7.0)).sum())(x[0])
    np.testing.assert_allclose(np.asarray(grad), np.asarray(expected), rtol=1e-5, atol=1e-6)
