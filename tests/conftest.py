"""Test-wide settings.

Compiling dominates the suite's time, so XLA's CPU backend compiles without LLVM
optimisation and emits fusions with its classic emitters rather than the MLIR-based ones;
each roughly halves the compile time of an episode, while the small test configs run a
little slower, which costs far less. Set before any test module imports jax; a flag the
caller sets in XLA_FLAGS keeps its own value.

Compiled programs also go to JAX's persistent cache in .pytest_cache/jax, shared by the
test workers and the subprocesses they start: tests that build the same program again (a resumed training run, the
command-line front ends after the library calls) load it instead of compiling. The key
is the program, the flags and the jax version, so a stale entry is never used.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest


def _with_flag(flag: str) -> str:
    return f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()


def _known_to_xla(flag: str) -> bool:
    """Whether the installed jaxlib knows `flag`: XLA aborts a process that sets an unknown
    one, so a child process tries it first (once: the test workers and the processes they
    start inherit the flags set here)."""
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True,
                          env={**os.environ, "XLA_FLAGS": _with_flag(flag)}).returncode == 0


_FLAGS = {"xla_backend_optimization_level": "0", "xla_cpu_use_fusion_emitters": "false"}
_UNSET = [f"--{name}={value}" for name, value in _FLAGS.items()
          if name not in os.environ.get("XLA_FLAGS", "")]
# One probe for all of them (each probe starts a process that imports jax); one at a time
# only where a jaxlib does not know one.
if _UNSET and _known_to_xla(" ".join(_UNSET)):
    os.environ["XLA_FLAGS"] = _with_flag(" ".join(_UNSET))
else:
    for _flag in _UNSET:
        if _known_to_xla(_flag):
            os.environ["XLA_FLAGS"] = _with_flag(_flag)

# An environment variable rather than jax.config, so the command-line runs the tests start
# as subprocesses use the cache too.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"))

# `make test` hands groups of test files to two workers in collection order (--dist
# loadfile, --no-loadscope-reorder: xdist would otherwise start with the groups of most
# tests). A group is a file, or files that train or trace the same programs, which one
# worker then builds once: a process keeps what it traced, while another process would only
# find the compiled program in the cache above and trace it again.
SHARED = {"test_train.py": "smoke_run", "test_train_chunks.py": "smoke_run",
          "test_train_crash.py": "smoke_run", "test_runtime_episode.py": "runtime_env",
          "test_runtime_parity.py": "runtime_env", "test_view.py": "view_env",
          "test_sectors.py": "view_env"}
# Groups whose compilations take longest, started first, so that no long one runs alone at
# the end.
LONGEST_FIRST = ("smoke_run", "test_env.py", "test_lookahead.py", "runtime_env",
                 "test_marl.py", "test_evaluate.py", "test_pipeline.py",
                 "test_runtime_belief_episode.py", "view_env", "test_gp.py",
                 "test_sweep_dynamic.py", "test_physics.py")


def _group(path: str) -> str:
    """The group of the test file at `path` (a path or a node id)."""
    name = path.split("::", 1)[0].rsplit("/", 1)[-1]
    return SHARED.get(name, name)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(_group(item.path.name), len(rank)))


def pytest_xdist_make_scheduler(config, log):
    """--dist loadfile by groups of files rather than by file (xdist's loadgroup reads
    node ids that pytest 9 no longer lets a plugin change)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class FileGroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _group(nodeid)

    return FileGroupScheduling(config, log)


@pytest.fixture(autouse=True)
def _progress_not_quiet_after():
    """A command's --quiet switches progress off for its whole process
    (`progress.set_quiet`); a test that runs one in-process must not silence the tests that
    follow it in the same worker, so each test ends with progress back to its default."""
    yield
    from jaxmripp.parallel import progress  # noqa: PLC0415 (jax after the flags above)

    progress.set_quiet(False)
