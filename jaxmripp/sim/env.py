"""The multi-robot MRIPP environment as pure functions (gymnax style).

`EnvParams` is static (hashable, passed to jit as a static argument); `EnvState` is a
pytree of arrays with per-robot data stacked on a leading robot axis of size N.

One step: actions (N,) -> straight-line moves checked against the ground truth -> ray
casts from the new poses (detections, occupancy maps) -> history and radio exchange ->
GP updates -> new candidates -> observations and rewards.
"""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.sim import candidates as cands
from jaxmripp.sim import comms, geometry, gp, sensing, world as worldmod
from jaxmripp.config import (CandidateConfig, Config, GPConfig, RadioConfig, RewardConfig,
                             RobotConfig, SensorConfig, WorldConfig)
from jaxmripp.sim.observation import FEATURES, ROBOT_STATE, Observation


@dataclasses.dataclass(frozen=True)
class EnvParams:
    world: WorldConfig
    robots: RobotConfig
    sensor: SensorConfig
    radio: RadioConfig
    candidates: CandidateConfig
    gp: GPConfig
    reward: RewardConfig
    max_steps: int

    @classmethod
    def from_config(cls, cfg: Config) -> "EnvParams":
        return cls(cfg.world, cfg.robots, cfg.sensor, cfg.radio, cfg.candidates, cfg.gp,
                   cfg.reward, cfg.episode.max_steps)

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
    def utility_gps(self) -> int:
        return 1 if self.gp.shared_utility else self.robots.count


@struct.dataclass
class Metrics:
    obstacle_collisions: jax.Array  # (N,) int32 moves stopped by a building
    robot_collisions: jax.Array  # (N,) int32 moves ending within d_c of another robot
    distance: jax.Array  # (N,) float32 path length flown
    contacts: jax.Array  # () int32 robot pairs in radio contact, summed over steps


@struct.dataclass
class EnvState:
    """N robots, T target slots, G voxels per side, H = T_max + 1 history entries."""

    world: worldmod.World
    position: jax.Array  # (N, 3) float32
    heading: jax.Array  # (N,) int32 index into geometry.HEADING_ANGLES
    budget_left: jax.Array  # (N,) float32
    budget_initial: jax.Array  # () float32 per-robot share of the team budget
    done: jax.Array  # (N,) bool: out of affordable candidates or out of steps
    occupancy: jax.Array  # (N, G, G, G) int8 per-robot maps (geometry codes)
    discovered: jax.Array  # (T,) bool: found by anybody
    history_pose: jax.Array  # (N, H, 4) poses each robot visited, in order
    history_utility: jax.Array  # (N, H) normalised number of windows seen from each
    know: jax.Array  # (N, N) int32: robot i knows the first know[i, j] entries of j's history
    fed: jax.Array  # (N, N) int32: entries of j's history already in robot i's GPs
    utility_gp: gp.GPState  # leading axis N (or 1 with a shared utility GP)
    comm_gp: gp.GPState  # leading axis N
    candidates: cands.Candidates  # (N, L) the poses the current observation offers
    step: jax.Array  # () int32
    metrics: Metrics


@struct.dataclass
class StepInfo:
    reward_exploration: jax.Array  # (N,) r_e
    reward_discovery: jax.Array  # (N,) r_u, new targets (ties split evenly)
    reward_communication: jax.Array  # (N,) r_c
    discovered_fraction: jax.Array  # ()
    acted: jax.Array  # (N,) bool: the robot was active and its action counted this step
    metrics: Metrics


# ---------------------------------------------------------------------------------------
# Reset and step


def reset(key: chex.PRNGKey, params: EnvParams) -> tuple[Observation, EnvState]:
    n, size = params.n_robots, params.size
    key_world, key_budget, key_rest = jax.random.split(key, 3)
    world = worldmod.generate(key_world, params.world)
    lo, hi = params.robots.budget
    budget = jax.random.uniform(key_budget, (), minval=lo, maxval=hi) / n
    eval_poses = gp.evaluation_poses(params.gp)
    batched = lambda tree, count: jax.tree.map(lambda x: jnp.broadcast_to(x, (count, *x.shape)), tree)
    empty_gp = gp.empty(params.gp, eval_poses)
    history = params.max_steps + 1
    state = EnvState(
        world=world,
        position=jnp.broadcast_to(jnp.asarray(params.robots.start, jnp.float32), (n, 3)),
        heading=jnp.full((n,), params.robots.start_heading, jnp.int32),
        budget_left=jnp.full((n,), budget, jnp.float32),
        budget_initial=budget.astype(jnp.float32),
        done=jnp.zeros((n,), bool),
        occupancy=jnp.broadcast_to(sensing.empty_occupancy(size), (n, size, size, size)),
        discovered=jnp.zeros(world.target_valid.shape, bool),
        history_pose=jnp.zeros((n, history, 4), jnp.float32),
        history_utility=jnp.zeros((n, history), jnp.float32),
        know=jnp.zeros((n, n), jnp.int32),
        fed=jnp.zeros((n, n), jnp.int32),
        utility_gp=batched(empty_gp, params.utility_gps),
        comm_gp=batched(empty_gp, n),
        candidates=None,
        step=jnp.zeros((), jnp.int32),
        metrics=Metrics(jnp.zeros((n,), jnp.int32), jnp.zeros((n,), jnp.int32),
                        jnp.zeros((n,), jnp.float32), jnp.zeros((), jnp.int32)),
    )
    state, _ = _after_move(key_rest, state, jnp.ones((n,), bool), params)
    return observe(state, params), state


def step(key: chex.PRNGKey, state: EnvState, actions: jax.Array, params: EnvParams):
    """actions (N,) int32 candidate indices -> (obs, state, reward (N,), done (N,), info)."""
    chex.assert_shape(actions, (params.n_robots,))
    n = params.n_robots
    rows = jnp.arange(n)
    target = state.candidates.position[rows, actions]
    target_heading = state.candidates.heading[rows, actions]
    moving = ~state.done & state.candidates.valid[rows, actions]

    stop, blocked, obstacle = jax.vmap(_fly, in_axes=(None, 0, 0, None))(
        state.world, state.position, target, params)
    position = jnp.where(moving[:, None], stop, state.position)
    flown = jnp.linalg.norm(position - state.position, axis=-1)
    turned = moving & (target_heading != state.heading)
    charge = flown + params.robots.turn_cost * turned
    separation = jnp.linalg.norm(position[:, None] - position[None], axis=-1)
    crowded = (separation < params.radio.collision_distance) & ~jnp.eye(n, dtype=bool)
    m = state.metrics
    metrics = m.replace(
        obstacle_collisions=m.obstacle_collisions + (moving & blocked),
        robot_collisions=m.robot_collisions + (moving & jnp.any(crowded, axis=1)),
        distance=m.distance + flown,
    )
    # A blocked robot learns the voxel it bumped into, so it does not try it again.
    size = params.size
    bumped = jnp.where(moving & blocked, geometry.linear_index(obstacle, size), size ** 3)
    occupancy = jax.vmap(lambda occ, index: occ.reshape(-1).at[index].set(
        geometry.OCCUPIED, mode="drop").reshape(occ.shape))(state.occupancy, bumped)
    moved = state.replace(
        position=position,
        occupancy=occupancy,
        heading=jnp.where(moving, target_heading, state.heading),
        budget_left=jnp.maximum(state.budget_left - charge, 0.0),
        step=state.step + 1,
        metrics=metrics,
    )
    state, parts = _after_move(key, moved, moving, params)
    r = params.reward
    reward = r.alpha * parts.reward_exploration + r.beta * parts.reward_discovery \
        + r.gamma * parts.reward_communication
    reward = jnp.where(moving, reward, 0.0)
    info = parts.replace(acted=moving)
    return observe(state, params), state, reward, state.done, info


def _fly(world, start, end, params: EnvParams):
    """Moves along a straight segment; stops at the last free sample before a building.

    Returns the stop position, whether the move was blocked and the blocking voxel.
    """
    points, voxels = geometry.segment_voxels(start, end, params.size, params.candidates.shell[1])
    hit = worldmod.occupied(world, voxels)
    first = jnp.argmax(hit)
    blocked = jnp.any(hit)
    last_free = jnp.where(first == 0, start, points[jnp.maximum(first - 1, 0)])
    return jnp.where(blocked, last_free, end), blocked, voxels[first]


def _after_move(key, state: EnvState, moved, params: EnvParams):
    """Sensing, history, radio, GP updates and new candidates after the robots moved."""
    n, size = params.n_robots, params.size
    casts = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))(
        state.world, state.position, state.heading, params.sensor, size)
    occupancy = jax.vmap(sensing.update_occupancy)(state.occupancy, casts)
    seen = casts.seen & moved[:, None]
    fresh = seen & ~state.discovered[None]
    finders = jnp.maximum(fresh.sum(axis=0), 1)
    reward_discovery = (fresh / finders).sum(axis=1)
    discovered = state.discovered | jnp.any(seen, axis=0)

    utility = jax.vmap(sensing.utility)(casts).astype(jnp.float32) / params.reward.utility_norm
    length = jnp.diagonal(state.know)
    slot = jnp.minimum(length, params.max_steps)
    rows = jnp.arange(n)
    pose = geometry.pose(state.position, state.heading)
    history_pose = state.history_pose.at[rows, slot].set(
        jnp.where(moved[:, None], pose, state.history_pose[rows, slot]))
    history_utility = state.history_utility.at[rows, slot].set(
        jnp.where(moved, utility, state.history_utility[rows, slot]))
    know = state.know + jnp.diag(moved.astype(jnp.int32))

    contact = comms.contacts(state.position, params.radio.range)
    know = comms.exchange(know, contact, params.radio.relay)
    state = state.replace(occupancy=occupancy, discovered=discovered, history_pose=history_pose,
                          history_utility=history_utility, know=know,
                          metrics=state.metrics.replace(
                              contacts=state.metrics.contacts + contact.sum() // 2))
    state, reward_exploration, reward_communication = _feed_gps(state, params)

    keys = jax.random.split(key, n)
    others_known = contact  # robots within radio range are the ones whose positions we know
    new_candidates = jax.vmap(
        cands.sample, in_axes=(0, 0, 0, 0, 0, None, 0, None, None, None, None))(
        keys, state.position, state.heading, state.budget_left, state.occupancy,
        state.position, others_known, params.candidates, params.robots,
        params.radio.collision_distance, size)
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


def _relative_drop(before, after):
    return jnp.where(before > 0, (before - after) / jnp.maximum(before, 1e-12), 0.0)


def _feed_gps(state: EnvState, params: EnvParams):
    """Adds newly known history entries to the GPs with a fixed number of slots per step.

    Each robot ingests its own newest pose first (its trace drop is r_e), then runs
    N - 1 + `catchup_rounds` peer rounds: in each it takes the oldest pending pose of the
    peer with the largest backlog (ties: the nearest peer offset) into both GPs (the trace
    drop on the communication GP is r_c). A steady exchange needs N - 1 rounds; the rest
    drain a backlog after radio silence. Every step does the same fixed amount of O(H^2)
    work: the rounds' poses enter each GP in blocks of up to gp.BLOCK points, masked where
    nothing is pending, and a per-robot utility GP takes the own pose as its block's first
    point.
    """
    n, cfg = params.n_robots, params.gp
    eval_poses = gp.evaluation_poses(cfg)
    rows = jnp.arange(n)

    def take(fed, know, i, j):
        pending = fed[i, j] < know[i, j]
        index = jnp.minimum(fed[i, j], params.max_steps)
        return pending, state.history_pose[j, index], state.history_utility[j, index]

    own_pending, own_pose, own_value = jax.vmap(lambda i: take(state.fed, state.know, i, i))(rows)
    fed = state.fed + jnp.diag(own_pending.astype(jnp.int32))

    # Peers' poses, learned by radio, for the communication GP (and per-robot utility
    # GPs). The rounds only pick poses (index bookkeeping); each GP then takes them in
    # blocks, each costing about one add instead of one per round (gp.add_many).
    peers = (rows[:, None] + jnp.arange(1, n)[None, :]) % n  # (N, N - 1) by offset

    def pick(fed, _):
        backlog = state.know[rows[:, None], peers] - fed[rows[:, None], peers]
        j = peers[rows, jnp.argmax(backlog, axis=1)]  # first maximum: nearest offset
        pending, pose, value = jax.vmap(lambda i, jj: take(fed, state.know, i, jj))(rows, j)
        return fed.at[rows, j].add(pending.astype(jnp.int32)), (pending, pose, value)

    if n > 1:
        fed, (pending, pose, value) = jax.lax.scan(pick, fed, length=n - 1 + cfg.catchup_rounds)
        pending, pose, value = (jnp.swapaxes(x, 0, 1) for x in (pending, pose, value))  # (N, R)
    else:  # a lone robot has no peers: no rounds
        pending, pose, value = jnp.zeros((n, 0), bool), jnp.zeros((n, 0, 4)), jnp.zeros((n, 0))
    add_many = jax.vmap(gp.add_many, in_axes=(0, 0, 0, None, None, 0))

    # Own newest pose into the utility GP(s), first: its trace drop is the exploration reward.
    if cfg.shared_utility:
        def own_shared(shared, i):
            before = gp.covariance_trace(shared)
            shared = gp.add(shared, own_pose[i], own_value[i], cfg, eval_poses, own_pending[i])
            return shared, _relative_drop(before, gp.covariance_trace(shared))

        shared = jax.tree.map(lambda x: x[0], state.utility_gp)
        shared, reward_exploration = jax.lax.scan(own_shared, shared, rows)
        utility_gp = jax.tree.map(lambda x: x[None], shared)
    else:
        # The own pose leads a block with the first peers' poses rather than going in as
        # an add of its own (measured: this function over 1024 envs 156 vs 173 ms), and
        # gp.add_block_first_trace still gives the own pose's trace drop exactly.
        lead = gp.BLOCK - 1
        before = jax.vmap(gp.covariance_trace)(state.utility_gp)
        block_pose, block_value, block_pending = (
            jnp.concatenate([own[:, None], peer[:, :lead]], axis=1) for own, peer in
            ((own_pose, pose), (own_value, value), (own_pending, pending)))
        utility_gp, own_trace = jax.vmap(
            gp.add_block_first_trace, in_axes=(0, 0, 0, None, None, 0))(
            state.utility_gp, block_pose, block_value, cfg, eval_poses, block_pending)
        reward_exploration = _relative_drop(before, own_trace)
        utility_gp = add_many(utility_gp, pose[:, lead:], value[:, lead:], cfg, eval_poses,
                              pending[:, lead:])

    comm_before = jax.vmap(gp.covariance_trace)(state.comm_gp)
    comm_gp = add_many(state.comm_gp, pose, jnp.ones_like(value), cfg, eval_poses, pending)
    reward_communication = _relative_drop(comm_before, jax.vmap(gp.covariance_trace)(comm_gp))
    state = state.replace(fed=fed, utility_gp=utility_gp, comm_gp=comm_gp)
    return state, reward_exploration, reward_communication


# ---------------------------------------------------------------------------------------
# Observations and metrics


def observe(state: EnvState, params: EnvParams) -> Observation:
    """Per-robot observations (leading axis N), laid out as observation.FEATURES."""
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
    features = jnp.concatenate([
        (c.position - state.position[:, None]) / params.candidates.shell[1],
        c.position,
        heading_onehot,
        u_mean[..., None], jnp.sqrt(u_var)[..., None],
        c_mean[..., None], jnp.sqrt(c_var)[..., None],
        c.cost[..., None],
        ((state.budget_left[:, None] - c.cost) / budget)[..., None],
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
    chex.assert_shape(features, (n, params.n_candidates, len(FEATURES)))
    chex.assert_shape(robot_state, (n, len(ROBOT_STATE)))
    return Observation(features=features.astype(jnp.float32), mask=mask,
                       robot_state=robot_state.astype(jnp.float32),
                       global_state=jnp.broadcast_to(global_state, (n, global_state.shape[0])))


def discovered_fraction(state: EnvState) -> jax.Array:
    """Share of the world's real windows found so far (divides by the real count)."""
    total = jnp.maximum(state.world.target_valid.sum(), 1)
    return (state.discovered & state.world.target_valid).sum() / total


def episode_done(state: EnvState) -> jax.Array:
    return jnp.all(state.done)


def step_auto_reset(keys, states: EnvState, actions, params: EnvParams,
                    reset_obs: Observation, reset_states: EnvState, max_resets: int,
                    pool_used: jax.Array | int = 0):
    """`step` over a leading environment axis E, then restarts environments whose robots
    are all done from a pool of P prepared reset states.

    Computing a fresh reset inside every step would double its cost (a reset casts, feeds
    GPs and samples candidates too), so rollouts prepare the resets up front. Swapping
    them in with a select over all E states would read and write every occupancy map and
    GP each step (measured: 10% of a 256-environment rollout), so at most `max_resets`
    environments, the lowest-numbered finished ones, are copied in, one row each. A
    finished environment beyond that waits a step: its robots are all done, so it yields
    no samples and loses nothing but time. Restarts take pool entries in order, from
    `pool_used` (entries taken so far in this rollout) on, wrapping around after P: an
    environment that finishes twice in one rollout starts a new world, where indexing the
    pool by environment replayed its previous start (measured: 6-9% of the episodes of a
    1024-environment rollout). Returns (obs, states, reward, done, info, restarted (E,)
    bool, pool_used after this step).
    """
    envs = actions.shape[0]
    pool = reset_obs.mask.shape[0]
    obs, states, reward, done, info = jax.vmap(step, in_axes=(0, 0, 0, None))(
        keys, states, actions, params)
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
