"""Sequential-allocation Monte-Carlo tree search over the candidate graph (the MCTS baseline).

The paper compares against an MCTS planner with sequential allocation: robots plan one
after another, each seeing the poses the others already chose. This is an affordable
version of it built on `mctx` (Gumbel MuZero search, which makes good use of a few
simulations), with the robot's own utility GP as the model. Simplifications, on purpose:

- Actions. Every tree node offers the L candidate moves of the root, as offsets: action a
  at a node at position q flies to q + (c_a - p) with heading h_a, where c_a, h_a are the
  robot's current candidates and p its position. No candidates are re-sampled inside the
  tree. At the root the env's feasibility mask is used as is; deeper, a move is feasible
  when its slot is a real draw, it stays in the unit cube, fits the node's remaining
  budget (distance + turn cost), is not a no-op and its straight line crosses no voxel
  the robot's own map knows to be occupied.
- Model (the reward of reaching pose x). With S the hallucinated poses (the node's own
  path in the tree and the poses that peers within radio range chose this step) and
  mu, sigma^2 the utility GP's posterior mean and variance,
      r(x | S) = mu(x) sigma^2(x | S) / variance + kappa sigma(x | S)      (novelty=True)
  sigma(x | S) conditions the GP on observations at S: a hallucinated update, whose
  values are unknown but whose effect on the variance is not. The GP predicts how many
  windows a pose sees, not how many it sees first, and a hallucinated update leaves the
  mean unchanged, so the expected windows are weighted by the relative variance: near a
  visited or claimed pose they were probably seen already. With novelty=False the
  discount is simpler: r = mu(x) (1 - max_s k(x, s) / variance) + kappa sigma(x | S).
  On small test worlds the novelty form with kappa = 0.3 found the most windows.
- Leaf values are the best one-step reward among the leaf's children (a greedy rollout of
  length one); rewards along a path are discounted by `discount`.
- Search: `mctx.gumbel_muzero_policy` with `simulations`, `max_depth` and
  `considered` actions; priors are r / `temperature`. With gumbel_scale = 0 (default) the
  result is deterministic apart from a tiny random tie-break, like the other baselines.
- Robots search in index order (scan), so the cost per step grows linearly with N.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mctx
from flax import struct

from jaxmripp.sim import comms, geometry, gp
from jaxmripp.evaluation.baselines import no_memory, masked_argmax
from jaxmripp.sim.episode import Planner

_NEG = -1e9  # prior logit of infeasible actions


@struct.dataclass
class Node:
    """One tree node (an mctx embedding). D = max depth, L = candidates."""

    position: jax.Array  # (3,)
    heading: jax.Array  # () int32
    budget: jax.Array  # () float32 left at this node
    path: jax.Array  # (D, 4) poses reached in the tree so far
    path_valid: jax.Array  # (D,) bool
    depth: jax.Array  # () int32
    child_score: jax.Array  # (L,) r(child | S) of each action from here
    child_valid: jax.Array  # (L,) bool


@struct.dataclass
class Context:
    """What stays fixed during one robot's search (passed to mctx as `params`)."""

    utility: gp.GPState  # the robot's own utility GP
    occupancy: jax.Array  # (G, G, G) int8 the robot's own map
    offset: jax.Array  # (L, 3) candidate position minus robot position
    heading: jax.Array  # (L,) int32 candidate headings
    slot_kept: jax.Array  # (L,) bool the candidate's slot is a real draw
    peer_pose: jax.Array  # (N, 4) poses chosen by robots earlier in the order
    peer_valid: jax.Array  # (N,) bool chosen and within radio range
    turn_cost: jax.Array  # () DynamicParams.turn_cost


def scores(ctx: Context, poses, path, path_valid, gp_cfg, kappa: float, novelty: bool = True):
    """r(x | S) for poses (K, 4), S = path (valid rows) + the peers' chosen poses."""
    s = jnp.concatenate([path, ctx.peer_pose])
    on = jnp.concatenate([path_valid, ctx.peer_valid])
    mean, var, px = gp.predict_projected(ctx.utility, poses, gp_cfg)
    ps = gp.predict_projected(ctx.utility, s, gp_cfg)[2]
    prior_xs = gp.kernel(poses, s, gp_cfg)
    c_xs = jnp.where(on[None], prior_xs - px @ ps.T, 0.0)  # posterior covariance (K, S)
    c_ss = gp.kernel(s, s, gp_cfg) - ps @ ps.T
    c_ss = jnp.where(on[:, None] & on[None], c_ss, 0.0) + jnp.diag(
        jnp.where(on, gp_cfg.noise, 1.0))
    factor = jax.scipy.linalg.cho_factor(c_ss, lower=True)
    drop = jnp.sum(c_xs * jax.scipy.linalg.cho_solve(factor, c_xs.T).T, axis=-1)
    var_s = jnp.clip(var - drop, 0.0, gp_cfg.variance)
    if novelty:
        return mean * var_s / gp_cfg.variance + kappa * jnp.sqrt(var_s)
    corr = jnp.max(jnp.where(on[None], prior_xs / gp_cfg.variance, 0.0), axis=-1)
    return mean * (1.0 - corr) + kappa * jnp.sqrt(var_s)


def tree_search_planner(params, simulations: int = 16, max_depth: int = 2,
                        considered: int = 4, kappa: float = 0.3, discount: float = 0.9,
                        temperature: float = 0.1, gumbel_scale: float = 0.0,
                        novelty: bool = True, name: str = "mcts") -> Planner:
    """The MCTS baseline (module docstring); `params` is the env's static EnvParams, the
    turn cost and radio range come traced from `act`'s `dyn`."""
    gp_cfg, size = params.gp, params.size
    reach = params.candidates.shell[1]
    shared = params.gp.shared_utility
    line_ok = geometry.line_rule(params.safety.flight)

    def children(ctx: Context, node: Node):
        """Poses (L, 4), feasibility (L,) and scores (L,) of a (non-root) node's actions."""
        position = node.position + ctx.offset
        distance = jnp.linalg.norm(ctx.offset, axis=-1)
        turned = ctx.heading != node.heading
        cost = distance + ctx.turn_cost * turned
        valid = (ctx.slot_kept & geometry.inside_world(position) & (cost <= node.budget)
                 & ((distance > 0) | turned)
                 & line_ok(node.position, position, ctx.occupancy, size, reach))
        return geometry.pose(position, ctx.heading), valid

    def expand(ctx: Context, action, node: Node):
        ok = node.child_valid[action]
        reward = jnp.where(ok, node.child_score[action], 0.0)
        offset = ctx.offset[action]
        heading = ctx.heading[action]
        cost = jnp.linalg.norm(offset) + ctx.turn_cost * (heading != node.heading)
        position = node.position + offset
        slot = jnp.minimum(node.depth, node.path.shape[0] - 1)
        child = node.replace(
            position=position, heading=heading, budget=node.budget - cost,
            path=node.path.at[slot].set(geometry.pose(position, heading)),
            path_valid=node.path_valid.at[slot].set(True), depth=node.depth + 1)
        poses, valid = children(ctx, child)
        valid &= ok
        score = scores(ctx, poses, child.path, child.path_valid, gp_cfg, kappa, novelty)
        child = child.replace(child_score=score, child_valid=valid)
        child = jax.tree.map(lambda new, old: jnp.where(ok, new, old), child,
                             node.replace(child_valid=jnp.zeros_like(valid)))
        value = jnp.max(jnp.where(valid, score, 0.0))
        out = mctx.RecurrentFnOutput(
            reward=reward, discount=jnp.where(ok & jnp.any(valid), discount, 0.0),
            prior_logits=jnp.where(valid, score / temperature, _NEG), value=value)
        return out, child

    def recurrent_fn(ctx, rng, action, node):
        del rng
        return jax.vmap(expand, in_axes=(None, 0, 0))(ctx, action, node)

    def act(key, memory, obs, state, dyn):
        n = obs.mask.shape[0]
        c = state.candidates
        hears = comms.contacts(state.position, dyn.radio_range)
        slot_kept = jnp.repeat(jnp.any(c.valid.reshape(n, -1, geometry.N_HEADINGS), axis=-1),
                               geometry.N_HEADINGS, axis=-1)
        keys = jax.random.split(key, n)

        def choose(carry, i):
            peer_pose, peer_chosen = carry
            utility = jax.tree.map(lambda x: x[0 if shared else i], state.utility_gp)
            ctx = Context(utility=utility, occupancy=state.occupancy[i],
                          offset=c.position[i] - state.position[i], heading=c.heading[i],
                          slot_kept=slot_kept[i], peer_pose=peer_pose,
                          peer_valid=peer_chosen & hears[i], turn_cost=dyn.turn_cost)
            mask = obs.mask[i]
            poses = geometry.pose(c.position[i], c.heading[i])
            path = jnp.zeros((max_depth, 4), jnp.float32)
            path_valid = jnp.zeros((max_depth,), bool)
            key_jitter, key_search = jax.random.split(keys[i])
            score = scores(ctx, poses, path, path_valid, gp_cfg, kappa, novelty)
            score += 1e-4 * jax.random.uniform(key_jitter, score.shape)
            root_node = Node(position=state.position[i], heading=state.heading[i],
                             budget=state.budget_left[i], path=path, path_valid=path_valid,
                             depth=jnp.zeros((), jnp.int32), child_score=score,
                             child_valid=mask)
            root = mctx.RootFnOutput(
                prior_logits=jnp.where(mask, score / temperature, _NEG)[None],
                value=jnp.max(jnp.where(mask, score, 0.0))[None],
                embedding=jax.tree.map(lambda x: x[None], root_node))
            invalid = ~mask & jnp.any(mask)  # all-infeasible: let mctx pick anything
            out = mctx.gumbel_muzero_policy(
                ctx, key_search, root, recurrent_fn, simulations,
                invalid_actions=invalid[None], max_depth=max_depth,
                max_num_considered_actions=min(considered, mask.shape[0]),
                gumbel_scale=gumbel_scale)
            a = out.action[0]
            a = jnp.where(mask[a], a, masked_argmax(score, mask))
            peer_pose = peer_pose.at[i].set(poses[a])
            peer_chosen = peer_chosen.at[i].set(jnp.any(mask))
            return (peer_pose, peer_chosen), a

        init = (jnp.zeros((n, 4), jnp.float32), jnp.zeros((n,), bool))
        _, actions = jax.lax.scan(choose, init, jnp.arange(n))
        return memory, actions

    return Planner(name, no_memory, act)
