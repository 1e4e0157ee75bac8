"""Evaluation: many episodes per planner in one vmapped, jitted call.

Worlds come from fixed seeds: episode k of every planner uses the same key, hence the
same world and budget, so planners are compared on identical problems.

- `eval_params` / `eval_dynamic`: the static and dynamic env parameters of an evaluation
  (test layout, fixed team budget); `max_steps` covers the largest budget of a sweep.
- `compare` / `summary_table`: the quick comparison `pipeline.report` runs after training
  (one key per episode, world and trial randomness together); `tune`, `tune_greedy`,
  `tune_nbv`, `tune_nbv_ahead`, `tune_nbv_targets`, `tune_mcts`, `tune_rig`: the
  baselines' weights, searched on training-layout worlds.
- The sweep primitive (cells of N, G, rho, B compiled once per N, G) is
  `jaxmripp.evaluation.cells`; planners by name are in `jaxmripp.evaluation.planners`;
  statistics in `jaxmripp.evaluation.stats`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxmripp.config import Config
from jaxmripp.evaluation import baselines
from jaxmripp.evaluation.cells import SAFETY_COUNTS, safety_columns, safety_counts
from jaxmripp.evaluation.planners import eval_setting
from jaxmripp.parallel.mesh import data_parallel
from jaxmripp.sim.episode import Planner
from jaxmripp.sim import episode, xla_options
from jaxmripp.sim.params import DynamicParams, EnvParams


def eval_params(cfg: Config, budgets: float | Sequence[float], layout: str = "random",
                robots: int | None = None, size: int | None = None) -> EnvParams:
    """Static EnvParams for evaluation: test layout, every window slot filled, per-robot
    utility GPs, and enough steps for the largest of `budgets` (team budgets) to be spent
    at the smallest candidate distance; smaller budgets' episodes just end earlier."""
    largest = float(np.max(budgets))
    count = robots or cfg.robots.count
    params = EnvParams.from_config(cfg)
    world = dataclasses.replace(cfg.world, layout=layout, size=size or cfg.world.size,
                                targets=(cfg.world.targets[1],) * 2)
    steps = max(params.max_steps,
                int(math.ceil(largest / count / cfg.candidates.shell[0])) + 4)
    return dataclasses.replace(params, world=world, max_steps=steps,
                               robots=dataclasses.replace(params.robots, count=count),
                               gp=dataclasses.replace(cfg.gp, shared_utility=False))


def eval_dynamic(cfg: Config, budget: float, radio_range: float | None = None) -> DynamicParams:
    """DynamicParams for evaluation: a fixed team budget, optionally another radio range."""
    dyn = DynamicParams.from_config(cfg).with_budget(budget)
    return dyn if radio_range is None else dyn.with_values(radio_range=radio_range)


@functools.partial(jax.jit, static_argnames=("params", "planner"))
def run_episodes(keys: jax.Array, params: EnvParams, dyn: DynamicParams, planner: Planner):
    """Runs len(keys) episodes in one vmapped call. Of each final state only what a picture
    of the episode needs is kept (the world, the robots and the windows found): maps, GPs,
    histories and candidates are dropped, being the bulk of it.

    Compiled once per (params, planner, number of keys): pass the same planner object.
    """

    def one(key):
        result = episode.run(key, params, dyn, planner)
        return result.replace(final_state=result.final_state.replace(
            team_map=None, building_top=None, history_pose=None, history_utility=None,
            utility_gp=None, comm_gp=None, candidates=None))

    return jax.vmap(one)(keys)


def episode_keys(seed: int, count: int) -> jax.Array:
    return jax.random.split(jax.random.PRNGKey(seed), count)


def compare(planners: list[Planner], params: EnvParams, dyn: DynamicParams,
            keys: jax.Array, compiler_options: dict | None = None) -> dict[str, dict]:
    """{planner name: per-episode arrays, planning time per step per robot (ms) and the
    first episode (an unbatched `episode.EpisodeResult` with run_episodes' slim final
    state, for a picture)}.

    Each planner is compiled ahead of time, so its one run is timed without compilation.
    The episodes are split over every device (`parallel.mesh`).
    """
    data = data_parallel()
    count = len(keys)
    keys, dyn = data.put_batch(keys), data.put_replicated(dyn)
    out = {}
    for planner in planners:
        start = time.perf_counter()
        compiled = run_episodes.lower(keys, params, dyn, planner).compile(
            xla_options.simulation(compiler_options))
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        result = jax.block_until_ready(compiled(keys, dyn))
        run_s = time.perf_counter() - start
        result = data.gather(result, count)
        steps = max(float(result.steps.sum()) * params.n_robots, 1.0)
        out[planner.name] = {
            "discovered": np.asarray(result.discovered_fraction) * 100.0,
            "safety": safety_counts(result),
            "distance": np.asarray(result.distance),
            "ms_per_robot_step": 1000.0 * run_s / steps,
            "compile_s": seconds,
            "curve_discovered": np.asarray(result.trajectory.discovered_fraction) * 100.0,
            "curve_budget": np.asarray(result.trajectory.budget_used),
            "first_episode": jax.tree.map(lambda x: x[0], result),
        }
    return out


def summary_table(results: dict[str, dict], title: str = "") -> str:
    """Markdown table: mean +- std % discovered, 95% CI, ms per robot-step, safety counts."""
    lines = [f"### {title}" if title else "",
             "| planner | % targets | 95% CI | ms / robot-step | " + safety_columns(),
             "|---|---|---|---|" + "---|" * len(SAFETY_COUNTS)]
    for name, r in results.items():
        d = r["discovered"]
        half = 1.96 * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
        lines.append(f"| {name} | {d.mean():.2f} +- {d.std(ddof=1) if len(d) > 1 else 0:.2f} | "
                     f"[{d.mean() - half:.2f}, {d.mean() + half:.2f}] | "
                     f"{r['ms_per_robot_step']:.3f} | " + safety_columns(r["safety"]))
    return "\n".join(line for line in lines if line)


def tune(cfg: Config, planner_of, grid, worlds: int, seed: int,
         budget: float) -> list[tuple[tuple[float, ...], float]]:
    """Grid search of a baseline's weights on `cfg.world.layout` worlds.

    planner_of(weights (k,) traced, params) -> Planner; grid: (G, k) weight rows. Returns
    (weights, mean % found) rows, best first. The grid is a traced argument vmapped next to
    the worlds, so the whole search is one compilation.
    """
    params = eval_params(cfg, budget, layout=cfg.world.layout)
    grid = np.asarray(grid, np.float32)
    found = _grid_search(episode_keys(seed, worlds), jnp.asarray(grid), params,
                         eval_dynamic(cfg, budget), planner_of)
    means = np.asarray(found).mean(axis=1) * 100.0
    rows = [(tuple(float(w) for w in weights), float(m)) for weights, m in zip(grid, means)]
    return sorted(rows, key=lambda r: -r[1])


def tune_greedy(cfg: Config, kappas, lambdas, worlds: int, seed: int,
                budget: float) -> list[tuple[float, float, float]]:
    """`tune` over greedy's kappa x lambda: (kappa, lambda, mean % found) rows, best first."""
    grid = [(k, lam) for k in kappas for lam in lambdas]
    rows = tune(cfg, _greedy_of, grid, worlds, seed, budget)
    return [(k, lam, m) for (k, lam), m in rows]


def tune_nbv(cfg: Config, facade_weights, team: bool, worlds: int, seed: int,
             budget: float) -> list[tuple[float, float]]:
    """`tune` over the facade weight of nbv (team=False) or nbv_team: (weight, mean % found)
    rows, best first."""
    rows = tune(cfg, _nbv_team_of if team else _nbv_of, [(w,) for w in facade_weights],
                worlds, seed, budget)
    return [(w, m) for (w,), m in rows]


def tune_mcts(cfg: Config, simulations, depths, worlds: int, seed: int, budget: float
              ) -> list[tuple[int, int, float, float]]:
    """The tree search's simulations x depth on `cfg.world.layout` worlds (static shapes:
    one compilation per pair): (simulations, depth, mean % found, ms per robot-step of
    simulation and planning) rows, best first."""
    from jaxmripp.evaluation.tree_search import tree_search_planner  # noqa: PLC0415 (mctx)

    params = eval_params(cfg, budget, layout=cfg.world.layout)
    planners = [tree_search_planner(params, simulations=n, max_depth=d,
                                    considered=cfg.eval.mcts_considered, kappa=cfg.eval.mcts_kappa,
                                    name=f"{n}x{d}") for n in simulations for d in depths]
    results = compare(planners, params, eval_dynamic(cfg, budget), episode_keys(seed, worlds))
    rows = [(n, d, float(results[f"{n}x{d}"]["discovered"].mean()),
             float(results[f"{n}x{d}"]["ms_per_robot_step"])) for n in simulations for d in depths]
    return sorted(rows, key=lambda r: -r[2])


def tune_rig(cfg: Config, iterations, depths, worlds: int, seed: int, budget: float
             ) -> list[tuple[int, int, float]]:
    """`tune` over RIG's iterations x depth on `cfg.world.layout` worlds: (iterations,
    depth, mean % found) rows, best first. One compilation: the tree is allocated for the
    largest iterations and depth and each grid row limits its rounds and depth as traced
    values, so every row costs as much as the largest (time a setting with `compare`)."""
    grid = [(n, d) for n in iterations for d in depths]
    planner_of = functools.partial(_rig_of, iterations=max(iterations), max_depth=max(depths),
                                   kappa=eval_setting(cfg, "rig_kappa"))
    rows = tune(cfg, planner_of, grid, worlds, seed, budget)
    return [(int(n), int(d), m) for (n, d), m in rows]


def tune_nbv_ahead(cfg: Config, discounts, branches: int, flights: int, worlds: int,
                   seed: int, budget: float) -> list[tuple[float, float]]:
    """`tune` over nbv_ahead's discount with `branches` and `flights` (static) and
    eval.nbv_team_facade: (discount, mean % found) rows, best first."""
    planner_of = functools.partial(_nbv_ahead_of, facade=cfg.eval.nbv_team_facade,
                                   branches=branches, flights=flights)
    rows = tune(cfg, planner_of, [(d,) for d in discounts], worlds, seed, budget)
    return [(d, m) for (d,), m in rows]


def tune_nbv_targets(cfg: Config, strengths, facades, discounts, worlds: int, seed: int,
                     budget: float) -> list[tuple[float, float, float, float]]:
    """`tune` over nbv_targets' prior strength x facade weight x discount with
    eval.nbv_targets_branches and eval.nbv_ahead_flights (static): (strength, facade,
    discount, mean % found) rows, best first."""
    grid = [(k, w, d) for k in strengths for w in facades for d in discounts]
    planner_of = functools.partial(_nbv_targets_of, branches=cfg.eval.nbv_targets_branches,
                                   flights=cfg.eval.nbv_ahead_flights)
    rows = tune(cfg, planner_of, grid, worlds, seed, budget)
    return [(k, w, d, m) for (k, w, d), m in rows]


def _nbv_targets_of(weights, params, branches, flights):
    return baselines.nbv_targets_planner(params, weights[0], weights[1], weights[2], branches,
                                         flights)


def _nbv_ahead_of(weights, params, facade, branches, flights):
    return baselines.nbv_ahead_planner(params, facade, weights[0], branches, flights)


def _rig_of(weights, params, iterations, max_depth, kappa):
    from jaxmripp.evaluation.rig import rig_planner  # noqa: PLC0415 (mctx)

    return rig_planner(params, iterations, max_depth, kappa, rounds=weights[0],
                       depth_limit=weights[1])


def _nbv_of(weights, params):
    return baselines.nbv_planner(weights[0])


def _nbv_team_of(weights, params):
    return baselines.nbv_team_planner(params, weights[0])


def _greedy_of(weights, params):
    return baselines.greedy_planner(weights[0], weights[1])


@functools.partial(jax.jit, static_argnames=("params", "planner_of"))
def _grid_search(keys, grid, params: EnvParams, dyn: DynamicParams, planner_of):
    def one(weights, key):
        return episode.run(key, params, dyn, planner_of(weights, params)).discovered_fraction

    return jax.vmap(lambda w: jax.vmap(lambda k: one(w, k))(keys))(grid)
