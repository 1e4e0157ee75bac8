"""The GP feeding schedule: which known history entries enter which GP, each step.

Each robot ingests its own newest pose first (its trace drop is r_e), then runs
R = N - 1 + `catchup_rounds` peer rounds: in each it takes the oldest
pending pose of the peer with the largest backlog (ties: the nearest peer offset) into
both GPs (the trace drop on the communication GP is r_c). A steady exchange needs N - 1
rounds; the rest drain a backlog after radio silence. Every step does the same fixed
amount of O(H^2) work: the rounds' poses enter each GP in blocks of up to gp.BLOCK points,
masked where nothing is pending, and a per-robot utility GP takes the own pose as its
block's first point.

Only static parameters are read: the schedule's shape is fixed by N, H and the GP config.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmripp.sim import gp
from jaxmripp.sim.params import EnvParams
from jaxmripp.sim.types import EnvState
from jaxmripp.spec.feeding import peer_rounds


def relative_drop(before, after):
    return jnp.where(before > 0, (before - after) / jnp.maximum(before, 1e-12), 0.0)


def feed_gps(state: EnvState, params: EnvParams):
    """Feeds the GPs one step's worth; returns (state, r_e (N,), r_c (N,))."""
    n, cfg = params.n_robots, params.gp
    rows = jnp.arange(n)

    def take(fed, i, j):
        pending = fed[i, j] < state.know[i, j]
        index = jnp.minimum(fed[i, j], params.max_steps)
        return pending, state.history_pose[j, index], state.history_utility[j, index]

    own_pending, own_pose, own_value = jax.vmap(lambda i: take(state.fed, i, i))(rows)
    fed = state.fed + jnp.diag(own_pending.astype(jnp.int32))
    rounds = peer_rounds(n, cfg.catchup_rounds)
    fed, pending, pose, value = _pick_peer_poses(state, fed, take, n, rounds)
    own = (own_pending, own_pose, own_value)
    peers = (pending, pose, value)
    if cfg.shared_utility:
        utility_gp, reward_exploration = _own_into_shared(state.utility_gp, own, params)
    else:
        utility_gp, reward_exploration = _own_and_peers(state.utility_gp, own, peers, params)

    # The communication GP takes every peer pose with value 1: it marks where peers have
    # been, not what they saw there.
    eval_poses = gp.evaluation_poses(cfg)
    comm_before = jax.vmap(gp.covariance_trace)(state.comm_gp)
    comm_gp = _add_many(state.comm_gp, pose, jnp.ones_like(value), cfg, eval_poses, pending)
    reward_communication = relative_drop(comm_before, jax.vmap(gp.covariance_trace)(comm_gp))
    state = state.replace(fed=fed, utility_gp=utility_gp, comm_gp=comm_gp)
    return state, reward_exploration, reward_communication


_add_many = jax.vmap(gp.add_many, in_axes=(0, 0, 0, None, None, 0))


def _pick_peer_poses(state: EnvState, fed, take, n: int, rounds: int):
    """Picks the peers' poses of every round: (fed, pending, pose, value), each (N, R).

    The rounds only pick poses (index bookkeeping); each GP then takes them in blocks,
    each costing about one add instead of one per round (gp.add_many).
    """
    if rounds == 0:  # a lone robot has no peers
        return fed, jnp.zeros((n, 0), bool), jnp.zeros((n, 0, 4)), jnp.zeros((n, 0))
    rows = jnp.arange(n)
    peers = (rows[:, None] + jnp.arange(1, n)[None, :]) % n  # (N, N - 1) by offset

    def pick(fed, _):
        backlog = state.know[rows[:, None], peers] - fed[rows[:, None], peers]
        j = peers[rows, jnp.argmax(backlog, axis=1)]  # first maximum: nearest offset
        pending, pose, value = jax.vmap(lambda i, jj: take(fed, i, jj))(rows, j)
        return fed.at[rows, j].add(pending.astype(jnp.int32)), (pending, pose, value)

    fed, picked = jax.lax.scan(pick, fed, length=rounds)
    return (fed, *(jnp.swapaxes(x, 0, 1) for x in picked))


def _own_into_shared(utility_gp, own, params: EnvParams):
    """One utility GP for the team: robots add their own pose in index order, and each
    robot's r_e is the trace drop its pose causes after the robots before it."""
    cfg = params.gp
    eval_poses = gp.evaluation_poses(cfg)
    own_pending, own_pose, own_value = own

    def add_own(shared, i):
        before = gp.covariance_trace(shared)
        shared = gp.add(shared, own_pose[i], own_value[i], cfg, eval_poses, own_pending[i])
        return shared, relative_drop(before, gp.covariance_trace(shared))

    shared = jax.tree.map(lambda x: x[0], utility_gp)
    shared, reward_exploration = jax.lax.scan(add_own, shared, jnp.arange(params.n_robots))
    return jax.tree.map(lambda x: x[None], shared), reward_exploration


def _own_and_peers(utility_gp, own, peers, params: EnvParams):
    """Per-robot utility GPs: the own pose leads a block with the first peers' poses
    rather than going in as an add of its own (one block update is cheaper than two), and
    gp.add_block_first_trace still gives the own pose's trace drop exactly."""
    cfg = params.gp
    eval_poses = gp.evaluation_poses(cfg)
    lead = gp.BLOCK - 1
    pending, pose, value = peers
    before = jax.vmap(gp.covariance_trace)(utility_gp)
    block_pending, block_pose, block_value = (
        jnp.concatenate([o[:, None], p[:, :lead]], axis=1) for o, p in zip(own, peers))
    utility_gp, own_trace = jax.vmap(
        gp.add_block_first_trace, in_axes=(0, 0, 0, None, None, 0))(
        utility_gp, block_pose, block_value, cfg, eval_poses, block_pending)
    reward_exploration = relative_drop(before, own_trace)
    utility_gp = _add_many(utility_gp, pose[:, lead:], value[:, lead:], cfg, eval_poses,
                           pending[:, lead:])
    return utility_gp, reward_exploration
