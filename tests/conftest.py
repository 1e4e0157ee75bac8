"""Test-wide settings.

Compiling dominates the suite's time, so XLA's CPU backend compiles without LLVM
optimisation (about half the compile time; the small test configs run a little slower,
which costs far less). Set before any test module imports jax; an XLA_FLAGS the caller
sets keeps its own choice.
"""

import os

_FLAG = "--xla_backend_optimization_level=0"
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FLAG}".strip()
