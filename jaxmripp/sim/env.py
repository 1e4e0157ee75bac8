"""The multi-robot MRIPP environment as pure functions (gymnax style).

`EnvParams` (static: shapes and code paths) and `DynamicParams` (traced: ranges, budgets,
costs, reward weights) come from `jaxmripp.sim.params`; `EnvState` is a pytree of arrays
with per-robot data stacked on a leading robot axis of size N (`jaxmripp.sim.types`).

One step: actions (N,) -> flights under the rules of `jaxmripp.spec.flight` (known-free
space, intents between robots in range), checked against the ground truth -> ray
casts from the new poses (detections, occupancy maps) -> history and radio exchange ->
GP updates (`jaxmripp.sim.feeding`) -> new candidates -> observations and rewards.
"""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp

from jaxmripp.sim import candidates as cands
from jaxmripp.sim import comms, flight, geometry, gp, lookahead, maps, sensing, tops
from jaxmripp.sim import world as worldmod
from jaxmripp.sim.geometry import FREE, OCCUPIED
from jaxmripp.sim.feeding import feed_gps
from jaxmripp.sim.observation import (FEATURES, ROBOT_STATE, Observation,  # noqa: F401
                                      belief_rates, observe)
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.sim.types import (EnvState, Metrics, StepInfo, discovered_fraction,  # noqa: F401
                                episode_done)


# ---------------------------------------------------------------------------------------
# Reset and step
#
# reset, step and their shared parts are jitted where they are defined, with inline=True:
# inside a program (an episode, a rollout, a teacher) JAX then traces each of them once per
# process for each static `params` and argument shapes, and inlines the cached equations
# wherever they are called. A sweep over many planners, or training followed by its
# evaluation, thus traces the environment once instead of once per program, and compiles
# the same program as before: a nested call that is not inlined lowers as a function call,
# which made the vmapped step about a fifth slower on CPU (benchmarks/env.py).


@functools.partial(jax.jit, static_argnames="params", inline=True)
def reset(key: chex.PRNGKey, params: EnvParams,
          dyn: DynamicParams) -> tuple[Observation, EnvState]:
    n, size = params.n_robots, params.size
    key_world, key_budget, key_rest = jax.random.split(key, 3)
    world = worldmod.generate(key_world, params.world)
    lo, hi = dyn.budget[0], dyn.budget[1]
    budget = jax.random.uniform(key_budget, (), minval=lo, maxval=hi) / n
    eval_poses = gp.evaluation_poses(params.gp)
    batched = lambda tree, count: jax.tree.map(lambda x: jnp.broadcast_to(x, (count, *x.shape)), tree)
    empty_gp = gp.empty(params.gp, eval_poses)
    history = params.max_steps + 1
    state = EnvState(
        world=world,
        position=flight.pads(dyn.start, n, dyn.pad_spacing),
        heading=jnp.full((n,), params.robots.start_heading, jnp.int32),
        budget_left=jnp.full((n,), budget, jnp.float32),
        budget_initial=budget.astype(jnp.float32),
        done=jnp.zeros((n,), bool),
        team_map=maps.empty(world.height, n),
        building_top=jnp.broadcast_to(tops.empty_tops(size), (n, size, size)),
        heard=jnp.zeros((n, n), bool),
        discovered=jnp.zeros(world.target_valid.shape, bool),
        history_pose=jnp.zeros((n, history, 4), jnp.float32),
        history_utility=jnp.zeros((n, history), jnp.float32),
        know=jnp.zeros((n, n), jnp.int32),
        fed=jnp.zeros((n, n), jnp.int32),
        utility_gp=batched(empty_gp, params.utility_gps),
        comm_gp=batched(empty_gp, n),
        candidates=None,
        step=jnp.zeros((), jnp.int32),
        metrics=Metrics.zeros(n),
    )
    state, _ = _after_move(key_rest, state, jnp.ones((n,), bool), params, dyn)
    return _observations(key_rest, state, params, dyn), state


@functools.partial(jax.jit, static_argnames="params", inline=True)
def step(key: chex.PRNGKey, state: EnvState, actions: jax.Array, params: EnvParams,
         dyn: DynamicParams):
    """actions (N,) int32 candidate indices -> (obs, state, reward (N,), done (N,), info)."""
    chex.assert_shape(actions, (params.n_robots,))
    moved, moving = _move(state, actions, params, dyn)
    state, parts = _after_move(key, moved.replace(candidates=None), moving, params, dyn)
    reward = dyn.alpha * parts.reward_exploration + dyn.beta * parts.reward_discovery \
        + dyn.gamma * parts.reward_communication
    reward = jnp.where(moving, reward, 0.0)
    info = parts.replace(acted=moving)
    return _observations(key, state, params, dyn), state, reward, state.done, info


@functools.partial(jax.jit, static_argnames="params", inline=True)
def _observations(key, state: EnvState, params: EnvParams, dyn: DynamicParams) -> Observation:
    """The team's observations with the lookahead input; the belief's facade rates are
    computed once for both."""
    rates = belief_rates(state, params)
    return lookahead.with_ahead_rates(key, observe(state, params, rates), state, params, dyn,
                                      rates)


def _move(state: EnvState, actions, params: EnvParams, dyn: DynamicParams):
    """Flies every active robot towards its chosen candidate under the flight rules of
    `jaxmripp.spec.flight`, charges the budget and counts collisions against the truth;
    returns (state, moving (N,) bool)."""
    n, size, reach = params.n_robots, params.size, params.candidates.shell[1]
    rows = jnp.arange(n)
    target = state.candidates.position[rows, actions]
    target_heading = state.candidates.heading[rows, actions]
    chosen = ~state.done & state.candidates.valid[rows, actions]

    # One traversal per flight, checked against the truth and, with `truncate`, against
    # the robot's map: it stops before the first voxel that is a building or (truncate) not
    # known to be free. Maps never call a building FREE, so with `truncate` the first such
    # voxel is always one the robot did not know: a blocked move, never a collision.
    truncate = params.safety.flight == "truncate"

    def fly(start, end, robot):
        own_map = maps.robot_map(state.team_map, robot)

        def unknown(v):
            return geometry.read_codes(own_map, geometry.linear_index(v, size)) != FREE

        def building(v):
            return worldmod.occupied(state.world, v)

        stop, hit, _, voxel = geometry.fly_until(
            start, end, (lambda v: unknown(v) | building(v)) if truncate else building,
            size, reach)
        crashed = hit & building(voxel) & ~(truncate & unknown(voxel))
        return stop, crashed, hit & ~crashed, voxel

    stop, crashed, blocked, obstacle = jax.vmap(fly)(state.position, target, rows)
    heard = comms.contacts(state.position, dyn.radio_range)
    # Robots announce the flights they will really fly (their intents).
    held = flight.holds(state.position, stop, chosen, heard, dyn.collision_distance)
    moving = chosen & ~held
    blocked = moving & blocked
    crashed = moving & crashed
    position = jnp.where(moving[:, None], stop, state.position)
    flown = jnp.linalg.norm(position - state.position, axis=-1)
    turned = moving & (target_heading != state.heading)
    charge = flown + dyn.turn_cost * turned
    in_range, out_of_range = flight.robot_collisions(state.position, position, moving, heard,
                                                     dyn.collision_distance)
    m = state.metrics
    metrics = m.replace(
        obstacle_collisions=m.obstacle_collisions + crashed,
        blocked=m.blocked + blocked,
        held=m.held + held,
        robot_collisions_in_range=m.robot_collisions_in_range + in_range,
        robot_collisions_out_of_range=m.robot_collisions_out_of_range + out_of_range,
        distance=m.distance + flown,
    )
    # A robot that hit a building learns the voxel, so it does not try it again.
    bumped = jnp.where(crashed, geometry.linear_index(obstacle, size), size ** 3)
    team_map = maps.observe(state.team_map, bumped[:, None])
    top = jax.vmap(tops.raise_tops)(state.building_top, bumped,
                                    jnp.full((n,), OCCUPIED, jnp.int8))
    moved = state.replace(
        position=position,
        team_map=team_map,
        building_top=top,
        heading=jnp.where(moving, target_heading, state.heading),
        budget_left=jnp.maximum(state.budget_left - charge, 0.0),
        step=state.step + 1,
        metrics=metrics,
    )
    return moved, moving


@functools.partial(jax.jit, static_argnames="params", inline=True)
def _after_move(key, state: EnvState, moved, params: EnvParams, dyn: DynamicParams):
    """Sensing, history, radio, GP updates and new candidates after the robots moved.

    `state` comes without candidates (None): this computes them afresh, so reset and
    step hand it the same structure and share its trace."""
    n, size = params.n_robots, params.size
    casts = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))(
        state.world, state.position, state.heading, params.sensor, size)
    team_map = maps.observe(state.team_map, casts.voxels)
    top = jax.vmap(tops.raise_tops_from_cast)(state.building_top, casts)
    seen = casts.seen & moved[:, None]
    fresh = seen & ~state.discovered[None]
    finders = fresh.sum(axis=0)  # (T,) robots that found each window at this step
    new_windows = finders > 0
    reward_discovery = (fresh / jnp.maximum(finders, 1)).sum(axis=1)  # split among finders
    discovered = state.discovered | new_windows

    utility = jax.vmap(sensing.utility)(casts).astype(jnp.float32) / dyn.utility_norm
    length = jnp.diagonal(state.know)
    slot = jnp.minimum(length, params.max_steps)
    rows = jnp.arange(n)
    pose = geometry.pose(state.position, state.heading)
    history_pose = state.history_pose.at[rows, slot].set(
        jnp.where(moved[:, None], pose, state.history_pose[rows, slot]))
    history_utility = state.history_utility.at[rows, slot].set(
        jnp.where(moved, utility, state.history_utility[rows, slot]))
    know = state.know + jnp.diag(moved.astype(jnp.int32))

    contact = comms.contacts(state.position, dyn.radio_range)
    know = comms.exchange(know, contact, params.radio.relay)
    if params.radio.share_maps:
        team_map, top = comms.share_maps(team_map, top, contact, params.radio.relay)
    state = state.replace(team_map=team_map, building_top=top, heard=contact,
                          discovered=discovered, history_pose=history_pose,
                          history_utility=history_utility, know=know,
                          metrics=state.metrics.replace(
                              contacts=state.metrics.contacts + contact.sum() // 2))
    state, reward_exploration, reward_communication = feed_gps(state, params)

    new_candidates = team_candidates(key, state, contact, params, dyn)
    done = state.done | ~jnp.any(new_candidates.valid, axis=1) | (state.step >= params.max_steps)
    state = state.replace(candidates=new_candidates, done=done)
    info = StepInfo(
        reward_exploration=reward_exploration,
        reward_discovery=reward_discovery,
        reward_communication=reward_communication,
        discovered_fraction=discovered_fraction(state),
        acted=moved,
        metrics=state.metrics,
    )
    return state, info


def team_candidates(key, state: EnvState, contact: jax.Array, params: EnvParams,
                    dyn: DynamicParams) -> cands.Candidates:
    """Every robot's candidates (`candidates.sample`) on its own map; (N, N) `contact`:
    the robots within radio range, the ones whose positions a robot knows."""
    own_maps = maps.robot_map(state.team_map, jnp.arange(params.n_robots))
    return jax.vmap(
        cands.sample,
        in_axes=(0, 0, 0, 0, maps.RobotMap(None, 0), None, 0, None, None, None, None, None))(
        jax.random.split(key, params.n_robots), state.position, state.heading,
        state.budget_left, own_maps, state.position, contact, params.candidates,
        params.safety, dyn.turn_cost, dyn.collision_distance, params.size)


def step_auto_reset(keys, states: EnvState, actions, params: EnvParams, dyn: DynamicParams,
                    reset_obs: Observation, reset_states: EnvState, max_resets: int,
                    pool_used: jax.Array | int = 0):
    """`step` over a leading environment axis E, then restarts environments whose robots
    are all done from a pool of P prepared reset states.

    Computing a fresh reset inside every step would double its cost (a reset casts, feeds
    GPs and samples candidates too), so rollouts prepare the resets up front. Swapping
    them in with a select over all E states would read and write every occupancy map and
    GP each step, so at most `max_resets` environments, the lowest-numbered finished ones,
    are copied in, one row each. A finished environment beyond that waits a step: its
    robots are all done, so it yields no samples and loses nothing but time. Restarts take
    pool entries in order, from `pool_used` (entries taken so far in this rollout) on,
    wrapping around after P: an environment that finishes twice in one rollout starts a
    new world, where indexing the pool by environment would replay its previous start.
    Returns (obs, states, reward, done, info, restarted (E,) bool, pool_used after this
    step).
    """
    envs = actions.shape[0]
    pool = reset_obs.mask.shape[0]
    obs, states, reward, done, info = jax.vmap(step, in_axes=(0, 0, 0, None, None))(
        keys, states, actions, params, dyn)
    finished = jax.vmap(episode_done)(states)
    (slots,) = jnp.nonzero(finished, size=max_resets, fill_value=envs)  # envs: no slot
    restarted = jnp.zeros((envs,), bool).at[slots].set(True, mode="drop")

    def copy_in(index, carry):
        # One row copy per restarted environment: XLA:CPU runs a scatter element by
        # element, a dynamic slice update as a block copy.
        slot, entry = slots[index], (pool_used + index) % pool

        def put(current, fresh):
            new = jax.lax.dynamic_index_in_dim(fresh, entry, keepdims=True)
            return jax.lax.dynamic_update_index_in_dim(current, new, slot, axis=0)

        return jax.tree.map(put, carry, (reset_obs, reset_states))

    # A traced trip count: only the restarted environments are copied, not max_resets.
    count = jnp.minimum(jnp.sum(finished), max_resets)
    obs, states = jax.lax.fori_loop(0, count, copy_in, (obs, states))
    return obs, states, reward, done, info, restarted, pool_used + count
