"""Allowed values: one rule per key, checks across keys, and `validate`.

Each rule is (predicate, description of what is allowed); a failed rule raises
`ConfigError` with one line naming the key, the value and the description.
"""

from __future__ import annotations

import math
from typing import Any

from jaxmripp.config.errors import ConfigError, shown
from jaxmripp.config.sections import Config
from jaxmripp.spec.flight import FLIGHT_MODES
from jaxmripp.spec.view import FACADE_TOPS


def _range(lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
    """A number in [lo, hi], each end open on request."""
    def check(v):
        above = v > lo if lo_open else v >= lo
        below = v < hi if hi_open else v <= hi
        return above and below

    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    return check, f"a number in {left}{lo}, {hi}{right}"


def _choice(*options):
    """One of the given strings."""
    return (lambda v: v in options), "one of " + ", ".join(options)


def _each(rule):
    """A list whose every element satisfies rule."""
    check, text = rule
    return (lambda v: all(check(x) for x in v)), f"a list of {text.replace('a number', 'numbers')}"


def _pair(rule):
    """[min, max] with both satisfying rule and min <= max."""
    check, text = rule
    return (lambda v: all(check(x) for x in v) and v[0] <= v[1]), (
        f"[min, max] with min <= max, each {text}"
    )


_POSITIVE = _range(0, lo_open=True)
_NONNEG = _range(0)
_UNIT = _range(0, 1)
METRIC_SINKS = ("jsonl", "tensorboard", "wandb")  # where train.log may send metrics
PLANNERS = ("policy", "random", "greedy", "coordinated", "nbv", "nbv_team", "nbv_ahead",
            "nbv_targets", "mcts", "rig", "oracle", "oracle_ahead", "oracle_rate", "oracle_city")
# Upper references: they read the truth, so tables never count them as baselines.
REFERENCES = ("oracle", "oracle_ahead", "oracle_rate", "oracle_city")

RULES: dict[str, tuple] = {
    "world.size": _range(10, 256),
    "world.layout": _choice("grid", "random"),
    "world.buildings": _range(1, 10_000),
    "world.footprint": _range(1, 16),
    "world.footprint_min": _range(0, 16),
    "world.height_range": _pair(_range(0, 1, lo_open=True)),
    "world.targets": _pair(_range(1, 100_000)),
    "world.target_placement": _choice("facade", "footprint"),
    "world.clearance": _range(0, 8),
    "robots.count": _range(1, 256),
    "robots.budget": _pair(_POSITIVE),
    "robots.turn_cost": _NONNEG,
    "robots.start": (lambda v: len(v) == 3 and all(0 <= x <= 1 for x in v), "3 numbers in [0, 1]"),
    "robots.start_heading": _range(0, 3),
    "robots.pad_spacing": _NONNEG,
    "sensor.model": _choice("raycast", "frustum"),
    "sensor.fov_deg": _range(1, 170),
    "sensor.range": _range(0, 1, lo_open=True),
    "sensor.rays_per_voxel": _range(0.5, 8),
    "sensor.gain_facade": _choice(*FACADE_TOPS),
    "radio.range": _NONNEG,
    "radio.collision_distance": _NONNEG,
    "safety.flight": _choice(*FLIGHT_MODES),
    "candidates.positions": _range(1, 512),
    "candidates.shell": _pair(_range(0, 1, lo_open=True)),
    "candidates.oversample": _range(1, 32),
    "gp.capacity": _range(2, 4096),
    "gp.length_scale": _POSITIVE,
    "gp.heading_scale": _NONNEG,
    "gp.variance": _POSITIVE,
    "gp.noise": _range(1e-6, 10),
    "gp.eval_grid": _range(1, 16),
    "gp.catchup_rounds": _range(0, 64),
    "reward.alpha": _NONNEG,
    "reward.beta": _NONNEG,
    "reward.gamma": _NONNEG,
    "reward.utility_norm": _POSITIVE,
    "episode.max_steps": _range(1, 4096),
    "policy.width": _range(4, 4096),
    "policy.heads": _range(1, 64),
    "policy.layers": _range(0, 16),
    "policy.ff_mult": _range(1, 16),
    "policy.ahead_branches": _range(0, 4096),
    "policy.ahead_discount": _NONNEG,
    "policy.ahead_facade_weight": _NONNEG,
    "policy.belief_strength": _POSITIVE,
    "ppo.algo": _choice("ippo", "mappo"),
    "ppo.learning_rate": _range(0, 1, lo_open=True),
    "ppo.lr_decay": _range(0, 1, lo_open=True),
    "ppo.lr_decay_every": _range(1, 10**9),
    "ppo.clip": _range(0, 1, lo_open=True),
    "ppo.epochs": _range(1, 100),
    "ppo.minibatches": _range(1, 4096),
    "ppo.discount": _UNIT,
    "ppo.gae_lambda": _UNIT,
    "ppo.entropy_coef": _NONNEG,
    "ppo.value_coef": _NONNEG,
    "ppo.max_grad_norm": _POSITIVE,
    "ppo.teacher_coef": _NONNEG,
    "ppo.teacher_updates": _NONNEG,
    "ppo.teacher": _choice("nbv", "nbv_ahead", "nbv_targets", "oracle_rate", "oracle_city"),
    "ppo.teacher_facade": _NONNEG,
    "ppo.search_coef": _NONNEG,
    "ppo.search_simulations": _range(2, 4096),
    "ppo.search_value": _choice("model", "learned"),
    "train.seed": _range(0, 2**31 - 1),
    "train.envs": _range(1, 1 << 20),
    "train.rollout_steps": _range(1, 4096),
    "train.reset_share": _range(0, 1, lo_open=True),
    "train.updates": _range(0, 10**9),
    "train.updates_per_chunk": _range(1, 10**6),
    "train.keep_checkpoints": _range(1, 1000),
    "train.log": (lambda v: len(set(v)) == len(v) and all(x in METRIC_SINKS for x in v),
                  "a list of distinct names from " + ", ".join(METRIC_SINKS)),
    "train.blocks": _range(0, 1 << 20),
    "train.eval_worlds": _range(1, 100_000),
    "train.eval_budget": _POSITIVE,
    "eval.planners": (
        lambda v: len(v) > 0 and all(p in PLANNERS for p in v),
        "a non-empty list from " + ", ".join(PLANNERS),
    ),
    "eval.team_sizes": _each(_range(1, 256)),
    "eval.world_sizes": _each(_range(10, 256)),
    "eval.radio_ranges": _each(_NONNEG),
    "eval.budgets": _each(_POSITIVE),
    "eval.worlds": _range(1, 100_000),
    "eval.trials": _range(1, 100_000),
    "eval.seed": _range(0, 2**31 - 1),
    "eval.layout": _choice("grid", "random"),
    "eval.greedy_kappa": _NONNEG,
    "eval.greedy_lambda": _NONNEG,
    "eval.coordinated_kappa": _NONNEG,
    "eval.coordinated_lambda": _NONNEG,
    "eval.coordinated_mu": _NONNEG,
    "eval.nbv_facade": _NONNEG,
    "eval.nbv_team_facade": _NONNEG,
    "eval.nbv_ahead_discount": _NONNEG,
    "eval.nbv_ahead_branches": _range(1, 4096),
    "eval.nbv_ahead_flights": _range(2, 4),
    "eval.nbv_targets_strength": _POSITIVE,
    "eval.nbv_targets_facade": _NONNEG,
    "eval.nbv_targets_discount": _NONNEG,
    "eval.nbv_targets_branches": _range(1, 4096),
    "eval.oracle_ahead_branches": _range(1, 4096),
    "eval.mcts_simulations": _range(1, 4096),
    "eval.mcts_depth": _range(1, 64),
    "eval.mcts_considered": _range(1, 512),
    "eval.mcts_kappa": _NONNEG,
    "eval.budget_mode": _choice("team", "per_robot"),
    "eval.zip_with_size": (lambda v: all(x in ("team_sizes", "radio_ranges", "budgets")
                                         for x in v),
                           "a list from team_sizes, radio_ranges, budgets"),
    "eval.pairs": (lambda v: all(x.count(":") == 1 and all(x.split(":")) for x in v),
                   'a list of "a:b" planner pairs'),
    "eval.batch": _range(0, 10**6),
}


def _world_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """The world's sizes must fit together, and its windows suit the sensor."""
    problems = []
    w = cfg.world
    if w.footprint + 2 * w.clearance >= w.size:
        problems.append(("world.size", w.size,
                         f"larger than footprint + 2 * clearance = {w.footprint + 2 * w.clearance}"))
    lots = (w.size - w.clearance) // (w.footprint + w.clearance)
    if w.n_buildings > lots * lots:
        problems.append(("world.buildings", w.buildings,
                         f"at most {lots * lots} buildings fit a {w.size}^3 world"))
    if w.footprint_min > w.footprint:
        problems.append(("world.footprint_min", w.footprint_min,
                         f"0 (every side world.footprint) or 1 .. world.footprint = "
                         f"{w.footprint}"))
    if w.target_placement == "facade" and w.clearance < 1:
        problems.append(("world.clearance", w.clearance,
                         "at least 1 with facade windows (every window must face free air)"))
    if w.target_placement == "footprint" and cfg.sensor.model == "raycast":
        problems.append(("world.target_placement", w.target_placement,
                         "facade with sensor.model=raycast (footprint windows are inside walls)"))
    return problems


def _run_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """Radio, network, sweep and training settings that depend on one another."""
    problems = []
    r = cfg.radio
    if r.collision_distance >= r.range:
        problems.append(("radio.collision_distance", r.collision_distance,
                         f"less than radio.range = {r.range}"))
    problems += _pad_checks(cfg)
    if cfg.ppo.privileged_critic and cfg.ppo.algo != "mappo":
        problems.append(("ppo.privileged_critic", True,
                         "false while ppo.algo is ippo (only the central critic reads it)"))
    if cfg.ppo.teacher_coef > 0 and not cfg.policy.view_features:
        problems.append(("ppo.teacher_coef", cfg.ppo.teacher_coef,
                         "0 while policy.view_features is false (the teacher reads them)"))
    # the planners a sweep runs and the one that teaches
    runs = set(cfg.eval.planners) | ({cfg.ppo.teacher} if cfg.ppo.teacher_coef > 0 else set())
    if "nbv_ahead" in runs and cfg.eval.nbv_ahead_branches > cfg.candidates.count:
        problems.append(("eval.nbv_ahead_branches", cfg.eval.nbv_ahead_branches,
                         f"at most the candidate count 4 x candidates.positions = "
                         f"{cfg.candidates.count}"))
    for name in ("nbv_targets", "oracle_rate", "oracle_ahead"):
        key = "oracle_ahead_branches" if name == "oracle_ahead" else "nbv_targets_branches"
        branches = getattr(cfg.eval, key)
        if name in runs and branches > cfg.candidates.count:
            problems.append((f"eval.{key}", branches, f"at most the candidate count 4 x "
                             f"candidates.positions = {cfg.candidates.count}"))
    believes = cfg.policy.belief_features or bool(runs & {"nbv_targets", "oracle_rate",
                                                          "oracle_city"})
    if believes and cfg.world.clearance < 1:
        problems.append(("world.clearance", cfg.world.clearance,
                         "at least 1 with the target belief (policy.belief_features, "
                         "nbv_targets, oracle_rate, oracle_city: buildings must not touch)"))
    if cfg.policy.ahead_branches > cfg.candidates.count:
        problems.append(("policy.ahead_branches", cfg.policy.ahead_branches,
                         f"0 (no lookahead input) to the candidate count 4 x "
                         f"candidates.positions = {cfg.candidates.count}"))
    if cfg.policy.ahead_rated and not (cfg.policy.ahead_branches and
                                       cfg.policy.belief_features):
        problems.append(("policy.ahead_rated", cfg.policy.ahead_rated,
                         "false, or true with policy.ahead_branches > 0 and "
                         "policy.belief_features true (it weighs the lookahead by the belief)"))
    if (cfg.ppo.search_coef > 0 and cfg.ppo.search_value == "model"
            and not cfg.policy.ahead_branches):
        problems.append(("ppo.search_coef", cfg.ppo.search_coef,
                         "0 while policy.ahead_branches is 0 (the model search values "
                         "candidates by the lookahead input; ppo.search_value=learned does not)"))
    problems += _rated_input_checks(cfg)
    if cfg.policy.width % cfg.policy.heads:
        problems.append(("policy.width", cfg.policy.width,
                         f"a multiple of policy.heads = {cfg.policy.heads}"))
    for name in cfg.eval.zip_with_size:
        if len(getattr(cfg.eval, name)) != len(cfg.eval.world_sizes):
            problems.append((f"eval.{name}", getattr(cfg.eval, name),
                             f"one entry per world size ({len(cfg.eval.world_sizes)}), "
                             "because eval.zip_with_size pairs them"))
    if cfg.train.envs % cfg.ppo.minibatches:
        problems.append(("ppo.minibatches", cfg.ppo.minibatches,
                         f"a divisor of train.envs = {cfg.train.envs}"))
    per_minibatch = cfg.train.envs // max(cfg.ppo.minibatches, 1)
    if cfg.train.blocks and per_minibatch % cfg.train.blocks:
        problems.append(("train.blocks", cfg.train.blocks,
                         f"0 or a divisor of the environments per minibatch (train.envs / "
                         f"ppo.minibatches = {per_minibatch})"))
    return problems


def _rated_input_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """A rated lookahead input beside the nbv_targets teacher is the value that teacher
    ranks by, so each of its settings must equal the teacher's."""
    p, e = cfg.policy, cfg.eval
    if not (p.ahead_rated and cfg.ppo.teacher == "nbv_targets" and cfg.ppo.teacher_coef > 0):
        return []
    pairs = (("policy.ahead_facade_weight", p.ahead_facade_weight, "ppo.teacher_facade",
              cfg.ppo.teacher_facade),
             ("policy.ahead_discount", p.ahead_discount, "eval.nbv_targets_discount",
              e.nbv_targets_discount),
             ("policy.ahead_branches", p.ahead_branches, "eval.nbv_targets_branches",
              e.nbv_targets_branches),
             ("policy.belief_strength", p.belief_strength, "eval.nbv_targets_strength",
              e.nbv_targets_strength))
    return [(key, value, f"{teacher_key} = {teacher_value} (the rated input is the value "
             "of the nbv_targets teacher)")
            for key, value, teacher_key, teacher_value in pairs if value != teacher_value]


def _pad_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """Take-off pads (jaxmripp.spec.flight) must keep robots apart and inside the world."""
    n, spacing = cfg.robots.count, cfg.robots.pad_spacing
    if n == 1:
        return []
    if spacing <= cfg.radio.collision_distance:
        return [("robots.pad_spacing", spacing,
                 f"more than radio.collision_distance = {cfg.radio.collision_distance} "
                 f"(robots start on pads that far apart)")]
    side = math.ceil(math.sqrt(n))
    x, _, z = cfg.robots.start
    reach = max(x + spacing * (side - 1), z + spacing * ((n - 1) // side))
    if reach > 1.0:
        return [("robots.pad_spacing", spacing,
                 f"at most {(1.0 - max(x, z)) / (side - 1):.4g} so that {n} pads in a "
                 f"{side}-wide grid from robots.start fit in the unit cube")]
    return []


def _cross_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """Constraints that involve more than one value: (key, value, allowed)."""
    return _world_checks(cfg) + _run_checks(cfg)


def validate(cfg: Config) -> Config:
    """Returns cfg, or raises ConfigError for the first rule or cross-check it breaks."""
    for key, (check, allowed) in RULES.items():
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        if not check(value):
            raise ConfigError(f"{key}: got {shown(value)}; allowed: {allowed}")
    for key, value, allowed in _cross_checks(cfg):
        raise ConfigError(f"{key}: got {shown(value)}; allowed: {allowed}")
    return cfg
