"""XLA compiler options for simulation programs, chosen for the host CPU.

On a CPU with AVX-512, XLA:CPU still vectorises loops 256 bits wide unless asked for
more. The simulator's step is elementwise passes, gathers and small GP solves, and runs
faster with 512-bit vectors; the PPO update (dense network arithmetic) runs slower with
them. So the option is set per compiled program rather than process-wide (XLA_FLAGS):
programs that are mostly simulation (evaluation sweeps, the make-train comparison, the
environment benchmarks) compile with `simulation()`, training chunks with XLA's defaults.
docs/performance.md gives the measurements.

Float sums may round differently with wider vectors, so on such a CPU a GP's last bits
can differ from a build without the option (results stay deterministic for a given CPU
kind). A width named in XLA_FLAGS is left alone: `XLA_FLAGS=--xla_cpu_prefer_vector_width=256`
turns the choice off.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Callable

import jax

VECTOR_WIDTH = "xla_cpu_prefer_vector_width"
CPUINFO = Path("/proc/cpuinfo")


def simulation(options: dict | None = None) -> dict:
    """The compiler options of a simulation program: the host's (`host_simulation`)
    updated with `options` (which win where both name an option)."""
    return {**host_simulation(), **(options or {})}


def simulation_jit(fn: Callable, **kwargs) -> Callable:
    """`jax.jit(fn, **kwargs)` compiled with the simulation options (`simulation()`)."""
    return jax.jit(fn, compiler_options=simulation(), **kwargs)


@functools.cache
def host_simulation() -> dict:
    """{VECTOR_WIDTH: 512} when JAX computes on a CPU with AVX-512 and XLA_FLAGS names no
    vector width; {} otherwise."""
    if VECTOR_WIDTH in os.environ.get("XLA_FLAGS", ""):
        return {}
    if jax.default_backend() != "cpu" or "avx512f" not in cpu_flags():
        return {}
    return {VECTOR_WIDTH: 512}


def cpu_flags(cpuinfo: Path | None = None) -> frozenset[str]:
    """The feature flags of the first CPU in `cpuinfo` (default CPUINFO, Linux's); empty
    where it cannot be read or lists none."""
    try:
        text = (cpuinfo or CPUINFO).read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return frozenset(value.split())
    return frozenset()
