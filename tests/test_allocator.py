"""jaxmripp.allocator: large blocks come from the reusable heap, not from fresh mmaps."""

import platform
import subprocess
import sys

import pytest

from jaxmripp import allocator

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")

# Prints the bytes glibc holds in mmapped chunks while a 96 MB block is alive.
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
block = libc.malloc(96 << 20)
print(libc.mallinfo2().hblkhd - before)
"""

# Prints how many arenas glibc runs once three threads have allocated at the same time
# (malloc_info writes one <heap> element per arena).
ARENA_PROBE = """
import ctypes, sys, tempfile, threading
from jaxmripp import allocator
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.fopen.restype = ctypes.c_void_p
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
if sys.argv[1] == "keep":
    assert allocator.keep_freed_memory()
together = threading.Barrier(4)
def allocate():
    libc.malloc(1 << 16)
    together.wait()
threads = [threading.Thread(target=allocate) for _ in range(3)]
for thread in threads:
    thread.start()
together.wait()
with tempfile.NamedTemporaryFile("r") as report:
    stream = libc.fopen(report.name.encode(), b"w")
    libc.malloc_info(0, stream)
    libc.fclose(stream)
    print(report.read().count("<heap nr="))
"""


def probe(script: str, mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", script, mode], check=True, capture_output=True,
                         text=True)
    return int(out.stdout)


def test_keep_freed_memory_serves_large_blocks_from_the_heap():
    assert probe(PROBE, "default") >= 96 << 20  # glibc's default: mmap
    assert probe(PROBE, "keep") == 0


def test_keep_freed_memory_caps_the_arenas():
    # Worker threads' arenas mmap any block over 64 MB; capped, most land on the main one.
    assert probe(ARENA_PROBE, "default") >= 3
    assert probe(ARENA_PROBE, "keep") == allocator.ARENAS


@pytest.mark.parametrize("platforms, accelerator", [("cuda", True), ("tpu,cpu", True),
                                                    ("cpu", False), ("CPU,cuda", False)])
def test_tuning_is_skipped_where_jax_computes_on_an_accelerator(monkeypatch, platforms,
                                                                accelerator):
    monkeypatch.setenv("JAX_PLATFORMS", platforms)
    assert allocator.accelerator_expected() is accelerator
    if accelerator:
        assert allocator.keep_freed_memory() is False
