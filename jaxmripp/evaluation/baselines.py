"""Non-learning planners with the same interface as the learned policy.

A planner is a pair of pure functions: `init(n_robots) -> memory` and
`act(key, memory, obs, state, dyn) -> (memory, actions)`, where `obs` is the team's
observation (leading robot axis N), `state` the `EnvState` (only privileged planners such
as the oracle may read it), `dyn` the episode's `DynamicParams` (traced; planners that
model the radio or the budget read it) and `actions` (N,) are candidate indices. Planners
that read neither state nor dyn default both to None. Stateless planners keep a dummy
memory so that every planner runs through the same episode code.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from jaxmripp.sim import belief, claims, comms, geometry, gp, lookahead, oracle
from jaxmripp.sim.episode import Planner
from jaxmripp.spec import layout
from jaxmripp.sim.observation import FEATURES, Observation

UTILITY_MEAN = FEATURES.index("utility_mean")
UTILITY_STD = FEATURES.index("utility_std")
COMM_MEAN = FEATURES.index("comm_mean")


def no_memory(n_robots: int) -> jax.Array:
    return jnp.zeros((n_robots, 1), jnp.float32)


def masked_argmax(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """Argmax over feasible entries of the last axis; 0 where nothing is feasible."""
    return layout.masked_argmax(scores, mask, jnp)


def random_planner() -> Planner:
    """Uniform over each robot's feasible candidates."""

    def act(key, memory, obs, state=None, dyn=None):
        noise = jax.random.uniform(key, obs.mask.shape)
        return memory, masked_argmax(noise, obs.mask)

    return Planner("random", no_memory, act)


def greedy_scores(obs: Observation, kappa: float, lam: float) -> jax.Array:
    f = obs.features
    return f[..., UTILITY_MEAN] + kappa * f[..., UTILITY_STD] - lam * f[..., COMM_MEAN]


def greedy_planner(kappa: float = 1.0, lam: float = 0.0, name: str = "greedy") -> Planner:
    """Maximises utility mean + kappa * std - lam * communication mean (UCB-style).

    Ties (common early on, when every prediction is the prior) are broken at random
    rather than by candidate order, which would favour turning in place.
    """

    def act(key, memory, obs, state=None, dyn=None):
        jitter = 1e-5 * jax.random.uniform(key, obs.mask.shape)
        return memory, masked_argmax(greedy_scores(obs, kappa, lam) + jitter, obs.mask)

    return Planner(name, no_memory, act)


# ---------------------------------------------------------------------------------------
# Planners that read more than the observation. They are built per environment shape
# (`EnvParams` gives the GP and sensor settings), read the radio range and d_c from the
# traced `dyn` (so one compilation serves a sweep over them) and read `state`:
# `coordinated_planner` only what a robot knows anyway (its peers' positions within radio
# range), `oracle_planner` the ground truth (an upper reference, not a fair competitor).


def _sequential(choose: Callable, carry, n_robots: int) -> jax.Array:
    """Robots choose one after another (index order); returns actions (N,)."""
    _, actions = jax.lax.scan(choose, carry, jnp.arange(n_robots))
    return actions


def novelty_scores(obs: Observation, kappa: float, lam: float,
                   variance: float = 1.0) -> jax.Array:
    """Expected new windows: mean * (std^2 / prior variance) + kappa * std - lam * comm mean.

    The utility GP predicts how many windows a pose sees, not how many it sees first; the
    posterior variance (relative to the prior, 1 with the default GP) is small near poses
    the robot or its peers already visited, so it discounts windows that were likely seen.
    """
    f = obs.features
    std = f[..., UTILITY_STD]
    novelty = std * std / variance
    return f[..., UTILITY_MEAN] * novelty + kappa * std - lam * f[..., COMM_MEAN]


def coordinated_planner(params, kappa: float = 0.3, lam: float = 0.0, mu: float = 0.3,
                        novelty: bool = True, name: str = "coordinated") -> Planner:
    """Greedy with sequential allocation among robots that hear each other.

    Score = `novelty_scores` (or, with novelty=False, the UCB of `greedy_scores`), which
    subtracts lam * communication-GP mean (regions peers explored), minus mu * the largest
    correlation (GP kernel / variance) with the poses that peers within radio range
    already chose this step. Robots choose in index order; robot i sees the choices of the
    robots j < i it can hear, and never picks a position within the collision distance
    d_c of one of them unless nothing else is feasible.
    """
    gp_cfg = params.gp
    score_fn = (lambda obs, k, l: novelty_scores(obs, k, l, gp_cfg.variance)) if novelty \
        else greedy_scores

    def act(key, memory, obs, state, dyn):
        n = obs.mask.shape[0]
        jitter = 1e-5 * jax.random.uniform(key, obs.mask.shape)
        base = score_fn(obs, kappa, lam) + jitter
        poses = geometry.pose(state.candidates.position, state.candidates.heading)  # (N, L, 4)
        hears = comms.contacts(state.position, dyn.radio_range)

        def choose(carry, i):
            chosen_pose, chosen = carry
            known = chosen & hears[i]
            corr = gp.kernel(poses[i], chosen_pose, gp_cfg) / gp_cfg.variance  # (L, N)
            corr = jnp.max(jnp.where(known[None], corr, 0.0), axis=-1)
            gap = jnp.linalg.norm(poses[i, :, None, :3] - chosen_pose[None, :, :3], axis=-1)
            near = jnp.any(known[None] & (gap <= dyn.collision_distance), axis=-1)
            allowed = obs.mask[i] & ~near
            allowed = jnp.where(jnp.any(allowed), allowed, obs.mask[i])
            a = masked_argmax(base[i] - mu * corr, allowed)
            chosen_pose = chosen_pose.at[i].set(poses[i, a])
            chosen = chosen.at[i].set(jnp.any(obs.mask[i]))
            return (chosen_pose, chosen), a

        init = (jnp.zeros((n, 4), jnp.float32), jnp.zeros((n,), bool))
        return memory, _sequential(choose, init, n)

    return Planner(name, no_memory, act)


def oracle_planner(params, name: str = "oracle") -> Planner:
    """Sequential greedy on the ground truth, windows per unit of flight cost
    (`jaxmripp.sim.oracle.choose_in_turn`): an upper reference, not a fair planner.
    Every robot sees what all robots before it chose, whatever the radio's range. Ties
    (e.g. nothing in view) are broken by the next-best-view score."""
    def act(key, memory, obs, state, dyn=None):
        return memory, oracle.choose_in_turn(obs.mask, state, params, oracle.view_tie(key, obs),
                                             per_cost=True)

    return Planner(name, no_memory, act)


def oracle_ahead_planner(params, discount=3.0, branches: int = 8,
                         name: str = "oracle_ahead") -> Planner:
    """The window oracle per unit of cost looking a flight ahead, robots hearing only the
    claims of robots in radio range (`jaxmripp.sim.oracle.choose_ahead`): the ceiling the
    tables quote, never a baseline."""
    lookahead.check(params, branches, 2)

    def act(key, memory, obs, state, dyn):
        key_tie, key_ahead = jax.random.split(key)
        return memory, oracle.choose_ahead(key_ahead, obs.mask, state, dyn, params,
                                           oracle.view_tie(key_tie, obs), discount, branches)

    return Planner(name, no_memory, act)


def nbv_scores(features: jax.Array, facade_weight: float) -> jax.Array:
    """Next-best-view score (`jaxmripp.spec.layout.nbv_score`, shared with the runtime)."""
    return layout.nbv_score(features, facade_weight)


def nbv_planner(facade_weight: float = 1.0, name: str = "nbv") -> Planner:
    """Next-best view: every robot takes its candidate with the largest `nbv_scores` on
    its own map (the team's, with `radio.share_maps`), independently of its peers."""

    def act(key, memory, obs, state=None, dyn=None):
        jitter = 1e-6 * jax.random.uniform(key, obs.mask.shape)
        return memory, masked_argmax(nbv_scores(obs.features, facade_weight) + jitter, obs.mask)

    return Planner(name, no_memory, act)


def nbv_team_planner(params, facade_weight: float = 1.0, name: str = "nbv_team") -> Planner:
    """Next-best view in turn: robots choose in index order; robot i scores its candidates
    on its map with the voxels that robots j < i it hears will look at counted as seen
    (`jaxmripp.sim.claims`), so the team spreads its views."""
    shell = params.candidates.shell[1]

    def act(key, memory, obs, state, dyn):
        jitter = 1e-6 * jax.random.uniform(key, obs.mask.shape)

        def decide(i, mine, occupancy):
            score = nbv_scores(mine.features, facade_weight) + jitter[i]
            return masked_argmax(score, mine.mask), None

        _, actions, _ = claims.in_turn(decide, obs, state, params.sensor, shell,
                                       params.radio.relay)
        return memory, actions

    return Planner(name, no_memory, act)


def nbv_ahead_planner(params, facade_weight: float = 2.0, discount=3.0, branches: int = 32,
                      flights: int = 2, name: str = "nbv_ahead", rates=None) -> Planner:
    """Next-best view in turn looking `flights` flights ahead (`jaxmripp.sim.lookahead`);
    with `rates` (a function of the state giving every robot's facade rates (N, G, G),
    `jaxmripp.sim.belief`) the facade is weighed by them."""
    lookahead.check(params, branches, flights)

    def act(key, memory, obs, state, dyn):
        return memory, lookahead.choose_in_turn(
            key, obs, state, dyn, params, facade_weight, discount, branches, flights,
            rates=None if rates is None else rates(state))

    return Planner(name, no_memory, act)


def nbv_targets_planner(params, strength=3.0, facade_weight=2.0, discount=3.0,
                        branches: int = 32, flights: int = 2,
                        name: str = "nbv_targets") -> Planner:
    """`nbv_ahead` with each facade sample weighed by its building's posterior window rate
    from what the robot's map holds (`jaxmripp.spec.belief`, prior strength `strength`)."""
    return nbv_ahead_planner(params, facade_weight, discount, branches, flights, name,
                             rates=belief.rates_for("belief", strength, params.sensor,
                                                    params.world))


def oracle_rate_planner(params, facade_weight=2.0, discount=3.0, branches: int = 32,
                        flights: int = 2, name: str = "oracle_rate") -> Planner:
    """`nbv_targets` with the true rates: each building's windows the robot has not found
    over its surface the robot has not seen (`jaxmripp.sim.belief.true_rates`). It knows
    how many windows are left on a building, not where on it: an upper reference of what
    a better belief can be worth, never a baseline."""
    return nbv_ahead_planner(params, facade_weight, discount, branches, flights, name,
                             rates=belief.rates_for("truth", None, params.sensor,
                                                    params.world))


def oracle_city_planner(params, name: str = "oracle_city") -> Planner:
    """The expected-window oracle per unit of cost (`jaxmripp.sim.oracle.choose_city_in_turn`):
    robots in turn, each knowing the city's true geometry and how many windows every
    building has left, not where on it. An upper reference of what a one-flight planner
    that does not see windows before looking could reach, never a baseline."""
    true_rates = belief.rates_for("truth", None, params.sensor, params.world)

    def act(key, memory, obs, state, dyn=None):
        return memory, oracle.choose_city_in_turn(obs.mask, state, params,
                                                  oracle.view_tie(key, obs), true_rates(state))

    return Planner(name, no_memory, act)
