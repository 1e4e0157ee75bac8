"""Batches computed in a fixed number of equal blocks, whatever the device count.

XLA compiles an operation for the shape it is given, and for some operations (a layer
norm's row sums, a weight gradient's sum over samples) the order of the float32
additions follows the shape. Splitting a batch over D devices gives each device a
smaller shape, so the same run on 1 and on 2 devices drifts apart in the last bits and,
a few updates later, samples a different action.

Here a batch is cut into `blocks` equal blocks; a device computes its blocks one after
another (`lax.map`), so every block has the same shapes on every device count that
divides `blocks`, and block results are added in block order. With the network written
so that XLA has no rewrite to apply differently (`jaxmripp.learn.policy.softmax`), the
parameters are then the same to the bit on 1 and 2 devices and processes (tested).
`blocks = 0` means one block per device: the fastest layout, whose results differ with
the device count at the level of float32 rounding.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec

from jaxmripp.parallel.mesh import AXIS, DataParallel


# Off: `fn` sees `shared` as a plain value of its device, so a gradient taken inside `fn`
# is its block's own. With the check on, JAX marks `shared` as device-invariant and sums
# such a gradient over the devices.
_VMA_CHECK = False


def blocks_per_device(blocks: int, data: DataParallel | None) -> int:
    """How many blocks each device computes in turn (`blocks = 0`: one)."""
    devices = 1 if data is None else data.devices
    return max(blocks // devices, 1)


def _to_blocks(x: jax.Array, count: int) -> jax.Array:
    """(n, ...) -> (count, n / count, ...): a block is a contiguous slice, in the same
    memory layout on every device count."""
    return x.reshape((count, x.shape[0] // count) + x.shape[1:])


def _isolated(fn: Callable, block: Any, shared: Any) -> Any:
    """fn(block, shared) behind optimisation barriers, which keep XLA from fusing it with
    the slicing of blocks around it or hoisting its work on `shared` out of the loop over
    blocks: with one block per device the loop disappears, and without the barriers the
    gradients were compiled differently from the several-block program."""
    block, shared = jax.lax.optimization_barrier((block, shared))
    return jax.lax.optimization_barrier(fn(block, shared))


def _on_devices(local: Callable, split: Any, shared: Any, blocks: int,
                data: DataParallel | None, out_spec: PartitionSpec) -> Any:
    """local(split_blocks, shared) on every device, split_blocks being that device's part
    of `split` cut into its (count, ...) blocks; without `data`, once on the whole batch."""

    def cut(split, shared):
        count = blocks_per_device(blocks, data)
        return local(jax.tree.map(lambda x: _to_blocks(x, count), split), shared)

    if data is None:
        return cut(split, shared)
    return jax.shard_map(cut, mesh=data.mesh, in_specs=(PartitionSpec(AXIS), PartitionSpec()),
                         out_specs=out_spec, check_vma=_VMA_CHECK)(split, shared)


def map_blocks(fn: Callable, split: Any, shared: Any, blocks: int,
               data: DataParallel | None) -> Any:
    """fn(split_block, shared) over the blocks of `split`'s leading axis; the outputs,
    batched along that axis, are joined in block order (and stay split over the
    devices)."""

    def local(split_blocks, shared):
        out = jax.lax.map(lambda block: _isolated(fn, block, shared), split_blocks)
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    return _on_devices(local, split, shared, blocks, data, PartitionSpec(AXIS))


def sum_blocks(fn: Callable, split: Any, shared: Any, blocks: int,
               data: DataParallel | None) -> Any:
    """The sum over the blocks of `split`'s leading axis of fn(split_block, shared),
    added in block order (the same on every device count dividing `blocks`); the result
    is replicated: every device adds the same gathered parts in the same order."""

    def local(split_blocks, shared):
        parts = jax.lax.map(lambda block: _isolated(fn, block, shared), split_blocks)
        if data is not None:
            parts = jax.lax.all_gather(parts, AXIS, tiled=True)
        first = jax.tree.map(lambda x: x[0], parts)
        rest = jax.tree.map(lambda x: x[1:], parts)
        total, _ = jax.lax.scan(lambda acc, part: (jax.tree.map(jnp.add, acc, part), None),
                                first, rest)
        return total

    return _on_devices(local, split, shared, blocks, data, PartitionSpec())
