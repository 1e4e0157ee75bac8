"""Typed, frozen, validated configuration.

Every section is a frozen dataclass, so a whole `Config` is hashable and can be passed to
`jax.jit` as a static argument. YAML files and dotted command-line overrides
(`world.size=64`) are merged into the defaults and validated once, on load: a bad value
raises `ConfigError` with one line naming the key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from pathlib import Path
from typing import Any

import yaml

REFERENCE_SIZE = 50  # the paper's grid; counts below are quoted at this size


class ConfigError(ValueError):
    """A configuration value is unknown, mistyped or out of range."""


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    size: int = 50  # G: voxels per side of the unit cube
    layout: str = "grid"  # grid (training) | random (test)
    buildings: int = 25  # at G = 50; scaled by (G / 50)^2 to keep the density
    footprint: int = 3  # building footprint side, voxels
    height_range: tuple[float, float] = (0.2, 0.99)  # fraction of the world height
    targets: tuple[int, int] = (250, 250)  # windows at G = 50 (min, max); scaled like buildings
    target_placement: str = "facade"  # facade (line of sight) | footprint (reference)
    clearance: int = 1  # free voxels kept around every footprint and the world border

    @property
    def scale(self) -> float:
        return (self.size / REFERENCE_SIZE) ** 2

    @property
    def n_buildings(self) -> int:
        return max(1, round(self.buildings * self.scale))

    @property
    def target_capacity(self) -> int:
        return max(1, round(self.targets[1] * self.scale))

    @property
    def target_min(self) -> int:
        return max(1, round(self.targets[0] * self.scale))


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    count: int = 3  # N
    budget: tuple[float, float] = (10.0, 10.0)  # team budget B (min, max), split evenly
    turn_cost: float = 0.05  # charged when the heading changes
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_heading: int = 1  # index into headings (0, pi/2, pi, 3pi/2)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    model: str = "raycast"  # raycast (occlusion) | frustum (reference, no occlusion)
    fov_deg: float = 90.0
    range: float = 0.24  # fraction of the world size
    rays_per_voxel: float = 2.0  # ray grid density at the far end of the range


@dataclasses.dataclass(frozen=True)
class RadioConfig:
    range: float = 0.3  # rho; .inf for global communication
    relay: bool = False  # forward everything known (multi-hop) instead of single hop
    collision_distance: float = 0.05  # d_c


@dataclasses.dataclass(frozen=True)
class CandidateConfig:
    positions: int = 20  # K; L = 4 K candidate poses
    shell: tuple[float, float] = (0.19, 0.21)  # sampling distance range
    oversample: int = 3  # positions drawn per kept position before masking

    @property
    def count(self) -> int:
        return 4 * self.positions


@dataclasses.dataclass(frozen=True)
class GPConfig:
    capacity: int = 64  # H
    length_scale: float = 0.2
    heading_scale: float = 0.1  # distance added per radian of heading difference
    variance: float = 1.0
    noise: float = 0.01
    eval_grid: int = 3  # trace evaluation set: eval_grid^3 positions x 4 headings
    catchup_rounds: int = 1  # peer rounds per step beyond N - 1 (env._feed_gps)
    shared_utility: bool = False  # one utility GP per environment fed by all robots


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    alpha: float = 20.0  # exploration (utility GP trace drop)
    beta: float = 0.02  # per newly discovered target
    gamma: float = 1.0  # communication GP trace drop
    utility_norm: float = 16.0


@dataclasses.dataclass(frozen=True)
class EpisodeConfig:
    max_steps: int = 32  # T_max


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    width: int = 64
    heads: int = 4
    layers: int = 1
    ff_mult: int = 4
    comm_features: bool = True  # False: ablation without communication-GP inputs


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    algo: str = "ippo"  # ippo | mappo
    learning_rate: float = 3e-4
    lr_decay: float = 0.96
    lr_decay_every: int = 512  # optimiser steps
    clip: float = 0.2
    epochs: int = 4
    minibatches: int = 4
    discount: float = 0.99
    gae_lambda: float = 0.95
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    max_grad_norm: float = 0.5


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    name: str = "default"
    envs: int = 64
    rollout_steps: int = 16
    reset_share: float = 0.25  # most environments restarted per rollout step, as a share
    updates: int = 100
    updates_per_chunk: int = 10
    keep_checkpoints: int = 3
    eval_worlds: int = 100
    eval_budget: float = 10.0


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    planners: tuple[str, ...] = ("policy", "greedy", "random")
    team_sizes: tuple[int, ...] = (3,)
    world_sizes: tuple[int, ...] = (50,)
    radio_ranges: tuple[float, ...] = (math.inf,)
    budgets: tuple[float, ...] = (10.0,)
    worlds: int = 25
    trials: int = 10
    seed: int = 1000
    layout: str = "random"
    greedy_kappa: float = 1.0  # tuned on training-layout worlds: see README
    greedy_lambda: float = 0.0
    coordinated_kappa: float = 0.3
    coordinated_lambda: float = 0.0
    coordinated_mu: float = 0.3
    mcts_simulations: int = 16
    mcts_depth: int = 2
    mcts_considered: int = 4
    mcts_kappa: float = 0.3
    budget_mode: str = "team"  # team: budgets are team budgets | per_robot
    zip_with_size: tuple[str, ...] = ()  # lists that pair element-wise with world_sizes
    pairs: tuple[str, ...] = ()  # Welch t-tests, each "a:b"
    batch: int = 0  # episodes per vmapped call; 0 sizes it to memory
    time_planning: bool = True
    render: bool = True


@dataclasses.dataclass(frozen=True)
class Config:
    world: WorldConfig = WorldConfig()
    robots: RobotConfig = RobotConfig()
    sensor: SensorConfig = SensorConfig()
    radio: RadioConfig = RadioConfig()
    candidates: CandidateConfig = CandidateConfig()
    gp: GPConfig = GPConfig()
    reward: RewardConfig = RewardConfig()
    episode: EpisodeConfig = EpisodeConfig()
    policy: PolicyConfig = PolicyConfig()
    ppo: PPOConfig = PPOConfig()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()


# ---------------------------------------------------------------------------------------
# Allowed values. Each rule is (predicate, description of what is allowed).

def _range(lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
    def check(v):
        above = v > lo if lo_open else v >= lo
        below = v < hi if hi_open else v <= hi
        return above and below

    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    return check, f"a number in {left}{lo}, {hi}{right}"


def _choice(*options):
    return (lambda v: v in options), "one of " + ", ".join(options)


def _each(rule):
    check, text = rule
    return (lambda v: all(check(x) for x in v)), f"a list of {text.replace('a number', 'numbers')}"


def _pair(rule):
    check, text = rule
    return (lambda v: all(check(x) for x in v) and v[0] <= v[1]), (
        f"[min, max] with min <= max, each {text}"
    )


_POSITIVE = _range(0, lo_open=True)
_NONNEG = _range(0)
_UNIT = _range(0, 1)

RULES: dict[str, tuple] = {
    "world.size": _range(10, 256),
    "world.layout": _choice("grid", "random"),
    "world.buildings": _range(1, 10_000),
    "world.footprint": _range(1, 16),
    "world.height_range": _pair(_range(0, 1, lo_open=True)),
    "world.targets": _pair(_range(1, 100_000)),
    "world.target_placement": _choice("facade", "footprint"),
    "world.clearance": _range(0, 8),
    "robots.count": _range(1, 256),
    "robots.budget": _pair(_POSITIVE),
    "robots.turn_cost": _NONNEG,
    "robots.start": (lambda v: len(v) == 3 and all(0 <= x <= 1 for x in v), "3 numbers in [0, 1]"),
    "robots.start_heading": _range(0, 3),
    "sensor.model": _choice("raycast", "frustum"),
    "sensor.fov_deg": _range(1, 170),
    "sensor.range": _range(0, 1, lo_open=True),
    "sensor.rays_per_voxel": _range(0.5, 8),
    "radio.range": _NONNEG,
    "radio.collision_distance": _NONNEG,
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
    "train.seed": _range(0, 2**31 - 1),
    "train.envs": _range(1, 1 << 20),
    "train.rollout_steps": _range(1, 4096),
    "train.reset_share": _range(0, 1, lo_open=True),
    "train.updates": _range(0, 10**9),
    "train.updates_per_chunk": _range(1, 10**6),
    "train.keep_checkpoints": _range(1, 1000),
    "train.eval_worlds": _range(1, 100_000),
    "train.eval_budget": _POSITIVE,
    "eval.planners": (
        lambda v: len(v) > 0 and all(p in PLANNERS for p in v),
        "a non-empty list from policy, random, greedy, coordinated, mcts, oracle",
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
PLANNERS = ("policy", "random", "greedy", "coordinated", "mcts", "oracle")


def _cross_checks(cfg: Config) -> list[tuple[str, Any, str]]:
    """Constraints that involve more than one value: (key, value, allowed)."""
    problems = []
    w = cfg.world
    if w.footprint + 2 * w.clearance >= w.size:
        problems.append(("world.size", w.size,
                         f"larger than footprint + 2 * clearance = {w.footprint + 2 * w.clearance}"))
    lots = (w.size - w.clearance) // (w.footprint + w.clearance)
    if w.n_buildings > lots * lots:
        problems.append(("world.buildings", w.buildings,
                         f"at most {lots * lots} buildings fit a {w.size}^3 world"))
    if w.target_placement == "facade" and w.clearance < 1:
        problems.append(("world.clearance", w.clearance,
                         "at least 1 with facade windows (every window must face free air)"))
    if w.target_placement == "footprint" and cfg.sensor.model == "raycast":
        problems.append(("world.target_placement", w.target_placement,
                         "facade with sensor.model=raycast (footprint windows are inside walls)"))
    r = cfg.radio
    if r.collision_distance >= r.range:
        problems.append(("radio.collision_distance", r.collision_distance,
                         f"less than radio.range = {r.range}"))
    if cfg.policy.width % cfg.policy.heads:
        problems.append(("policy.width", cfg.policy.width,
                         f"a multiple of policy.heads = {cfg.policy.heads}"))
    for name in cfg.eval.zip_with_size:
        if len(getattr(cfg.eval, name)) != len(cfg.eval.world_sizes):
            problems.append((f"eval.{name}", getattr(cfg.eval, name),
                             f"one entry per world size ({len(cfg.eval.world_sizes)}), "
                             "because eval.zip_with_size pairs them"))
    if cfg.train.updates % cfg.train.updates_per_chunk:
        problems.append(("train.updates", cfg.train.updates,
                         f"a multiple of train.updates_per_chunk = {cfg.train.updates_per_chunk}"))
    if cfg.train.envs % cfg.ppo.minibatches:
        problems.append(("ppo.minibatches", cfg.ppo.minibatches,
                         f"a divisor of train.envs = {cfg.train.envs}"))
    return problems


# ---------------------------------------------------------------------------------------
# Conversion between plain data and the dataclasses.

def _coerce(key: str, value: Any, annotation) -> Any:
    """Converts a YAML value to the annotated type, or raises ConfigError."""
    origin = typing.get_origin(annotation)
    if origin is tuple:
        args = typing.get_args(annotation)
        if not isinstance(value, (list, tuple)):
            value = [value] if args[-1] is Ellipsis else value
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: got {value!r}; allowed: a list")
        items = args[:1] * len(value) if args[-1] is Ellipsis else args
        if len(items) != len(value):
            raise ConfigError(f"{key}: got {list(value)!r}; allowed: a list of {len(items)} values")
        return tuple(_coerce(key, v, a) for v, a in zip(value, items))
    if annotation is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: got {value!r}; allowed: true or false")
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{key}: got {value!r}; allowed: an integer")
        return value
    if annotation is float:
        if isinstance(value, str) and value.strip().lower() in ("inf", ".inf", "infinity"):
            return math.inf
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: got {value!r}; allowed: a number")
        if math.isnan(value):
            raise ConfigError(f"{key}: got nan; allowed: a number")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: got {value!r}; allowed: a string")
        return value
    raise TypeError(f"unsupported annotation {annotation} for {key}")


def _unknown_key(key: str, known: typing.Iterable[str]) -> ConfigError:
    section, _, name = key.rpartition(".")
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f"; did you mean '{section + '.' if section else ''}{close[0]}'?" if close else ""
    return ConfigError(f"{key}: unknown key{hint} (known: {', '.join(sorted(known))})")


def from_dict(data: dict[str, Any] | None, base: Config | None = None) -> Config:
    """Merges nested plain data into `base` (default: the defaults) and validates."""
    base = base or Config()
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError(f"config: got {type(data).__name__}; allowed: a mapping of sections")
    hints = typing.get_type_hints(Config)
    sections = {}
    for name, values in data.items():
        if name not in hints:
            raise _unknown_key(name, hints)
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"{name}: got {values!r}; allowed: a mapping of keys")
        cls = hints[name]
        fields = typing.get_type_hints(cls)
        current = getattr(base, name)
        changes = {}
        for key, value in values.items():
            if key not in fields:
                raise _unknown_key(f"{name}.{key}", fields)
            changes[key] = _coerce(f"{name}.{key}", value, fields[key])
        sections[name] = dataclasses.replace(current, **changes)
    cfg = dataclasses.replace(base, **sections)
    validate(cfg)
    return cfg


def validate(cfg: Config) -> Config:
    for key, (check, allowed) in RULES.items():
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        if not check(value):
            raise ConfigError(f"{key}: got {_show(value)}; allowed: {allowed}")
    for key, value, allowed in _cross_checks(cfg):
        raise ConfigError(f"{key}: got {_show(value)}; allowed: {allowed}")
    return cfg


def _show(value):
    return list(value) if isinstance(value, tuple) else value


def to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    """Plain nested data (lists for tuples, .inf kept) suitable for YAML."""
    out = {}
    for section in dataclasses.fields(cfg):
        values = getattr(cfg, section.name)
        out[section.name] = {
            f.name: _show(getattr(values, f.name)) for f in dataclasses.fields(values)
        }
    return out


def to_yaml(cfg: Config) -> str:
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def parse_override(text: str) -> tuple[list[str], Any]:
    """`world.size=64` -> (['world', 'size'], 64); the value is parsed as YAML."""
    key, sep, raw = text.partition("=")
    if not sep or "." not in key:
        raise ConfigError(f"{text}: overrides look like section.key=value (e.g. world.size=64)")
    return key.strip().split("."), yaml.safe_load(raw) if raw.strip() else None


def load(path: str | Path | None = None, overrides: typing.Sequence[str] = ()) -> Config:
    """Reads a YAML preset (which may name a `base` preset) and applies dotted overrides."""
    cfg = Config()
    if path is not None:
        cfg = _load_file(Path(path))
    if overrides:
        merged: dict[str, dict[str, Any]] = {}
        for text in overrides:
            keys, value = parse_override(text)
            if len(keys) != 2:
                raise ConfigError(f"{text}: overrides name exactly section.key")
            merged.setdefault(keys[0], {})[keys[1]] = value
        cfg = from_dict(merged, base=cfg)
    return cfg


def _load_file(path: Path, depth: int = 0) -> Config:
    if depth > 8:
        raise ConfigError(f"{path}: 'base' presets nest too deeply")
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})".replace("\n", " ")) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config is a mapping of sections")
    base = Config()
    if "base" in data:
        base = _load_file(path.parent / data.pop("base"), depth + 1)
    try:
        return from_dict(data, base=base)
    except ConfigError as err:
        raise ConfigError(f"{path.name}: {err}") from None

