"""Ground-truth choices: robots in turn take the view that reveals the most windows nobody
has found yet. They read the true world (`EnvState.world`, `discovered`), so they are
upper references (the `oracle` and `oracle_ahead` planners), never something a robot
could compute.

- `choose_in_turn`: one flight; the windows in view, or (`per_cost`) the windows in view
  per unit of flight cost as the next-best-view planners score views (`view.per_cost`).
  Every robot sees the views all robots before it chose, whatever the radio's range.
- `choose_ahead`: windows per unit of cost looking a flight further, as `nbv_ahead` looks
  at unknown space (`jaxmripp.sim.lookahead`): a robot values each of its `branches` best
  first flights a by max(r(a), max_b (w(a) + d w(b | a)) / (c(a) + d c(b))), w the windows
  neither discovered nor claimed nor (for b) seen from a, b drawn around a as the
  environment draws candidates on the robot's map with a's view counted as seen. Robots
  hear the claims of the robots in radio range only (with relay, of their component).
- `choose_city_in_turn`: one flight, per cost, scored by the windows a pose is expected to
  reveal when the city is known but not where its windows are: each building's true
  remaining windows spread over its unseen voxels that can hold one (the `oracle_city`
  reference).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.sim import belief, comms, lookahead, sensing, view
from jaxmripp.sim.geometry import UNKNOWN
from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.sim.types import EnvState
from jaxmripp.spec import belief as belief_spec, layout


def view_tie(key, obs: Observation) -> jax.Array:
    """(N, L) tie-break scores for the window oracles: nbv_team's view score (facade
    weight 2) squashed below 0.1, under one window per unit of cost, plus a jitter."""
    jitter = 1e-4 * jax.random.uniform(key, obs.mask.shape)
    return 0.1 * jnp.tanh(layout.nbv_score(obs.features, 2.0)) + jitter


def _seen_from(state: EnvState, params: EnvParams):
    """positions (L, 3), headings (L,) -> (L, T) bool windows each pose sees (the truth)."""
    return jax.vmap(lambda p, h: sensing.cast(state.world, p, h, params.sensor,
                                              params.size).seen)


def choose_in_turn(mask: jax.Array, state: EnvState, params: EnvParams,
                   tie: jax.Array, per_cost: bool = False) -> jax.Array:
    """The team's choices (N,) int32. mask (N, L) the feasible candidates, tie (N, L) the
    tie-break scores, each below 0.5 in magnitude so that one window outweighs them (per
    cost: below 0.5 x shell[1] / the largest candidate cost). Robot i (index order) casts
    the sensor on the true world from each of its candidates and takes the one with the
    most windows (per cost) neither discovered nor seen from the poses robots j < i chose
    this step. One environment: callers vmap."""
    c = state.candidates
    cast = _seen_from(state, params)
    shell = params.candidates.shell[1]

    def choose(covered, i):
        seen = cast(c.position[i], c.heading[i])  # (L, T)
        fresh = jnp.sum(seen & ~covered[None], axis=-1).astype(jnp.float32)
        if per_cost:
            fresh = view.per_cost(fresh, c.cost[i], shell)
        a = layout.masked_argmax(fresh + tie[i], mask[i], jnp)
        covered = covered | (seen[a] & jnp.any(mask[i]))
        return covered, a

    _, actions = jax.lax.scan(choose, state.discovered, jnp.arange(mask.shape[0]))
    return actions


def choose_ahead(key, mask: jax.Array, state: EnvState, dyn: DynamicParams,
                 params: EnvParams, tie: jax.Array, discount, branches: int) -> jax.Array:
    """The team's choices (N,) int32 by the two-flight window rate of the module docstring
    (mask, tie as `choose_in_turn`'s, per cost). One environment: callers vmap."""
    lookahead.check(params, branches, 2)
    c = state.candidates
    cast = _seen_from(state, params)
    shell = params.candidates.shell[1]
    hears = comms.links(state.heard, params.radio.relay)
    keys = jax.random.split(key, mask.shape[0])

    def choose(claimed, i):
        covered = state.discovered | jnp.any(claimed & hears[i][:, None], axis=0)
        seen = cast(c.position[i], c.heading[i])  # (L, T)
        fresh = jnp.sum(seen & ~covered[None], axis=-1).astype(jnp.float32)
        rate = view.per_cost(fresh, c.cost[i], shell)
        top_rate, order = jax.lax.top_k(jnp.where(mask[i], rate + tie[i], -jnp.inf), branches)
        search = lookahead.Search(params, dyn, state.position, state.heard[i], 0.0, discount,
                                  branches)

        def value(a, key):
            _, following = lookahead.draw_following(
                search, state.occupancy[i], state.building_top[i], c.position[i, a],
                c.heading[i, a], state.budget_left[i] - c.cost[i, a], key)
            later = cast(following.position, following.heading) & ~(covered | seen[a])[None]
            gained = fresh[a] + discount * jnp.sum(later, axis=-1).astype(jnp.float32)
            rates = view.per_cost(gained, c.cost[i, a] + discount * following.cost, shell)
            best = jnp.max(jnp.where(following.valid, rates, -jnp.inf))
            return jnp.maximum(rate[a], best) + tie[i, a]

        values = jax.vmap(value)(order, jax.random.split(keys[i], branches))
        values = jnp.full(rate.shape, -jnp.inf).at[order].set(
            jnp.where(jnp.isfinite(top_rate), values, -jnp.inf))
        a = layout.masked_argmax(values, mask[i], jnp)
        return claimed.at[i].set(seen[a] & jnp.any(mask[i])), a

    claimed = jnp.zeros((mask.shape[0], state.discovered.shape[0]), bool)
    _, actions = jax.lax.scan(choose, claimed, jnp.arange(mask.shape[0]))
    return actions


def choose_city_in_turn(mask: jax.Array, state: EnvState, params: EnvParams,
                        tie: jax.Array, rates: jax.Array) -> jax.Array:
    """The team's choices (N,) int32 by the expected new windows per unit of flight cost of
    a planner that knows the city but not where its windows are. mask, tie as
    `choose_in_turn`'s; rates (N, G, G) int32 each robot's quantised facade rates of the
    truth (`belief.true_rates`: a building's windows the robot has not found over the
    surface it has not seen, relative to the prior m). Robot i (index order) casts the
    sensor on the true world from each of its candidates; a pose's expected new windows
    are, over the voxels it would observe that can hold a window (`belief.window_voxels`),
    that the robot's map does not hold and that no robot j < i will observe from the pose
    it chose this step, the sum of their building's rate times m. One environment:
    callers vmap."""
    c = state.candidates
    n, cells = mask.shape[0], params.size**3
    cast = jax.vmap(lambda p, h: sensing.cast(state.world, p, h, params.sensor,
                                              params.size).voxels)
    slots = belief.window_voxels(state.world.height, params.world).reshape(-1)
    unknown = state.occupancy.reshape(n, cells) == UNKNOWN
    per_slot = rates.reshape(n, -1).astype(jnp.float32) * (belief.prior(params.world)
                                                          / belief_spec.RATE_SCALE)
    shell = params.candidates.shell[1]

    def choose(covered, i):
        observed = cast(c.position[i], c.heading[i])  # (L, V) flat voxels, cells where none
        voxel = jnp.minimum(observed, cells - 1)
        fresh = (observed < cells) & slots[voxel] & unknown[i][voxel] & ~covered[voxel]
        expected = jnp.sum(jnp.where(fresh, per_slot[i][voxel // params.size], 0.0), axis=-1)
        a = layout.masked_argmax(view.per_cost(expected, c.cost[i], shell) + tie[i],
                                 mask[i], jnp)
        chosen = jnp.where(jnp.any(mask[i]), observed[a], cells)
        return covered.at[chosen].set(True, mode="drop"), a

    _, actions = jax.lax.scan(choose, jnp.zeros(cells, bool), jnp.arange(n))
    return actions
