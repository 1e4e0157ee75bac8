"""What one robot sees at one step: the data contract between the env and the policy.

The env fills an `Observation` per robot; the policy reads one robot's observation
(callers `vmap` over robots and environments, so every field may carry leading batch
axes). `observe` builds the team's observations from an `EnvState`.

Shapes (L candidates, F = EnvParams.n_features, S = len(ROBOT_STATE), N robots):
    features      (..., L, F)        float32, columns in FEATURES order, then the belief
                                     and lookahead inputs where configured
                                     (`jaxmripp.spec.layout.features`)
    mask          (..., L)           bool, True = feasible candidate
    robot_state   (..., S)           float32, columns in ROBOT_STATE order
    global_state  (..., N * S + 2)   float32, every robot's robot_state (robot-major),
                                     then the discovered fraction and the mean fraction
                                     of budget left (input of a centralised critic)
"""

from __future__ import annotations

import chex
import flax.struct
import jax
import jax.numpy as jnp

from jaxmripp.sim import belief, geometry, gp, view
from jaxmripp.config import SensorConfig
from jaxmripp.sim.params import EnvParams
from jaxmripp.sim.types import EnvState, discovered_fraction

# The layout is defined once, next to the exported file format, in the NumPy-only runtime
# (which must not import this module). FEATURES per candidate: dx, dy, dz offset from the
# robot; x, y, z absolute position; one-hot heading; posterior mean and standard deviation
# of the utility and communication GPs; path cost; budget left after the move.
# ROBOT_STATE: position, one-hot heading, budget left, step counter.
from jaxmripp.spec.layout import BELIEF_FEATURES, FEATURE_GROUPS, FEATURES, ROBOT_STATE
from jaxmripp.spec import sectors as sectors_spec

N_FEATURES = len(FEATURES)  # F = 21
N_ROBOT_STATE = len(ROBOT_STATE)  # S = 9
N_GLOBAL_EXTRA = 2  # discovered fraction, mean budget left fraction


def global_state_size(robots: int) -> int:
    """Length of `Observation.global_state` for a team of `robots`."""
    return robots * N_ROBOT_STATE + N_GLOBAL_EXTRA


@flax.struct.dataclass
class Observation:
    features: jax.Array  # (..., L, F) float32 per-candidate features, layout FEATURES
    mask: jax.Array  # (..., L) bool, True = feasible candidate
    robot_state: jax.Array  # (..., S) float32, layout ROBOT_STATE
    global_state: jax.Array  # (..., N*S + 2) float32, for a centralised critic

    @classmethod
    def zeros(cls, params: EnvParams) -> "Observation":
        """One robot's observation, all zero: shapes for initialising a network without
        tracing a reset."""
        return cls(features=jnp.zeros((params.n_candidates, params.n_features), jnp.float32),
                   mask=jnp.zeros((params.n_candidates,), bool),
                   robot_state=jnp.zeros((N_ROBOT_STATE,), jnp.float32),
                   global_state=jnp.zeros((global_state_size(params.n_robots),), jnp.float32))


# The VIEW group's columns, in `view_columns`' order: one slice of FEATURES.
_VIEW = [FEATURES.index(name) for name in FEATURE_GROUPS["view"]]
assert _VIEW == list(range(_VIEW[0], _VIEW[0] + len(_VIEW))), "VIEW columns must be adjacent"
VIEW_COLUMNS = slice(_VIEW[0], _VIEW[-1] + 1)


def view_columns(occupancy: jax.Array, top: jax.Array, position: jax.Array, cost: jax.Array,
                 sensor: SensorConfig, size: int, shell_outer: float) -> jax.Array:
    """One robot's VIEW columns (view_unknown, view_facade and both per unit of cost),
    (L, 4), for its map (G, G, G), building tops (G, G) and candidates: positions (L, 3),
    which come in groups of the N_HEADINGS headings of one position, and costs (L,)."""
    gains = view.view_gain(occupancy, top, position[::geometry.N_HEADINGS], sensor, size)
    return _stacked_view_columns(gains, cost, shell_outer)


def _stacked_view_columns(gains, cost: jax.Array, shell_outer: float) -> jax.Array:
    """(view_unknown, view_facade), each (..., K, N_HEADINGS), and costs (..., L) -> the
    VIEW columns (..., L, 4)."""
    unknown, facade = (g.reshape(cost.shape) for g in gains)
    return jnp.stack([unknown, facade, view.per_cost(unknown, cost, shell_outer),
                      view.per_cost(facade, cost, shell_outer)], axis=-1)


def _belief_columns(windows: jax.Array, cost: jax.Array, shell_outer: float) -> jax.Array:
    """view_windows (..., K, N_HEADINGS) and costs (..., L) -> the BELIEF columns (..., L,
    2): view_windows and view_windows_per_cost (`jaxmripp.spec.belief`)."""
    windows = windows.reshape(cost.shape)
    return jnp.stack([windows, view.per_cost(windows, cost, shell_outer)], axis=-1)


def belief_rates(state: EnvState, params: EnvParams) -> jax.Array | None:
    """(N, G, G) int32 each robot's facade rates (`jaxmripp.sim.belief.team_rates`) where
    the policy reads the belief columns, else None: computed once per step and shared by
    `observe` and the rated lookahead input."""
    if not params.belief.features:
        return None
    return belief.team_rates(state, params.belief.strength, params.sensor, params.world)


def observe(state: EnvState, params: EnvParams, rates: jax.Array | None) -> Observation:
    """Per-robot observations (leading axis N), laid out as FEATURES and ROBOT_STATE;
    `rates` from `belief_rates`.

    Only static parameters are read: budgets enter as fractions of the initial budget.
    The lookahead input, which draws candidates, is appended by the env
    (`jaxmripp.sim.lookahead.with_ahead_rates`).
    """
    n = params.n_robots
    c = state.candidates
    poses = geometry.pose(c.position, c.heading)
    utility_gp = state.utility_gp if not params.gp.shared_utility else jax.tree.map(
        lambda x: jnp.broadcast_to(x, (n, *x.shape[1:])), state.utility_gp)
    predict = jax.vmap(gp.predict, in_axes=(0, 0, None))
    u_mean, u_var = predict(utility_gp, poses, params.gp)
    c_mean, c_var = predict(state.comm_gp, poses, params.gp)
    heading_onehot = jax.nn.one_hot(c.heading, geometry.N_HEADINGS)
    budget = jnp.maximum(state.budget_initial, 1e-6)
    shell = params.candidates.shell[1]
    gains = view.team_view_gain(state.team_map, state.building_top,
                                c.position[:, ::geometry.N_HEADINGS], state.position,
                                params.sensor, params.size, rates=rates)
    gain_columns = _stacked_view_columns(gains[:2], c.cost, shell)
    belief_columns = [] if rates is None else [_belief_columns(gains[2], c.cost, shell)]
    peers = jax.vmap(view.peer_distance, in_axes=(0, None, 0, None))(
        c.position, state.position, state.heard, shell)
    features = jnp.concatenate([
        (c.position - state.position[:, None]) / params.candidates.shell[1],
        c.position,
        heading_onehot,
        u_mean[..., None], jnp.sqrt(u_var)[..., None],
        c_mean[..., None], jnp.sqrt(c_var)[..., None],
        c.cost[..., None],
        ((state.budget_left[:, None] - c.cost) / budget)[..., None],
        gain_columns,
        peers[..., None],
        *belief_columns,
    ], axis=-1)
    robot_state = jnp.concatenate([
        state.position,
        jax.nn.one_hot(state.heading, geometry.N_HEADINGS),
        (state.budget_left / budget)[:, None],
        jnp.broadcast_to(state.step / params.max_steps, (n, 1)),
    ], axis=-1)
    global_state = jnp.concatenate([
        robot_state.reshape(-1),
        jnp.stack([discovered_fraction(state), jnp.mean(state.budget_left) / budget]),
    ])
    mask = c.valid & ~state.done[:, None]
    chex.assert_shape(features, (n, params.n_candidates,
                                 N_FEATURES + len(belief_columns) * len(BELIEF_FEATURES)))
    chex.assert_shape(robot_state, (n, N_ROBOT_STATE))
    return Observation(features=features.astype(jnp.float32), mask=mask,
                       robot_state=robot_state.astype(jnp.float32),
                       global_state=jnp.broadcast_to(global_state, (n, global_state.shape[0])))


def in_sectors(obs, state, dyn):
    """The team's observations (N, ...) with the sector rule of `jaxmripp.spec.sectors`
    applied to their masks (where it applies at dyn.radio_range)."""
    n = obs.mask.shape[0]
    mask = sectors_spec.offered(obs.mask, obs.features, state.candidates.position, dyn.start,
                                jnp.arange(n)[:, None], n, xp=jnp)
    return obs.replace(mask=jnp.where(sectors_spec.applies(dyn.radio_range), mask, obs.mask))
