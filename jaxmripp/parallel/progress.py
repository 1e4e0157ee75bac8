"""Progress on the terminal: a line for each compilation with its time, and bars with an ETA.

Only process 0 of a run shows progress (the others compute their shards silently), only
on a terminal (logs of batch jobs and CI keep just the lines a run prints anyway) and
only when the caller is not quiet (`train.py --quiet`). Everything goes to stderr, so
stdout keeps a run's results.
"""

from __future__ import annotations

import contextlib
import sys
import time
from typing import Callable, Iterator

import jax
import tqdm


_QUIET = False  # set_quiet: a command's --quiet, for every bar and line it shows


def set_quiet(quiet: bool = True) -> None:
    """Hides (or shows again) every bar and compiling line of this process: a command's
    --quiet, which then need not be passed down to each sweep and training run."""
    global _QUIET  # noqa: PLW0603 (one switch per process, as the terminal is)
    _QUIET = quiet


def shown(quiet: bool = False) -> bool:
    """Whether progress is displayed: neither the caller nor the process quiet, process 0,
    stderr a terminal."""
    return not (quiet or _QUIET) and jax.process_index() == 0 and sys.stderr.isatty()


class Timer:
    """What `compiling` measured: `seconds` once the block has ended."""

    seconds: float = 0.0


@contextlib.contextmanager
def compiling(what: str, quiet: bool = False) -> Iterator[Timer]:
    """Shows `compiling WHAT ...` while the block runs and its seconds when it ends."""
    timer, show = Timer(), shown(quiet)
    if show:
        print(f"compiling {what} ...", end="", file=sys.stderr, flush=True)
    start = time.perf_counter()
    try:
        yield timer
    finally:
        timer.seconds = time.perf_counter() - start
        if show:
            print(f" {timer.seconds:.1f} s", file=sys.stderr, flush=True)


def bar(total: int, desc: str, quiet: bool = False, initial: int = 0, unit: str = "it",
        leave: bool = True) -> tqdm.tqdm:
    """A tqdm bar with an ETA on stderr, displayed only where `shown(quiet)` (a hidden
    bar takes updates and does nothing)."""
    return tqdm.tqdm(total=total, initial=initial, desc=desc, unit=unit, leave=leave,
                     file=sys.stderr, disable=not shown(quiet), dynamic_ncols=True)


def above(log: Callable[[str], None]) -> Callable[[str], None]:
    """`log`, writing its lines above the bars on display instead of through them."""

    def write(line: str) -> None:
        with tqdm.tqdm.external_write_mode(file=sys.stderr):
            log(line)

    return write
