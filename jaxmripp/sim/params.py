"""Environment parameters, split by what a change costs (the gymnax pattern).

`EnvParams` is static: hashable, passed to jit as a static argument, and holds only what
sets array shapes or picks a code path (world and team size, sensor, candidates, GPs,
radio relay, T_max). Changing any of it compiles anew.

`DynamicParams` is a pytree of float32 arrays passed to jit as a traced argument: the
values that change no shape (radio range, collision distance, budget, turn cost, reward
weights, start position). One compiled function serves every value, and sweeps stack
them on a leading axis and vmap. Each value lives only here; the static side has no copy.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.config import (CandidateConfig, Config, GPConfig, SafetyConfig, SensorConfig,
                             WorldConfig)
from jaxmripp.spec import layout


@dataclasses.dataclass(frozen=True)
class StaticRobots:
    count: int  # N
    start_heading: int  # index into geometry.HEADING_ANGLES


@dataclasses.dataclass(frozen=True)
class StaticRadio:
    relay: bool  # forward everything known (multi-hop) instead of single hop
    share_maps: bool = True  # robots in range merge their maps (jaxmripp.spec.sharing)


@dataclasses.dataclass(frozen=True)
class StaticAhead:
    """The lookahead input (`ahead_rate`, jaxmripp.spec.layout); branches 0: none."""

    branches: int = 0
    discount: float = 2.0
    facade_weight: float = 2.0
    rated: bool = False  # the facade weighed by the target belief (nbv_targets' value)


@dataclasses.dataclass(frozen=True)
class StaticBelief:
    """The target-belief input (`view_windows`, jaxmripp.spec.belief); features False:
    none."""

    features: bool = False
    strength: float = 3.0


@dataclasses.dataclass(frozen=True)
class EnvParams:
    world: WorldConfig
    robots: StaticRobots
    sensor: SensorConfig
    radio: StaticRadio
    safety: SafetyConfig
    candidates: CandidateConfig
    gp: GPConfig
    max_steps: int  # T_max; history length T_max + 1
    ahead: StaticAhead = StaticAhead()
    belief: StaticBelief = StaticBelief()

    @classmethod
    def from_config(cls, cfg: Config) -> "EnvParams":
        return cls(world=cfg.world,
                   robots=StaticRobots(cfg.robots.count, cfg.robots.start_heading),
                   sensor=cfg.sensor, safety=cfg.safety,
                   radio=StaticRadio(cfg.radio.relay, cfg.radio.share_maps),
                   candidates=cfg.candidates, gp=cfg.gp, max_steps=cfg.episode.max_steps,
                   ahead=StaticAhead(cfg.policy.ahead_branches, cfg.policy.ahead_discount,
                                     cfg.policy.ahead_facade_weight,
                                     cfg.policy.ahead_rated),
                   belief=StaticBelief(cfg.policy.belief_features, cfg.policy.belief_strength))

    @property
    def size(self) -> int:
        return self.world.size

    @property
    def n_robots(self) -> int:
        return self.robots.count

    @property
    def n_candidates(self) -> int:
        return self.candidates.count

    @property
    def n_features(self) -> int:
        """F, the width of an observation's features (jaxmripp.spec.layout.features)."""
        return len(layout.features(self.ahead.branches > 0, self.belief.features))

    @property
    def utility_gps(self) -> int:
        return 1 if self.gp.shared_utility else self.robots.count


@struct.dataclass
class DynamicParams:
    """Traced environment values; shapes below are per environment (vmapped sweeps add
    leading axes). All float32.

    radio_range:        ()   rho, inclusive; inf = global communication, 0 = none
    collision_distance: ()   d_c: flights that come within it of a heard robot are not
                             offered, and flights closer than it count a robot collision
                             (jaxmripp.spec.flight)
    budget:             (2,) team budget range (lo, hi); reset draws B uniformly in it and
                             gives each of the N robots B / N
    turn_cost:          ()   budget charged when a move changes the heading
    start:              (3,) the first take-off pad
    pad_spacing:        ()   the distance between take-off pads (jaxmripp.spec.flight)
    alpha, beta, gamma: ()   reward weights of r_e (utility GP trace drop), r_u (new
                             windows) and r_c (communication GP trace drop)
    utility_norm:       ()   windows seen per pose are divided by it before entering a GP
    """

    radio_range: jax.Array
    collision_distance: jax.Array
    budget: jax.Array
    turn_cost: jax.Array
    start: jax.Array
    pad_spacing: jax.Array
    alpha: jax.Array
    beta: jax.Array
    gamma: jax.Array
    utility_norm: jax.Array

    @classmethod
    def create(cls, **values) -> "DynamicParams":
        """From plain numbers (every field by name), cast to float32 arrays."""
        return cls(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})

    @classmethod
    def from_config(cls, cfg: Config) -> "DynamicParams":
        return cls.create(
            radio_range=cfg.radio.range, collision_distance=cfg.radio.collision_distance,
            budget=cfg.robots.budget, turn_cost=cfg.robots.turn_cost, start=cfg.robots.start,
            pad_spacing=cfg.robots.pad_spacing,
            alpha=cfg.reward.alpha, beta=cfg.reward.beta, gamma=cfg.reward.gamma,
            utility_norm=cfg.reward.utility_norm)

    def with_values(self, **values) -> "DynamicParams":
        """A copy with some fields set from plain numbers, cast like `create` (a Python
        float left weakly typed would make jit trace again)."""
        return self.replace(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})

    def with_budget(self, team_budget) -> "DynamicParams":
        """A fixed team budget B (lo = hi = B), as evaluation uses."""
        return self.with_values(budget=(team_budget, team_budget))


def stack(dynamics: list[DynamicParams]) -> DynamicParams:
    """Stacks several DynamicParams on a new leading axis, for vmap."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *dynamics)
