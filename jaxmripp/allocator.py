"""Keep freed memory in the process heap for reuse instead of handing it back (glibc).

XLA:CPU's YNNPACK fusions allocate their intermediate buffers with malloc on every call:
the attention scores alone are E x N x heads x L^2 floats, 39 MB at 128 environments and
315 MB at 1024. glibc serves large blocks with a fresh mmap and unmaps them on free, so
every call page-faults each buffer in again (at 128 environments a third of the rollout's
wall time went to system time). With chunk-level mmap off and heap trimming effectively
off, freed blocks are reused: measured in one run of `benchmarks/train.py --envs 128`,
rollout 1,770 -> 2,499 and policy forward 2,627 -> 4,202 agent-steps/s. The price is that
the process keeps its peak heap until it exits, so the entry points that run long jobs
(training, evaluation, benchmarks) opt in; importing jaxmripp changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

# mallopt parameter numbers from glibc's malloc.h.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
# Largest value mallopt takes (an int): free space above 2 GB at the heap top is trimmed.
TRIM_THRESHOLD = 2**31 - 1


def keep_freed_memory() -> bool:
    """Turns off chunk-level mmap and heap trimming; False (and no change) if not glibc."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    no_mmap = bool(libc.mallopt(M_MMAP_MAX, 0))
    return no_mmap and bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
