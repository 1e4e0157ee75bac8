"""jaxmripp.allocator: large blocks come from the reusable heap, not from fresh mmaps."""

import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")

# Prints the bytes glibc holds in mmapped chunks while a 96 MB block is alive, allocated by
# the main thread or by a worker thread (as XLA's thread pool allocates temporaries): a
# worker's arena is made of 64 MB heaps, and glibc falls back to mmap for larger blocks
# there whatever the mmap settings, unless all threads share the main arena.
PROBE = """
import ctypes, sys, threading
from jaxmripp import allocator
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
libc.malloc.restype = ctypes.c_void_p
if sys.argv[1] == "keep":
    assert allocator.keep_freed_memory()
before = libc.mallinfo2().hblkhd
blocks = []
allocate = lambda: blocks.append(libc.malloc(96 << 20))
if sys.argv[2] == "worker":
    worker = threading.Thread(target=allocate)
    worker.start()
    worker.join()
else:
    allocate()
print(libc.mallinfo2().hblkhd - before)
"""


def mmapped_bytes_for_a_96mb_block(mode: str, thread: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, mode, thread], check=True,
                         capture_output=True, text=True)
    return int(out.stdout)


@pytest.mark.parametrize("thread", ["main", "worker"])
def test_keep_freed_memory_serves_large_blocks_from_the_heap(thread):
    assert mmapped_bytes_for_a_96mb_block("default", thread) >= 96 << 20  # glibc: mmap
    assert mmapped_bytes_for_a_96mb_block("keep", thread) == 0
