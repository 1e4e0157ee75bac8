"""The configuration's sections: frozen dataclasses with the defaults.

Every section is a frozen dataclass, so a whole `Config` is hashable and can be passed to
`jax.jit` as a static argument. What values are allowed is in `rules`.
"""

from __future__ import annotations

import dataclasses
import math


REFERENCE_SIZE = 50  # the paper's grid; counts below are quoted at this size


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    size: int = 50  # G: voxels per side of the unit cube
    layout: str = "grid"  # grid (training) | random (test)
    buildings: int = 25  # at G = 50; scaled by (G / 50)^2 to keep the density
    footprint: int = 3  # building footprint side, voxels (the largest, with footprint_min)
    footprint_min: int = 0  # > 0: each footprint side drawn from [footprint_min, footprint]
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
    pad_spacing: float = 0.06  # take-off pads apart in the y = start_y face (> d_c)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    model: str = "raycast"  # raycast (occlusion) | frustum (reference, no occlusion)
    fov_deg: float = 90.0
    range: float = 0.24  # fraction of the world size
    rays_per_voxel: float = 2.0  # ray grid density at the far end of the range
    # What the view-gain features (jaxmripp.spec.view) assume of this sensor and the world:
    # whether voxels mapped OCCUPIED block the gain's rays (the raycast sensor's occlusion;
    # false: they do not, as for the frustum, which sees through buildings), and which
    # building tops mark unknown voxels as facade: "nearby" (a column's and its four
    # neighbours': windows on facades) | "around" (and its corner neighbours': the Table I
    # protocol's) | "column" (its own: windows inside footprints)
    gain_occlusion: bool = True
    gain_facade: str = "nearby"


@dataclasses.dataclass(frozen=True)
class RadioConfig:
    range: float = 0.3  # rho; .inf for global communication
    relay: bool = False  # forward everything known (multi-hop) instead of single hop
    share_maps: bool = True  # robots in range merge their maps (jaxmripp.spec.sharing)
    collision_distance: float = 0.05  # d_c


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    """Safe flight: the rules are written in jaxmripp.spec.flight."""

    flight: str = "known_free"  # known_free | truncate | optimistic (unsafe reference)
    # Robots closer than d_c to a robot they hear may still fly what takes them no closer
    # (off: two robots that met out of radio range are offered nothing and retire)
    escape: bool = False


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
    # Peer rounds per step (jaxmripp.spec.feeding): R = N - 1 + catchup_rounds
    catchup_rounds: int = 1
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
    view_features: bool = True  # False: ablation without the view-gain inputs
    intent_features: bool = True  # False: ablation without the peer-distance input
    # > 0: one more input, the two-flight lookahead value of the robot's this many best
    # candidates (`ahead_rate`, jaxmripp.spec.layout), with these discount and facade weight
    ahead_branches: int = 0
    ahead_discount: float = 2.0
    ahead_facade_weight: float = 2.0
    # True: the lookahead input weighs the facade by the target belief (needs
    # belief_features, at belief_strength): the value nbv_targets ranks by
    ahead_rated: bool = False
    # True: two more inputs, the view's facade weighed by each building's posterior window
    # rate (`view_windows`, `view_windows_per_cost`: jaxmripp.spec.belief), with this prior
    # strength (pseudo-windows); the NumPy runtime computes them too (jaxmripp.runtime.belief)
    belief_features: bool = False
    belief_strength: float = 3.0


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    algo: str = "ippo"  # ippo | mappo
    # mappo only: the critic also reads where the undiscovered windows are, from the true
    # world (jaxmripp.sim.privileged); training only, the actor never reads it
    privileged_critic: bool = False
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
    # > 0: kickstarting: the loss adds this weight x the cross-entropy from the
    # next-best-view choice (jaxmripp.spec.layout.nbv_score with teacher_facade) on
    # the observation each robot decided on
    teacher_coef: float = 0.0
    teacher_updates: int = 0  # > 0: the weight falls linearly to 0 over these updates
    # whose choices: nbv (the score on the observation, as above), nbv_ahead or
    # nbv_targets (those baselines' choices with their eval.* settings, computed in the
    # rollouts), oracle_rate (nbv_targets with the true rates) or oracle_city (one flight on
    # the true geometry with the true rates): privileged teachers, training only
    teacher: str = "nbv"
    # the weight of unknown facade voxels in the teacher's score; nbv_team's tuned weight
    # by default (a training setting, chosen by the trained policies on training layouts)
    teacher_facade: float = 2.0
    # > 0: search-based policy improvement (jaxmripp.learn.search): the loss adds this
    # weight x the cross-entropy from a Gumbel MuZero search's improved policy over the
    # candidates
    search_coef: float = 0.0
    search_simulations: int = 16  # the search's simulations (and candidates it considers)
    # what values the search's candidates: model (the lookahead input, needs
    # policy.ahead_branches > 0) or learned (the network's action values, a head trained
    # on the returns that followed each action, with the critic's value at the root)
    search_value: str = "model"


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    name: str = "default"
    envs: int = 64
    rollout_steps: int = 16
    reset_share: float = 0.25  # most environments restarted per rollout step, as a share
    updates: int = 100
    # Updates per compiled call (a chunk): how often metrics reach the host, the progress
    # line is printed and a checkpoint is saved. It does not change what is trained: the
    # environments carry on from one chunk to the next.
    updates_per_chunk: int = 10
    # Environments are computed in this many equal blocks (0: one per device); every
    # device count dividing it trains to the same parameters (jaxmripp.parallel.blocks).
    blocks: int = 0
    # Start from these parameters instead of random ones (a fresh optimiser, update 0): a
    # training run's folder (its last checkpoint) or an export (policy.npz), e.g. to
    # continue a policy trained with fewer robots. "" = random initialisation.
    init_from: str = ""
    keep_checkpoints: int = 3
    # Where every update's metrics go (jaxmripp.learn.metrics): jsonl (metrics.jsonl),
    # tensorboard (event files in tensorboard/), wandb (Weights & Biases, offline unless
    # WANDB_MODE says otherwise; needs `pip install wandb`)
    log: tuple[str, ...] = ("jsonl", "tensorboard")
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
    nbv_facade: float = 0.0  # weight of unknown facade voxels in nbv's score (tuned)
    nbv_team_facade: float = 2.0  # ... in nbv_team's score (tuned: docs/baselines.md)
    nbv_ahead_discount: float = 3.0  # weight of nbv_ahead's later flights (tuned)
    nbv_ahead_branches: int = 32  # candidates nbv_ahead follows at each flight (tuned)
    nbv_ahead_flights: int = 2  # flights nbv_ahead looks ahead (2: one beyond the next)
    # nbv_targets: nbv_ahead's search on the unknown space plus the facade weighed by the
    # target belief (jaxmripp.spec.belief), with these prior strength, facade weight,
    # discount and branches (tuned: docs/baselines.md); flights as nbv_ahead. oracle_rate
    # runs the same search on the buildings' true remaining windows
    nbv_targets_strength: float = 3.0
    nbv_targets_facade: float = 2.0
    nbv_targets_discount: float = 3.0
    nbv_targets_branches: int = 32
    # oracle_ahead: the window oracle per unit of cost looking a flight ahead, following
    # this many first flights (each followed flight casts the sensor from every candidate)
    oracle_ahead_branches: int = 8
    mcts_simulations: int = 64  # tuned with mcts_depth: docs/baselines.md
    mcts_depth: int = 4
    mcts_considered: int = 4
    mcts_kappa: float = 0.3
    budget_mode: str = "team"  # team: budgets are team budgets | per_robot
    zip_with_size: tuple[str, ...] = ()  # lists that pair element-wise with world_sizes
    pairs: tuple[str, ...] = ()  # Welch t-tests, each "a:b"
    batch: int = 0  # episodes per vmapped call; 0 sizes it to memory
    time_planning: bool = True
    render: bool = True
    # every planner's robots keep to their sector of the world while it has views, where
    # the radio range is short (jaxmripp.spec.sectors; OnboardPlanner(sectors=True))
    sectors: bool = False


@dataclasses.dataclass(frozen=True)
class Config:
    world: WorldConfig = WorldConfig()
    robots: RobotConfig = RobotConfig()
    sensor: SensorConfig = SensorConfig()
    radio: RadioConfig = RadioConfig()
    safety: SafetyConfig = SafetyConfig()
    candidates: CandidateConfig = CandidateConfig()
    gp: GPConfig = GPConfig()
    reward: RewardConfig = RewardConfig()
    episode: EpisodeConfig = EpisodeConfig()
    policy: PolicyConfig = PolicyConfig()
    ppo: PPOConfig = PPOConfig()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
