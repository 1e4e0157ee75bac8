"""Evaluation: many episodes per planner in one vmapped, jitted call, and statistics.

Worlds come from fixed seeds: episode k of every planner uses the same key, hence the
same world and budget, so planners are compared on identical problems.

- `compare` / `summary_table` / `tune_greedy`: the quick comparison `pipeline.report` runs
  after training (one key per episode, world and trial randomness together).
- `run_shape`: the sweep primitive. World w comes from the key (seed, w) and trial t on it
  from (seed, w, t) (`world_keys`, `trial_keys`, `run_trial`), so worlds x trials of one
  planner on one `Shape` (N, G, rho, B) are compiled once and run in memory-sized chunks;
  `jaxmripp.evaluation.sweep` loops it over a config's eval section and writes the outputs.
- `baseline_planner`: non-learning planners by name; `welch_ttest`, `mean_ci`: statistics.
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

from jaxmripp.evaluation import baselines
from jaxmripp.sim import episode
from jaxmripp.sim import env as envmod
from jaxmripp.evaluation.baselines import Planner
from jaxmripp.config import Config
from jaxmripp.sim.env import EnvParams


def policy_planner(network, params, width: int, name: str = "policy") -> Planner:
    """The trained policy at deployment: each robot takes its most probable candidate."""
    from jaxmripp.learn.ppo import apply_batched  # ppo imports the env; keep this module light

    def init(n_robots):
        return jnp.zeros((n_robots, width), jnp.float32)

    def act(key, memory, obs, state=None):
        memory, logits, _ = apply_batched(network, params, memory, obs)
        return memory, baselines.masked_argmax(logits, obs.mask)

    return Planner(name, init, act)


def eval_params(cfg: Config, budget: float, layout: str = "random", robots: int | None = None,
                radio_range: float | None = None, size: int | None = None) -> EnvParams:
    """EnvParams for evaluation: fixed team budget, test layout, optional overrides."""
    world = dataclasses.replace(cfg.world, layout=layout, size=size or cfg.world.size,
                                targets=(cfg.world.targets[1],) * 2)
    team = dataclasses.replace(cfg.robots, budget=(budget, budget),
                               count=robots or cfg.robots.count)
    radio = cfg.radio if radio_range is None else dataclasses.replace(cfg.radio,
                                                                      range=radio_range)
    params = EnvParams.from_config(cfg)
    # Enough steps for the whole budget to be spent at the smallest candidate distance.
    steps = max(params.max_steps, int(math.ceil(budget / team.count / cfg.candidates.shell[0])) + 4)
    return dataclasses.replace(params, world=world, robots=team, radio=radio, max_steps=steps,
                               gp=dataclasses.replace(cfg.gp, shared_utility=False))


@functools.partial(jax.jit, static_argnames=("params", "planner"))
def run_episodes(keys: jax.Array, params: EnvParams, planner: Planner):
    """Runs len(keys) episodes in one vmapped call; drops the bulky final states.

    Compiled once per (params, planner, number of keys): pass the same planner object.
    """

    def one(key):
        result = episode.run(key, params, planner)
        return result.replace(final_state=None)

    return jax.vmap(one)(keys)


def episode_keys(seed: int, count: int) -> jax.Array:
    return jax.random.split(jax.random.PRNGKey(seed), count)


def compare(planners: list[Planner], params: EnvParams, keys: jax.Array) -> dict[str, dict]:
    """{planner name: per-episode arrays + planning time per step per robot (ms)}.

    Each planner is compiled ahead of time, so its one run is timed without compilation.
    """
    out = {}
    for planner in planners:
        start = time.perf_counter()
        compiled = run_episodes.lower(keys, params, planner).compile()
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        result = jax.block_until_ready(compiled(keys))
        run_s = time.perf_counter() - start
        steps = max(float(np.asarray(result.steps).sum()) * params.n_robots, 1.0)
        out[planner.name] = {
            "discovered": np.asarray(result.discovered_fraction) * 100.0,
            "obstacle_collisions": np.asarray(result.obstacle_collisions),
            "robot_collisions": np.asarray(result.robot_collisions),
            "distance": np.asarray(result.distance),
            "ms_per_robot_step": 1000.0 * run_s / steps,
            "compile_s": seconds,
            "curve_discovered": np.asarray(result.trajectory.discovered_fraction) * 100.0,
            "curve_budget": np.asarray(result.trajectory.budget_used),
        }
    return out


def summary_table(results: dict[str, dict], title: str = "") -> str:
    """Markdown table: mean +- std % discovered, 95% CI, ms per robot-step, collisions."""
    lines = [f"### {title}" if title else "",
             "| planner | % targets | 95% CI | ms / robot-step | obstacle coll. | robot coll. |",
             "|---|---|---|---|---|---|"]
    for name, r in results.items():
        d = r["discovered"]
        half = 1.96 * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
        lines.append(f"| {name} | {d.mean():.2f} +- {d.std(ddof=1) if len(d) > 1 else 0:.2f} | "
                     f"[{d.mean() - half:.2f}, {d.mean() + half:.2f}] | "
                     f"{r['ms_per_robot_step']:.3f} | {r['obstacle_collisions'].mean():.2f} | "
                     f"{r['robot_collisions'].mean():.2f} |")
    return "\n".join(line for line in lines if line)


def tune_greedy(cfg: Config, kappas, lambdas, worlds: int, seed: int,
                budget: float) -> list[tuple[float, float, float]]:
    """Grid search of greedy's kappa / lambda on training-layout worlds.

    Returns (kappa, lambda, mean % found) rows, best first. The grid is a traced argument
    vmapped next to the worlds, so the whole search is one compilation.
    """
    params = eval_params(cfg, budget, layout=cfg.world.layout)
    grid = np.array([(k, lam) for k in kappas for lam in lambdas], np.float32)
    found = _greedy_grid(episode_keys(seed, worlds), jnp.asarray(grid), params)
    means = np.asarray(found).mean(axis=1) * 100.0
    rows = [(float(k), float(lam), float(m)) for (k, lam), m in zip(grid, means)]
    return sorted(rows, key=lambda r: -r[2])


@functools.partial(jax.jit, static_argnames=("params",))
def _greedy_grid(keys, grid, params: EnvParams):
    def one(weights, key):
        planner = baselines.greedy_planner(weights[0], weights[1])
        return episode.run(key, params, planner).discovered_fraction

    return jax.vmap(lambda w: jax.vmap(lambda k: one(w, k))(keys))(grid)


# ---------------------------------------------------------------------------------------
# Sweeps: worlds x trials per shape, one compilation per (planner, shape).
#
# World w of a sweep comes from the key (seed, w) and trial t on it from (seed, w, t), so
# every planner, team size, radio range and budget sees the same worlds (the world only
# depends on the world key and the world config). env.reset draws the world, the budget
# (fixed here) and the first candidates from the world key; the trial key drives every
# step after that (candidate sampling and the planner's randomness).

TRACES: collections.Counter = collections.Counter()  # (planner, shape) -> times traced


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
    per_world = lambda w: jax.vmap(lambda t: jax.random.fold_in(
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
              planner: Planner) -> tuple[episode.EpisodeResult, Snapshot]:
    """One episode on the world of `world_key`, with randomness from `trial_key`."""
    result = episode.run(trial_key, params, planner, world_key=world_key)
    world = result.final_state.world
    return result.replace(final_state=None), Snapshot(
        world.height, world.target_voxel, world.target_valid, result.found_at)


def auto_batch(params: EnvParams, memory_bytes: float = 1.5e9) -> int:
    """Episodes per vmapped call such that the per-robot maps stay within memory_bytes.

    An episode holds N occupancy maps of G^3 bytes; the scan keeps about four copies
    alive (carry, step input / output, the reset state).
    """
    per_episode = 4 * params.n_robots * params.size ** 3 + 1e5
    return max(1, int(memory_bytes // per_episode))


@dataclasses.dataclass
class ShapeRun:
    """Every episode of one planner on one shape, as NumPy arrays, plus timings."""

    planner: str
    shape: Shape
    worlds: int
    trials: int
    max_steps: int
    discovered: np.ndarray  # (E,) % of the world's windows found; E = worlds * trials
    targets: np.ndarray  # (E,) real windows in the world
    steps: np.ndarray
    obstacle_collisions: np.ndarray
    robot_collisions: np.ndarray
    distance: np.ndarray
    contacts: np.ndarray
    curve_discovered: np.ndarray  # (E, T + 1) %
    curve_budget: np.ndarray  # (E, T + 1) fraction of the team budget used
    compile_s: float
    run_s: float
    ms_per_robot_step: float  # simulation + planning, per scan step per robot
    plan_ms_per_robot_step: float = float("nan")  # planner.act alone (see time_planning)
    positions: np.ndarray | None = None  # (E, T + 1, N, 3) kept for pictures
    active: np.ndarray | None = None  # (E, T, N)
    snapshot: Snapshot | None = None  # NumPy leaves, leading axis E

    def result_dict(self) -> dict:
        """The layout `summary_table` and viz.discovery_curves read."""
        return {"discovered": self.discovered, "obstacle_collisions": self.obstacle_collisions,
                "robot_collisions": self.robot_collisions, "distance": self.distance,
                "ms_per_robot_step": self.ms_per_robot_step, "compile_s": self.compile_s,
                "curve_discovered": self.curve_discovered, "curve_budget": self.curve_budget}


def run_shape(planner: Planner, params: EnvParams, shape: Shape, seed: int, worlds: int,
              trials: int, batch: int = 0, keep_pictures: bool = True,
              compiler_options: dict | None = None) -> ShapeRun:
    """All worlds x trials of one planner on one shape: compiled once, run in chunks.

    Episodes are ordered world-major (episode w * trials + t). The last chunk is padded
    with repeats of the last episode so every chunk has the compiled shape.
    `compiler_options` go to XLA (tests pass {"xla_backend_optimization_level": 0} to
    compile faster at the cost of slower code).
    """
    wk = world_keys(seed, worlds)
    tk = trial_keys(seed, worlds, trials).reshape(-1, 2)
    wk = jnp.repeat(wk, trials, axis=0)
    total = worlds * trials
    batch = min(total, batch or auto_batch(params))
    chunks = -(-total // batch)
    pad = chunks * batch - total
    if pad:
        wk = jnp.concatenate([wk, jnp.repeat(wk[-1:], pad, axis=0)])
        tk = jnp.concatenate([tk, jnp.repeat(tk[-1:], pad, axis=0)])

    def batched(world_key, trial_key):
        TRACES[(planner.name, shape)] += 1
        return jax.vmap(lambda w, t: run_trial(w, t, params, planner))(world_key, trial_key)

    start = time.perf_counter()
    compiled = jax.jit(batched).lower(wk[:batch], tk[:batch]).compile(compiler_options)
    compile_s = time.perf_counter() - start
    outputs = []
    start = time.perf_counter()
    for c in range(chunks):
        part = slice(c * batch, (c + 1) * batch)
        out = jax.block_until_ready(compiled(wk[part], tk[part]))
        outputs.append(jax.tree.map(np.asarray, out))
    run_s = time.perf_counter() - start
    result, snap = jax.tree.map(lambda *xs: np.concatenate(xs)[:total], *outputs)
    t = result.trajectory
    scan_steps = chunks * batch * params.max_steps * params.n_robots
    return ShapeRun(
        planner=planner.name, shape=shape, worlds=worlds, trials=trials,
        max_steps=params.max_steps,
        discovered=result.discovered_fraction.astype(np.float64) * 100.0,
        targets=snap.target_valid.sum(axis=-1),
        steps=result.steps, obstacle_collisions=result.obstacle_collisions,
        robot_collisions=result.robot_collisions, distance=result.distance,
        contacts=result.contacts,
        curve_discovered=t.discovered_fraction * 100.0, curve_budget=t.budget_used,
        compile_s=compile_s, run_s=run_s, ms_per_robot_step=1000.0 * run_s / scan_steps,
        positions=t.position if keep_pictures else None,
        active=t.active if keep_pictures else None,
        snapshot=snap if keep_pictures else None,
    )


@functools.lru_cache(maxsize=8)
def _reset_fn(params: EnvParams):
    return jax.jit(jax.vmap(lambda k: envmod.reset(k, params)))


def time_planning(planner: Planner, params: EnvParams, seed: int, count: int = 4,
                  repeats: int = 3, compiler_options: dict | None = None) -> tuple[float, float]:
    """Milliseconds of `planner.act` per robot decision, measured on `count` reset states
    (vmapped); returns (ms per robot-step, compile seconds). Best of `repeats` runs."""
    obs, state = _reset_fn(params)(world_keys(seed, count))
    memory = jnp.broadcast_to(planner.init(params.n_robots),
                              (count, *planner.init(params.n_robots).shape))
    keys = jax.random.split(jax.random.PRNGKey(seed), count)
    start = time.perf_counter()
    act = jax.jit(jax.vmap(planner.act)).lower(keys, memory, obs, state).compile(
        compiler_options)
    compile_s = time.perf_counter() - start
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(act(keys, memory, obs, state))
        best = min(best, time.perf_counter() - start)
    return 1000.0 * best / (count * params.n_robots), compile_s


# ---------------------------------------------------------------------------------------
# Planners by name and statistics


def baseline_planner(name: str, params: EnvParams, eval_cfg) -> Planner:
    """A non-learning planner for one shape, by its name in EvalConfig.planners.

    Tuning knobs are read from `eval_cfg` when present (see `EVAL_DEFAULTS`).
    """
    get = lambda field: getattr(eval_cfg, field, EVAL_DEFAULTS.get(field))
    kappa = get("greedy_kappa")
    if name == "random":
        return baselines.random_planner()
    if name == "greedy":
        return baselines.greedy_planner(kappa, get("greedy_lambda"))
    if name == "coordinated":
        return baselines.coordinated_planner(params, get("coordinated_kappa"),
                                             get("coordinated_lambda"), get("coordinated_mu"))
    if name == "oracle":
        return baselines.oracle_planner(params)
    if name == "mcts":
        from jaxmripp.evaluation.tree_search import tree_search_planner  # noqa: PLC0415 (mctx)

        return tree_search_planner(params, simulations=get("mcts_simulations"),
                                   max_depth=get("mcts_depth"),
                                   considered=get("mcts_considered"), kappa=get("mcts_kappa"))
    raise ValueError(f"unknown planner {name!r}; known: random, greedy, coordinated, mcts, "
                     "oracle (and policy, which needs --policy)")


# Defaults of the EvalConfig fields this module reads beyond the base ones; used while
# jaxmripp.config.EvalConfig does not define them.
EVAL_DEFAULTS = {
    "greedy_kappa": 1.0,
    "greedy_lambda": 0.0,
    "coordinated_kappa": 0.3,
    "coordinated_lambda": 0.0,
    "coordinated_mu": 0.3,
    "mcts_simulations": 16,
    "mcts_depth": 2,
    "mcts_considered": 4,
    "mcts_kappa": 0.3,
    "budget_mode": "team",
    "zip_with_size": (),
    "pairs": (),
    "batch": 0,
    "time_planning": True,
    "render": True,
}


def eval_setting(cfg: Config, field: str):
    """cfg.eval.<field>, or its default while EvalConfig lacks the field."""
    return getattr(cfg.eval, field, EVAL_DEFAULTS.get(field))


def welch_ttest(a, b) -> tuple[float, float, float]:
    """Welch's unequal-variance t-test: (t, degrees of freedom, two-sided p-value).

    Matches scipy.stats.ttest_ind(a, b, equal_var=False). Two constant samples give
    t = +-inf and p = 0 when their means differ, t = 0 and p = 1 when they do not.
    """
    from scipy import special  # noqa: PLC0415

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    diff = a.mean() - b.mean()
    se2 = va + vb
    if se2 == 0:
        return (0.0, float("nan"), 1.0) if diff == 0 else (math.copysign(math.inf, diff),
                                                           float("nan"), 0.0)
    t = diff / math.sqrt(se2)
    df = se2 ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    p = float(special.betainc(df / 2, 0.5, df / (df + t * t)))  # = 2 P(T_df > |t|)
    return float(t), float(df), p


def mean_ci(x, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, std, half-width of the Student-t confidence interval of the mean)."""
    from scipy import stats  # noqa: PLC0415

    x = np.asarray(x, np.float64)
    if len(x) < 2:
        return float(x.mean()), 0.0, float("nan")
    std = float(x.std(ddof=1))
    half = float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * std / math.sqrt(len(x)))
    return float(x.mean()), std, half
