"""Keep freed memory in the process heap for reuse instead of handing it back (glibc).

XLA:CPU's YNNPACK fusions allocate their intermediate buffers with malloc on every call
(the attention scores alone are E x N x heads x L^2 floats). glibc serves large blocks
with a fresh mmap and unmaps them on free, so every call would page-fault each buffer in
again; with chunk-level mmap off and heap trimming effectively off, freed blocks are
reused instead.

XLA's worker threads allocate from their own glibc arenas, whose heaps are at most 64 MB;
a larger block there is mmapped whatever M_MMAP_MAX says. Capping glibc at two arenas
puts most of XLA's big allocations on the main arena, which grows with brk and keeps what
it frees. One arena would remove the page faults completely but serialises every malloc
(the PPO update slows down); two cost nothing there. The price is that the process keeps
its peak heap until it exits, so the entry points that run long jobs (training,
evaluation, benchmarks) opt in; importing jaxmripp changes nothing. docs/performance.md
gives the measured effect.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import importlib.util
import os
import pkgutil
import platform

# mallopt parameter numbers from glibc's malloc.h.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
# Largest value mallopt takes (an int): free space above 2 GB at the heap top is trimmed.
TRIM_THRESHOLD = 2**31 - 1
# The main arena and one more (see the module docstring for the measurements).
ARENAS = 2


def keep_freed_memory() -> bool:
    """No chunk-level mmap, no heap trimming, two arenas; False (no change) if not glibc
    or if JAX will compute on an accelerator (whose buffers are not malloc'd).

    Call it before JAX starts its threads (their arenas would already exist): it asks only
    which platforms JAX can use, without starting one."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    if accelerator_expected():
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    settings = [(M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_ARENA_MAX, ARENAS)]
    return all([bool(libc.mallopt(param, value)) for param, value in settings])


def accelerator_expected() -> bool:
    """Whether JAX's default backend will be a GPU or TPU: JAX_PLATFORMS names one first,
    or (JAX_PLATFORMS unset) a GPU plugin or libtpu is installed."""
    chosen = os.environ.get("JAX_PLATFORMS", "").split(",")[0].strip().lower()
    if chosen:
        return chosen != "cpu"
    try:
        import jax_plugins  # noqa: PLC0415 (namespace package of JAX's GPU plugins)

        if any(pkgutil.iter_modules(jax_plugins.__path__)):
            return True
    except ImportError:
        pass
    return importlib.util.find_spec("libtpu") is not None
