"""The sweep primitive: worlds x trials of one planner on several sweep cells at once.

A cell (`Shape`) is a team size N, world size G, radio range rho and team budget B. Cells
that share N and G share the static `EnvParams` and differ only in `DynamicParams`, so
`run_shapes` traces and compiles one function for all of them and runs it vmapped over
the stacked (cell, episode) axis, in memory-sized chunks of the compiled shape.

World w of a sweep comes from the key (seed, w) and trial t on it from (seed, w, t), so
every planner, team size, radio range and budget sees the same worlds (the world only
depends on the world key and the world config). env.reset draws the world, the budget
(fixed here) and the first candidates from the world key; the trial key drives every
step after that (candidate sampling and the planner's randomness).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxmripp.sim.episode import Planner
from jaxmripp.sim import env as envmod
from jaxmripp.sim import episode, xla_options
from jaxmripp.parallel import progress
from jaxmripp.parallel.mesh import data_parallel
from jaxmripp.sim.params import DynamicParams, EnvParams, stack

TRACES: collections.Counter = collections.Counter()  # (planner, N, G) -> times traced


@dataclasses.dataclass(frozen=True)
class Shape:
    """One cell of a sweep: team size N, world size G, radio range rho, team budget B."""

    n_robots: int
    size: int
    radio_range: float
    budget: float

    def label(self) -> str:
        return (f"N = {self.n_robots}, G = {self.size}, rho = {_fmt(self.radio_range)}, "
                f"B = {self.budget:g}")


def _fmt(x: float) -> str:
    return "inf" if math.isinf(x) else f"{x:g}"


def world_keys(seed: int, worlds: int) -> jax.Array:
    """(worlds, 2) keys: world w from (seed, w)."""
    base = jax.random.fold_in(jax.random.PRNGKey(seed), 0)
    return jax.vmap(lambda w: jax.random.fold_in(base, w))(jnp.arange(worlds))


def trial_keys(seed: int, worlds: int, trials: int) -> jax.Array:
    """(worlds, trials, 2) keys: trial t on world w from (seed, w, t)."""
    base = jax.random.fold_in(jax.random.PRNGKey(seed), 1)
    per_world = lambda w: jax.vmap(lambda t: jax.random.fold_in(  # noqa: E731
        jax.random.fold_in(base, w), t))(jnp.arange(trials))
    return jax.vmap(per_world)(jnp.arange(worlds))


@struct.dataclass
class Snapshot:
    """What a picture of an episode needs beyond its trajectory (T = target capacity)."""

    height: jax.Array  # (G, G) building heights
    target_voxel: jax.Array  # (T, 3)
    target_valid: jax.Array  # (T,)
    found_at: jax.Array  # (T,) int32 step a window was first discovered (0 = at reset), -1 never


def run_trial(world_key: jax.Array, trial_key: jax.Array, params: EnvParams,
              dyn: DynamicParams, planner: Planner) -> tuple[episode.EpisodeResult, Snapshot]:
    """One episode on the world of `world_key`, with randomness from `trial_key`."""
    result = episode.run(trial_key, params, dyn, planner, world_key=world_key)
    world = result.final_state.world
    return result.replace(final_state=None), Snapshot(
        world.height, world.target_voxel, world.target_valid, result.found_at)


def auto_batch(params: EnvParams, memory_bytes: float = 1.5e9) -> int:
    """Episodes per vmapped call such that the robots' maps stay within memory_bytes.

    An episode's state holds a team map of W G^3 bytes (`sim.maps`), and planners that
    read the robots' int8 maps derive N G^3 bytes; the sizing leaves room for four copies
    of the latter (carry, step input / output, the reset state), as if the maps were int8.
    """
    per_episode = 4 * params.n_robots * params.size ** 3 + 1e5
    return max(1, int(memory_bytes // per_episode))


# Per-episode safety counts (jaxmripp.spec.flight): EpisodeResult field -> table header.
SAFETY_COUNTS = {
    "obstacle_collisions": "obstacle coll.",
    "robot_collisions_in_range": "robot coll. in range",
    "robot_collisions_out_of_range": "robot coll. out of range",
    "blocked": "blocked",
    "held": "held",
}


def safety_counts(result) -> dict[str, np.ndarray]:
    """{count: (E,) array} from an EpisodeResult (NumPy or JAX leaves)."""
    return {name: np.asarray(getattr(result, name)) for name in SAFETY_COUNTS}


def safety_columns(counts: dict[str, np.ndarray] | None = None) -> str:
    """Markdown cells: the headers (counts None) or the per-episode means."""
    if counts is None:
        return " | ".join(SAFETY_COUNTS.values()) + " |"
    return " | ".join(f"{counts[name].mean():.2f}" for name in SAFETY_COUNTS) + " |"


@dataclasses.dataclass
class ShapeRun:
    """Every episode of one planner on one cell, as NumPy arrays, plus timings."""

    planner: str
    shape: Shape
    worlds: int
    trials: int
    max_steps: int
    discovered: np.ndarray  # (E,) % of the world's windows found; E = worlds * trials
    targets: np.ndarray  # (E,) real windows in the world
    steps: np.ndarray
    safety: dict[str, np.ndarray]  # SAFETY_COUNTS -> (E,) per-episode counts
    distance: np.ndarray
    contacts: np.ndarray
    curve_discovered: np.ndarray  # (E, T + 1) %
    curve_budget: np.ndarray  # (E, T + 1) fraction of the team budget used
    compile_s: float  # of the one compilation shared by the `cells` cells run together
    run_s: float  # this cell's share of the vmapped calls
    ms_per_robot_step: float  # simulation + planning, per scan step per robot
    cells: int = 1  # cells compiled and run together with this one (same N and G)
    plan_ms_per_robot_step: float = float("nan")  # planner.act alone (see time_planning)
    positions: np.ndarray | None = None  # (E, T + 1, N, 3) kept for pictures
    active: np.ndarray | None = None  # (E, T, N)
    snapshot: Snapshot | None = None  # NumPy leaves, leading axis E

    def result_dict(self) -> dict:
        """The layout `evaluate.summary_table` and viz.discovery_curves read."""
        return {"discovered": self.discovered, "safety": self.safety, "distance": self.distance,
                "ms_per_robot_step": self.ms_per_robot_step, "compile_s": self.compile_s,
                "curve_discovered": self.curve_discovered, "curve_budget": self.curve_budget}


def _episode_inputs(shapes, dynamics, seed: int, worlds: int, trials: int):
    """World keys, trial keys and DynamicParams of every (cell, world, trial), flat and
    cell-major: (C * worlds * trials, ...)."""
    per_cell = worlds * trials
    wk = jnp.repeat(world_keys(seed, worlds), trials, axis=0)
    tk = trial_keys(seed, worlds, trials).reshape(-1, 2)
    cell = jnp.repeat(jnp.arange(len(shapes)), per_cell)
    dyn = jax.tree.map(lambda x: x[cell], stack(list(dynamics)))
    return jnp.tile(wk, (len(shapes), 1)), jnp.tile(tk, (len(shapes), 1)), dyn


def run_shapes(planner: Planner, params: EnvParams, shapes: list[Shape],
               dynamics: list[DynamicParams], seed: int, worlds: int, trials: int,
               batch: int = 0, keep_pictures: bool = True,
               compiler_options: dict | None = None) -> list[ShapeRun]:
    """All worlds x trials of one planner on every cell of `shapes` (one `DynamicParams`
    each, all sharing the static `params`): traced and compiled once, run in chunks.

    Episodes are ordered cell-major, then world-major (episode w * trials + t). The last
    chunk is padded with repeats of the last episode so every chunk has the compiled
    shape; a chunk is split over every device (`parallel.mesh`). `compiler_options` go
    to XLA on top of the host's simulation options (`xla_options`; tests pass
    {"xla_backend_optimization_level": 0} to compile faster at the cost of slower code).
    """
    per_cell, total = worlds * trials, len(shapes) * worlds * trials
    inputs = _episode_inputs(shapes, dynamics, seed, worlds, trials)
    data = data_parallel()
    batch = data.round_up(min(total, batch or auto_batch(params)))
    chunks = -(-total // batch)
    pad = chunks * batch - total
    inputs = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]),
                          inputs)

    def batched(world_key, trial_key, dyn):
        TRACES[(planner.name, params.n_robots, params.size)] += 1
        return jax.vmap(lambda w, t, d: run_trial(w, t, params, d, planner))(
            world_key, trial_key, dyn)

    def part(c: int):
        return data.put_split(jax.tree.map(lambda x: x[c * batch:(c + 1) * batch], inputs))

    start = time.perf_counter()
    compiled = jax.jit(batched).lower(*part(0)).compile(
        xla_options.simulation(compiler_options))
    compile_s = time.perf_counter() - start
    outputs = []
    start = time.perf_counter()
    # Large worlds run in many chunks, minutes each: show how far the planner has got.
    with progress.bar(total, f"{planner.name}, N = {params.n_robots}, G = {params.size}",
                      quiet=chunks < 2, unit="episode", leave=False) as bar:
        for c in range(chunks):
            outputs.append(data.gather(jax.block_until_ready(compiled(*part(c)))))
            bar.update(min(batch, total - c * batch))
    run_s = time.perf_counter() - start
    result, snap = jax.tree.map(lambda *xs: np.concatenate(xs)[:total], *outputs)
    ms = 1000.0 * run_s / (chunks * batch * params.max_steps * params.n_robots)
    runs = []
    for c, shape in enumerate(shapes):
        cell = jax.tree.map(lambda x: x[c * per_cell:(c + 1) * per_cell], (result, snap))
        runs.append(_shape_run(planner.name, shape, worlds, trials, params.max_steps, *cell,
                               compile_s=compile_s, run_s=run_s / len(shapes),
                               ms_per_robot_step=ms, cells=len(shapes),
                               keep_pictures=keep_pictures))
    return runs


def _shape_run(planner: str, shape: Shape, worlds: int, trials: int, max_steps: int,
               result, snap, keep_pictures: bool, **timing) -> ShapeRun:
    t = result.trajectory
    return ShapeRun(
        planner=planner, shape=shape, worlds=worlds, trials=trials, max_steps=max_steps,
        discovered=result.discovered_fraction.astype(np.float64) * 100.0,
        targets=snap.target_valid.sum(axis=-1),
        steps=result.steps, safety=safety_counts(result), distance=result.distance,
        contacts=result.contacts,
        curve_discovered=t.discovered_fraction * 100.0, curve_budget=t.budget_used,
        positions=t.position if keep_pictures else None,
        active=t.active if keep_pictures else None,
        snapshot=snap if keep_pictures else None,
        **timing,
    )


@functools.lru_cache(maxsize=8)
def _reset_fn(params: EnvParams):
    return xla_options.simulation_jit(
        jax.vmap(lambda k, d: envmod.reset(k, params, d), in_axes=(0, None)))


def time_planning(planner: Planner, params: EnvParams, dynamics: list[DynamicParams],
                  seed: int, count: int = 4, repeats: int = 3,
                  compiler_options: dict | None = None) -> tuple[list[float], float]:
    """Milliseconds of `planner.act` per robot decision in each cell, measured on `count`
    reset states (vmapped) with one compilation for all cells; returns (ms per robot-step
    per cell, compile seconds). Best of `repeats` runs."""
    keys = jax.random.split(jax.random.PRNGKey(seed), count)
    init = planner.init(params.n_robots)
    memory = jnp.broadcast_to(init, (count, *init.shape))
    act = jax.vmap(planner.act, in_axes=(0, 0, 0, 0, None))
    compiled, compile_s, out = None, 0.0, []
    for dyn in dynamics:
        obs, state = _reset_fn(params)(world_keys(seed, count), dyn)
        if compiled is None:
            start = time.perf_counter()
            compiled = jax.jit(act).lower(keys, memory, obs, state, dyn).compile(
                xla_options.simulation(compiler_options))
            compile_s = time.perf_counter() - start
        best = math.inf
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(compiled(keys, memory, obs, state, dyn))
            best = min(best, time.perf_counter() - start)
        out.append(1000.0 * best / (count * params.n_robots))
    return out, compile_s
