"""Keep freed memory in the process heap for reuse instead of handing it back (glibc).

XLA:CPU's YNNPACK fusions allocate their intermediate buffers with malloc on every call:
the attention scores alone are E x N x heads x L^2 floats, 39 MB at 128 environments and
315 MB at 1024. glibc serves large blocks with a fresh mmap and unmaps them on free, so
every call page-faults each buffer in again (at 128 environments a third of the rollout's
wall time went to system time). With chunk-level mmap off and heap trimming effectively
off, freed blocks are reused: measured in one run of `benchmarks/train.py --envs 128`,
rollout 1,770 -> 2,499 and policy forward 2,627 -> 4,202 agent-steps/s.

XLA's worker threads allocate from their own glibc arenas, whose heaps are at most 64 MB;
a larger block there is mmapped whatever M_MMAP_MAX says (the GP benchmark's 63 MB
kernel matrix plus headroom: 17,000 page faults and 40 ms of system time per call).
Capping glibc at two arenas puts most of XLA's big allocations on the main arena, which
grows with brk and keeps what it frees: `benchmarks/gp.py` went from 30,000 to 50,000 GP
steps/s and the 1024-environment rollout from 2,200 to 2,800 agent-steps/s (measured in
one session, two arenas against glibc's default). One arena removes the page faults
completely but serialises every malloc: 15 times more context switches, and the
64-environment PPO update of `make train` took 8-9 s instead of 6.7 s; two arenas cost
nothing there. The price of all this is that the process keeps its peak heap until it
exits, so the entry points that run long jobs (training, evaluation, benchmarks) opt in;
importing jaxmripp changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
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
    """No chunk-level mmap, no heap trimming, two arenas; False (no change) if not glibc."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    settings = [(M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_ARENA_MAX, ARENAS)]
    return all([bool(libc.mallopt(param, value)) for param, value in settings])
