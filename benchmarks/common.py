"""Helpers for benchmark scripts: median timing, JSON-line output and the entry points'
error convention.

Importing this module makes the process keep freed memory for reuse, as train.py and
eval.py do (jaxmripp.allocator), so benchmarks time what training runs.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import statistics
import sys
import time
from typing import Any, Callable

import jax

import figures
from jaxmripp import allocator
from jaxmripp.config.cli import ArgumentParser, fail
from jaxmripp.parallel import progress
from jaxmripp.sim.xla_options import simulation_jit

allocator.keep_freed_memory()


def user_errors() -> tuple[type[Exception], ...]:
    """What a user or a file can get wrong: a config value, a folder of the wrong kind, a
    corrupt export or checkpoint."""
    from jaxmripp import folders  # noqa: PLC0415 (orbax only when a main runs)
    from jaxmripp.config import ConfigError  # noqa: PLC0415
    from jaxmripp.learn.checkpoint import CheckpointError  # noqa: PLC0415
    from jaxmripp.runtime.errors import RuntimeInputError  # noqa: PLC0415

    return ConfigError, folders.FolderError, RuntimeInputError, CheckpointError


def entry_point(main: Callable[..., int | None]) -> Callable[..., int]:
    """A benchmark's main with the entry points' convention (jaxmripp.config.cli): a
    `user_errors()` exception becomes one line `error: ...` and exit status 2; it returns
    0 where main returned None."""
    @functools.wraps(main)
    def guarded(*args, **kwargs) -> int:
        try:
            return main(*args, **kwargs) or 0
        except user_errors() as err:
            return fail(err)
    return guarded


class _Quiet(argparse.Action):
    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, True)
        progress.set_quiet()


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """--quiet: no progress bars or compiling lines (shown only on a terminal anyway); the
    JSON lines on stdout are the same."""
    parser.add_argument("--quiet", action=_Quiet, nargs=0, default=False,
                        help="no progress bars or compiling lines")


@functools.cache
def machine() -> str:
    """What the figures were measured on: the accelerator's kind when JAX runs on one
    (e.g. "NVIDIA H100"), else the host CPU (`figures.host_cpu`)."""
    device = jax.devices()[0]
    return device.device_kind if device.platform != "cpu" else figures.host_cpu()


def emit(name: str, value: float, unit: str, **extra: Any) -> None:
    """Prints one benchmark figure as a JSON line, naming the machine it was measured on."""
    figures.emit(name, value, unit, device=machine(), **extra)


def emit_p(name: str, p: float) -> None:
    """Prints a p-value as a JSON line, to 3 significant digits (emit's rounding would
    print small ones as 0)."""
    print(figures.line(name, float(f"{p:.3g}"), "p", device=machine()))
    sys.stdout.flush()


def emit_text(name: str, text: Any) -> None:
    """Prints a line whose value is not a number (a planner's name, a command, a mapping
    of settings)."""
    print(figures.line(name, text, device=machine()))
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


def batch_arguments(description: str) -> ArgumentParser:
    """The batch-shape options shared by the environment-side benchmarks."""
    parser = ArgumentParser(description=description)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--size", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=5)
    return parser


class RandomTeamStepper:
    """A batch of environments stepped by the random planner: `reset()` then `step()`,
    one jitted, vmapped team step with the state donated (what env.py and scale.py time);
    both compiled with the simulation options that evaluation sweeps use (`xla_options`).
    `package` names the simulator package (env_ab.py steps another commit's copy)."""

    def __init__(self, params, dyn, envs: int, seed: int = 0, package: str = "jaxmripp"):
        baselines = importlib.import_module(f"{package}.evaluation.baselines")
        envmod = importlib.import_module(f"{package}.sim.env")

        self.params, self.dyn, self.envs = params, dyn, envs
        self.key = jax.random.PRNGKey(seed + 1)
        self._keys = jax.random.split(jax.random.PRNGKey(seed), envs)
        self._reset = simulation_jit(jax.vmap(lambda k, d: envmod.reset(k, params, d),
                                              in_axes=(0, None)))
        planner = baselines.random_planner()

        def team_step(key, obs, state, dyn):
            key_act, key_step = jax.random.split(key)
            _, actions = planner.act(key_act, None, obs, state, dyn)
            obs, state, reward, _, _ = envmod.step(key_step, state, actions, params, dyn)
            return obs, state, reward

        self._step = simulation_jit(jax.vmap(team_step, in_axes=(0, 0, 0, None)),
                                    donate_argnums=(1, 2))
        self.obs = self.state = None

    def reset(self):
        self.obs, self.state = jax.block_until_ready(self._reset(self._keys, self.dyn))
        return self.state

    def step(self):
        self.key, key = jax.random.split(self.key)
        self.obs, self.state, reward = self._step(jax.random.split(key, self.envs),
                                                  self.obs, self.state, self.dyn)
        return reward
