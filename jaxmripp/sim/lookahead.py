"""Next-best view in turn, looking more than one flight ahead (the `nbv_ahead` baseline,
the lookahead teacher of `ppo.teacher` and the policy's lookahead input of
`policy.ahead_branches`, `ahead_rates`; with `policy.ahead_rated`, nbv_targets' value).

`nbv_team` takes the candidate with the most view gain per unit of flight cost, one step
at a time. A pose that sees a little but opens onto a rich view next is worth more than
that score says, and one that sees much but leads nowhere less. Here robot i (deciding in
turn, on its map with its peers' claimed views counted as seen, `jaxmripp.sim.claims`)
values each of its `branches` best candidates `a` by its own rate or the best rate of a
sequence of up to `flights` flights starting with it, whichever is larger; for two,

    v(a) = max(g(a) / c(a), max_b (g(a) + discount g(b | a)) / (c(a) + discount c(b))),

where g is `nbv_team`'s gain (unknown voxels in view plus the facade weight times the
unknown facade voxels in view, `jaxmripp.spec.view`; with a robot's facade rates, the
`nbv_targets` baseline, the facade samples weighed by the target belief,
`jaxmripp.spec.belief`), c the flight cost, and b ranges
over candidates drawn around `a` as the environment would draw them
(`jaxmripp.sim.candidates.sample`, with the budget left after `a`), scored on the map with
`a`'s view counted as seen. A third flight adds discount^2 g(c | a, b) and discount^2 c(c)
for the `branches` best b, and so on. Taking the larger of the rates lets a rich view
count even where what follows it is poor (the robot will choose again there). Costs enter
as `nbv_team`'s do (`view.per_cost`), so with discount 0 the choice is `nbv_team`'s. The
other candidates keep -inf: a candidate outside the one-step top `branches` is never
taken. The discount, `branches` and `flights` are tuned on training-layout worlds
(docs/baselines.md).

Cost per robot and step: branches + branches^2 + ... + branches^(flights - 1) candidate
draws, each with the view gain of K positions (an observation's view gain is one).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.sim import candidates as cands
from jaxmripp.sim import claims, geometry, view
from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.sim.types import EnvState
from jaxmripp.spec import layout

_UNKNOWN = layout.FEATURES.index("view_unknown")
_FACADE = layout.FEATURES.index("view_facade")
_WINDOWS = layout.features(belief=True).index("view_windows")


@struct.dataclass
class Search:
    """What one robot's lookahead holds fixed: the peers it avoids and the scoring."""

    params: EnvParams = struct.field(pytree_node=False)
    dyn: DynamicParams
    others: jax.Array  # (N, 3) all robots' positions
    heard: jax.Array  # (N,) bool the robots this one hears
    facade_weight: float | jax.Array
    discount: jax.Array | float
    branches: int = struct.field(pytree_node=False)
    rates: jax.Array | None = None  # (G, G) int32 facade rates weighing the facade, or None


def draw_following(search: Search, occupancy, top, position, heading, budget_left, key):
    """What a robot could do after reaching the pose (position (3,), heading ()) with
    `budget_left`: its map (G, G, G) with that pose's view counted as seen and the
    candidates drawn around the pose ((L,) as `cands.sample` gives them) on it."""
    params, size = search.params, search.params.size
    seen = view.unknown_in_view(occupancy, top, position, heading, params.sensor, size)
    after = occupancy.reshape(-1).at[seen].set(geometry.FREE, mode="drop").reshape(
        occupancy.shape)
    following = cands.sample(key, position, heading, budget_left, after, search.others,
                             search.heard, params.candidates, params.safety,
                             search.dyn.turn_cost, search.dyn.collision_distance, size)
    return after, following


def gains(search: Search, occupancy, top, positions) -> jax.Array:
    """(L,) the search's gain g of the candidates at `positions` (K, 3), in groups of the
    N_HEADINGS headings, on the map (G, G, G)."""
    params = search.params
    values = view.view_gain(occupancy, top, positions, params.sensor, params.size,
                            rates=search.rates)
    facade = values[1] if search.rates is None else values[2]
    return layout.view_value(values[0].reshape(-1), facade.reshape(-1), search.facade_weight)


def next_flight(search: Search, occupancy, top, position, heading, budget_left, key):
    """`draw_following` and the candidates' gains (L,) on the map after the pose."""
    after, following = draw_following(search, occupancy, top, position, heading,
                                      budget_left, key)
    return after, following, gains(search, after, top,
                                   following.position[::geometry.N_HEADINGS])


def continuation(search: Search, occupancy, top, position, heading, budget_left, gained,
                 cost, weight, key, flights: int):
    """The best rate (gained + weighted gains) / (cost + weighted costs) over 1 to `flights`
    more flights from a pose reached with `gained` and `cost` so far, the next flight
    weighted `weight` and each later one `discount` times the one before; -inf where no
    flight is affordable. Beyond the first flight only the `branches` best are followed."""
    shell = search.params.candidates.shell[1]
    key_draw, key_deeper = jax.random.split(key) if flights > 1 else (key, None)
    after, following, gains = next_flight(search, occupancy, top, position, heading,
                                          budget_left, key_draw)
    rates = jnp.where(following.valid, view.per_cost(gained + weight * gains,
                                                     cost + weight * following.cost, shell),
                      -jnp.inf)
    best = jnp.max(rates)
    if flights == 1:
        return best
    top_rate, order = jax.lax.top_k(rates, search.branches)
    deeper = jax.vmap(lambda j, k: continuation(
        search, after, top, following.position[j], following.heading[j],
        budget_left - following.cost[j], gained + weight * gains[j],
        cost + weight * following.cost[j], weight * search.discount, k, flights - 1))(
        order, jax.random.split(key_deeper, search.branches))
    return jnp.maximum(best, jnp.max(jnp.where(jnp.isfinite(top_rate), deeper, -jnp.inf)))


def lookahead_values(search: Search, mine: Observation, occupancy, top, key,
                     candidates: cands.Candidates, budget_left, flights: int,
                     first_gain: jax.Array | None = None):
    """(L,) v(a) of the module docstring for robot i's `branches` best candidates by
    nbv_team's score, -inf for the others and for infeasible ones, and (L,) that score
    (the one-step rate). `mine` is the robot's observation (L, F) on `occupancy`, its map
    with its peers' claims counted as seen. The candidates' gains g (L,) are `first_gain`
    where given; else, with facade rates (`search.rates`), computed on that map, and
    without, read from the observation's view columns."""
    shell = search.params.candidates.shell[1]
    if first_gain is None and search.rates is None:
        first_gain = layout.view_value(mine.features[:, _UNKNOWN], mine.features[:, _FACADE],
                                       search.facade_weight)
    elif first_gain is None:
        first_gain = gains(search, occupancy, top,
                           candidates.position[::geometry.N_HEADINGS])
    rate = view.per_cost(first_gain, candidates.cost, shell)
    top_rate, order = jax.lax.top_k(jnp.where(mine.mask, rate, -jnp.inf), search.branches)

    def value(first, key):
        later = continuation(search, occupancy, top, candidates.position[first],
                             candidates.heading[first], budget_left - candidates.cost[first],
                             first_gain[first], candidates.cost[first], search.discount, key,
                             flights - 1)
        return jnp.maximum(rate[first], later)

    values = jax.vmap(value)(order, jax.random.split(key, search.branches))
    values = jnp.where(jnp.isfinite(top_rate), values, -jnp.inf)
    return jnp.full(rate.shape, -jnp.inf).at[order].set(values), rate


def ahead_rates(key, obs: Observation, state: EnvState, params: EnvParams,
                dyn: DynamicParams, rates: jax.Array | None) -> jax.Array:
    """(N, L) the `ahead_rate` input of `jaxmripp.spec.layout` for the team's observations
    `obs` (FEATURES columns, then the BELIEF columns where the policy reads them) on their
    own maps: `lookahead_values` over two flights where a candidate is followed, its
    one-step rate elsewhere; with `params.ahead.rated` the facade is weighed by each
    robot's target belief (the first flight's from the observation's `view_windows`, the
    later ones' from `rates` (N, G, G) int32, the facade rates `obs` was built with).
    One environment: callers vmap."""
    ahead = params.ahead
    keys = jax.random.split(key, params.n_robots)
    facade = _WINDOWS if ahead.rated else _FACADE

    def one(i, features, mask, occupancy, top, c, budget_left, key, rates_i):
        mine = Observation(features=features, mask=mask, robot_state=None, global_state=None)
        search = Search(params, dyn, state.position, state.heard[i], ahead.facade_weight,
                        ahead.discount, ahead.branches, rates_i)
        first_gain = layout.view_value(features[:, _UNKNOWN], features[:, facade],
                                       ahead.facade_weight)
        values, rate = lookahead_values(search, mine, occupancy, top, key, c, budget_left, 2,
                                        first_gain)
        return jnp.where(jnp.isfinite(values), values, rate)

    return jax.vmap(one)(jnp.arange(params.n_robots), obs.features, obs.mask,
                         state.occupancy, state.building_top, state.candidates,
                         state.budget_left, keys, rates if ahead.rated else None)


def with_ahead_rates(key, obs: Observation, state: EnvState, params: EnvParams,
                     dyn: DynamicParams, rates: jax.Array | None) -> Observation:
    """`obs` with the lookahead input appended when `params.ahead.branches` > 0 (the
    key: the step's, from which `ahead_rates` draws with `fold_in(key, 1)`; `rates`: the
    facade rates `obs` was built with, `jaxmripp.sim.observation.belief_rates`)."""
    if not params.ahead.branches:
        return obs
    values = ahead_rates(jax.random.fold_in(key, 1), obs, state, params, dyn, rates)
    return obs.replace(features=jnp.concatenate([obs.features, values[..., None]], axis=-1))


def choose_in_turn(key, obs: Observation, state: EnvState, dyn: DynamicParams,
                   params: EnvParams, facade_weight: float, discount, branches: int,
                   flights: int, rates: jax.Array | None = None) -> jax.Array:
    """The team's choices (N,) int32: robots in index order (`claims.in_turn`), each taking
    the candidate with the largest `lookahead_values` over `flights` flights (ties broken
    at random, as nbv_team's); with `rates` (N, G, G) int32 each robot weighs the facade by
    its facade rates (`jaxmripp.sim.belief`). One environment: callers vmap."""
    check(params, branches, flights)
    key_jitter, key_ahead = jax.random.split(key)
    jitter = 1e-6 * jax.random.uniform(key_jitter, obs.mask.shape)
    keys = jax.random.split(key_ahead, obs.mask.shape[0])

    def decide(i, mine, occupancy):
        search = Search(params, dyn, state.position, state.heard[i], facade_weight, discount,
                        branches, None if rates is None else rates[i])
        c = jax.tree.map(lambda x: x[i], state.candidates)
        values, _ = lookahead_values(search, mine, occupancy, state.building_top[i], keys[i],
                                     c, state.budget_left[i], flights)
        return layout.masked_argmax(values + jitter[i], mine.mask, jnp), None

    _, actions, _ = claims.in_turn(decide, obs, state, params.sensor,
                                   params.candidates.shell[1], params.radio.relay)
    return actions


def check(params: EnvParams, branches: int, flights: int) -> None:
    """One clear error for settings the search cannot use."""
    if not 1 <= branches <= params.candidates.count:
        raise ValueError(f"nbv_ahead: branches = {branches}; allowed: 1 to the candidate "
                         f"count {params.candidates.count}")
    if flights < 2:
        raise ValueError(f"nbv_ahead: flights = {flights}; allowed: 2 or more (1 is nbv_team)")
