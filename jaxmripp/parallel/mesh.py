"""One data-parallel layout for one device, several local devices and several processes.

Every device of every process forms a one-axis `Mesh` (axis "data"). Batches of
environments or evaluation episodes are split along that axis; network parameters,
optimiser state and environment parameters are replicated. Programs are ordinary `jit`
programs with sharding constraints, so the compiler partitions them and reduces the
gradients: the arithmetic is the single-device program's, and the device count changes
only the order of floating-point sums.

In a multi-process run each process holds only its own devices' shards; `put_*` builds
global arrays from values every process computes identically (seeded), and results are
returned replicated so every process can read them.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "data"


class ShardingError(ValueError):
    """A batch that cannot be split evenly over the devices."""


@dataclasses.dataclass(frozen=True)
class DataParallel:
    """The device mesh and the two layouts used on it."""

    mesh: Mesh

    @property
    def devices(self) -> int:
        return self.mesh.size

    @property
    def replicated(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec())

    def split(self, axis: int = 0) -> NamedSharding:
        """Arrays split along `axis` over the devices."""
        return NamedSharding(self.mesh, PartitionSpec(*([None] * axis), AXIS))

    def constrain(self, tree: Any, axis: int = 0) -> Any:
        """Inside a jitted function: keep `tree`'s leaves split along `axis`."""
        if self.devices == 1:
            return tree
        return jax.lax.with_sharding_constraint(tree, self.split(axis))

    def put_replicated(self, tree: Any) -> Any:
        return jax.tree.map(lambda x: _global_array(x, self.replicated), tree)

    def put_split(self, tree: Any, axis: int = 0) -> Any:
        return jax.tree.map(lambda x: _global_array(x, self.split(axis)), tree)

    def put_batch(self, tree: Any) -> Any:
        """A batch (leading axis) padded with repeats of its last item to a multiple of
        the device count, then split over the devices; `gather` cuts the padding off."""
        count = len(jax.tree.leaves(tree)[0])
        pad = self.round_up(count) - count
        padded = jax.tree.map(
            lambda x: np.concatenate([np.asarray(x), np.repeat(np.asarray(x)[-1:], pad, 0)]),
            tree)
        return self.put_split(padded)

    def gather(self, tree: Any, count: int | None = None) -> Any:
        """NumPy copies of (global) arrays on every process; the first `count` items of
        each leading axis when given."""
        def fetch(x):
            if isinstance(x, jax.Array) and not (x.is_fully_addressable or x.is_fully_replicated):
                x = multihost_utils.process_allgather(x, tiled=True)
            x = np.asarray(x)
            return x if count is None else x[:count]

        return jax.tree.map(fetch, tree)

    def check_divides(self, count: int, what: str) -> None:
        if count % self.devices:
            raise ShardingError(
                f"{what} = {count} cannot be split over {self.devices} devices; allowed: a "
                f"multiple of {self.devices} ({jax.process_count()} process(es) x "
                f"{jax.local_device_count()} local device(s))")

    def round_up(self, count: int) -> int:
        """The smallest multiple of the device count >= count."""
        return -(-count // self.devices) * self.devices


def _global_array(value: Any, sharding: NamedSharding) -> jax.Array:
    """A global array from a value every process holds in full."""
    if isinstance(value, jax.Array) and value.sharding == sharding:
        return value
    host = np.asarray(value)
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


@functools.lru_cache(maxsize=1)
def data_parallel() -> DataParallel:
    """Every device of every process, in JAX's global order (built once per process)."""
    return DataParallel(Mesh(np.asarray(jax.devices()), (AXIS,)))


def is_main_process() -> bool:
    """Process 0 writes files and logs; the others compute their shards silently."""
    return jax.process_index() == 0
