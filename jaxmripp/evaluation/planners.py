"""Planners by name: the trained policy at deployment and the baselines of eval.planners."""

from __future__ import annotations

import jax.numpy as jnp

from jaxmripp.config import Config
from jaxmripp.evaluation import baselines
from jaxmripp.sim.episode import Planner
from jaxmripp.sim.observation import in_sectors
from jaxmripp.sim.params import EnvParams


def policy_planner(network, params, width: int, name: str = "policy") -> Planner:
    """The trained policy at deployment: each robot takes its most probable candidate."""
    from jaxmripp.learn.ppo import apply_batched  # noqa: PLC0415 (ppo imports the env)

    def init(n_robots):
        return jnp.zeros((n_robots, width), jnp.float32)

    def act(key, memory, obs, state=None, dyn=None):
        memory, logits, _ = apply_batched(network, params, memory, obs)
        return memory, baselines.masked_argmax(logits, obs.mask)

    return Planner(name, init, act)


def deployed(planner: Planner, sectors: bool) -> Planner:
    """`planner` as a sweep runs it: with `sectors` (`eval.sectors`) its robots keep to
    their sectors of the world (`in_sectors`), whichever rule then chooses."""
    if not sectors:
        return planner

    def act(key, memory, obs, state, dyn):
        return planner.act(key, memory, in_sectors(obs, state, dyn), state, dyn)

    return Planner(planner.name, planner.init, act)


def baseline_planner(name: str, params: EnvParams, eval_cfg) -> Planner:
    """A non-learning planner for one static shape, by its name in EvalConfig.planners.

    Tuning knobs are read from `eval_cfg` when present (see `EVAL_DEFAULTS`); radio range,
    d_c and turn cost come traced at `act` time, so one planner serves a whole sweep.
    """
    get = lambda field: getattr(eval_cfg, field, EVAL_DEFAULTS.get(field))  # noqa: E731
    if name == "random":
        return baselines.random_planner()
    if name == "greedy":
        return baselines.greedy_planner(get("greedy_kappa"), get("greedy_lambda"))
    if name == "coordinated":
        return baselines.coordinated_planner(params, get("coordinated_kappa"),
                                             get("coordinated_lambda"), get("coordinated_mu"))
    if name == "nbv":
        return baselines.nbv_planner(get("nbv_facade"))
    if name == "nbv_team":
        return baselines.nbv_team_planner(params, get("nbv_team_facade"))
    if name == "nbv_ahead":
        return baselines.nbv_ahead_planner(params, get("nbv_team_facade"), get("nbv_ahead_discount"),
                                 get("nbv_ahead_branches"), get("nbv_ahead_flights"))
    if name == "nbv_targets":
        return baselines.nbv_targets_planner(
            params, get("nbv_targets_strength"), get("nbv_targets_facade"),
            get("nbv_targets_discount"), get("nbv_targets_branches"), get("nbv_ahead_flights"))
    if name == "oracle":
        return baselines.oracle_planner(params)
    if name == "oracle_ahead":
        return baselines.oracle_ahead_planner(params, get("nbv_targets_discount"),
                                              get("oracle_ahead_branches"))
    if name == "oracle_rate":
        return baselines.oracle_rate_planner(
            params, get("nbv_targets_facade"), get("nbv_targets_discount"),
            get("nbv_targets_branches"), get("nbv_ahead_flights"))
    if name == "oracle_city":
        return baselines.oracle_city_planner(params)
    if name == "mcts":
        from jaxmripp.evaluation.tree_search import tree_search_planner  # noqa: PLC0415 (mctx)

        return tree_search_planner(params, simulations=get("mcts_simulations"),
                                   max_depth=get("mcts_depth"),
                                   considered=get("mcts_considered"), kappa=get("mcts_kappa"))
    if name == "rig":
        from jaxmripp.evaluation.rig import rig_planner  # noqa: PLC0415 (mctx)

        return rig_planner(params, iterations=get("rig_iterations"), max_depth=get("rig_depth"),
                           kappa=get("rig_kappa"))
    raise ValueError(f"unknown planner {name!r}; known: random, greedy, coordinated, nbv, "
                     "nbv_team, nbv_ahead, nbv_targets, mcts, rig, oracle, oracle_ahead, "
                     "oracle_rate, oracle_city (and policy, which needs --policy)")


# Defaults of the EvalConfig fields read beyond the base ones; used while
# jaxmripp.config.EvalConfig does not define them.
EVAL_DEFAULTS = {
    "greedy_kappa": 1.0,
    "greedy_lambda": 0.0,
    "coordinated_kappa": 0.3,
    "coordinated_lambda": 0.0,
    "coordinated_mu": 0.3,
    "nbv_facade": 0.0,
    "nbv_team_facade": 2.0,
    "mcts_simulations": 64,
    "mcts_depth": 4,
    "mcts_considered": 4,
    "mcts_kappa": 0.3,
    "rig_iterations": 64,
    "rig_depth": 2,
    "rig_kappa": 0.3,
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
