"""Helpers for benchmark scripts: median timing and JSON-line output.

Importing this module makes the process keep freed memory for reuse, as train.py and
eval.py do (jaxmripp.allocator), so benchmarks time what training runs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from typing import Any, Callable

import jax

from jaxmripp import allocator

allocator.keep_freed_memory()


def emit(name: str, value: float, unit: str, **extra: Any) -> None:
    """Prints one benchmark figure as a JSON line."""
    print(json.dumps({"name": name, "value": round(float(value), 4), "unit": unit, **extra}))
    sys.stdout.flush()


def median_seconds(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of fn() (outputs blocked on), after warm-up calls that compile."""
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def median_cpu_seconds(fn: Callable[[], Any], repeats: int = 5) -> float:
    """Median process CPU time (all threads) of fn(), already compiled; steadier than wall
    time when other work shares the machine."""
    times = []
    for _ in range(repeats):
        start = time.process_time()
        jax.block_until_ready(fn())
        times.append(time.process_time() - start)
    return statistics.median(times)


def batch_arguments(description: str) -> argparse.ArgumentParser:
    """The batch-shape options shared by the environment-side benchmarks."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--size", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=5)
    return parser
