"""jaxmripp.allocator: large blocks come from the reusable heap, not from fresh mmaps."""

import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")

# Prints the bytes glibc holds in mmapped chunks while a 64 MB block is alive.
PROBE = """
import ctypes, sys
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
block = libc.malloc(64 << 20)
print(libc.mallinfo2().hblkhd - before)
"""


def mmapped_bytes_for_a_64mb_block(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], check=True, capture_output=True,
                         text=True)
    return int(out.stdout)


def test_keep_freed_memory_serves_large_blocks_from_the_heap():
    assert mmapped_bytes_for_a_64mb_block("default") >= 64 << 20  # glibc's default: mmap
    assert mmapped_bytes_for_a_64mb_block("keep") == 0
