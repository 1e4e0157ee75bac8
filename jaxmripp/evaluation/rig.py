"""Rapidly-exploring information gathering (RIG) with sequential allocation (the RIG baseline).

RIG (Hollinger & Sukhatme, 2014) grows a tree of feasible paths the way RRT does: sample a
point, take the nearest node, steer toward the point by at most a step and keep the new
node if its edge is feasible and its cost fits the budget. Every node carries the
information gathered along its path and the cost spent; the plan is the path to the most
informative node. Here robots plan one after another (index order), each seeing the poses
that robots before it and within radio range chose this step, re-plan at every step and
fly only the first edge. Simplifications, on purpose:

- Fixed-size tree. K = L + iterations preallocated nodes with a validity flag (like
  mctx's trees): node k < L is candidate k, node L + r is what round r added, or stays
  invalid when round r's extension was rejected. Static shapes let one compilation serve
  every environment of a vmapped evaluation.
- The first level is the env's L candidates, valid where the env's feasibility mask is:
  the action must be a candidate index, and the mask already holds the safety rules
  (collisions with peers, the flight rule, the budget) that the tree does not repeat.
- One extension per round, from the nearest open node only; no extension from the near
  set, no pruning of dominated nodes, no rewiring. Each of those compares a new node with
  a variable set of others; without them a round is one fixed-size update.
- Deeper edges: any direction (toward the sample), at most the candidate shell's outer
  radius, a heading drawn uniformly; feasible when inside the world, within the parent's
  budget (distance + turn cost) and when the line passes the flight rule on the robot's
  own map, as in the tree search. Peers' poses are not obstacles beyond the first level.
- Information: the tree search's model (`tree_search.scores`, a hallucinated update of
  the robot's utility GP), the reward of a pose given the poses on its path and the
  peers' choices: a path's reward is the sum of marginal gains, the form RIG's
  submodular objective takes along one path. Gains at depth d + 1 are weighted by
  discount^d, as in the tree search: the GP's prediction is least trustworthy far ahead.
- Sampling is uniform in the box that depth-cap edges can reach around the robot (clipped
  to the unit cube): samples beyond it would all pull on the few outermost open nodes
  (RRT's Voronoi bias). A fixed number of rounds (not anytime), so a decision costs the
  same in every environment.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.evaluation.baselines import no_memory, masked_argmax
from jaxmripp.evaluation.tree_search import Context, scores
from jaxmripp.sim import comms, geometry
from jaxmripp.sim.episode import Planner


@struct.dataclass
class Tree:
    """One robot's tree: K = L + iterations nodes, D = max depth."""

    position: jax.Array  # (K, 3)
    heading: jax.Array  # (K,) int32
    budget: jax.Array  # (K,) budget left at the node
    reward: jax.Array  # (K,) discounted information gathered along the path
    cost: jax.Array  # (K,) budget spent from the robot's position
    path: jax.Array  # (K, D, 4) poses from the first move down to the node
    path_valid: jax.Array  # (K, D) bool
    depth: jax.Array  # (K,) int32, 1 for the candidates
    root_action: jax.Array  # (K,) int32 the candidate the path starts with
    valid: jax.Array  # (K,) bool


def grow(key, origin, budget, heading, cand_position, cand_heading, cand_cost, mask, score, clear,
         turn_cost, reach: float, iterations: int, max_depth: int, discount: float = 0.9,
         rounds=None, depth_limit=None) -> Tree:
    """Grows one robot's tree from its candidates (L,) and the position (3,), budget and
    heading it has.

    score(poses (M, 4), path (D, 4), path_valid (D,)) -> (M,) the information of each pose
    given the path; clear(start (3,), end (3,)) -> () whether the line of flight passes
    the map. `rounds` <= iterations and `depth_limit` <= max_depth (default: equal) may be
    traced, so a grid search over them shares one compilation.
    """
    n_cand = cand_position.shape[0]
    rounds = iterations if rounds is None else rounds
    depth_limit = max_depth if depth_limit is None else depth_limit
    poses = geometry.pose(cand_position, cand_heading)
    # samples beyond what depth_limit edges can reach would only stretch the outermost nodes
    radius = reach * depth_limit
    path = jnp.zeros((n_cand, max_depth, 4), jnp.float32).at[:, 0].set(poses)
    path_valid = jnp.zeros((n_cand, max_depth), bool).at[:, 0].set(True)
    first = score(poses, jnp.zeros((max_depth, 4), jnp.float32), jnp.zeros((max_depth,), bool))

    def pad(x):
        return jnp.concatenate([x, jnp.zeros((iterations, *x.shape[1:]), x.dtype)])

    tree = jax.tree.map(pad, Tree(
        position=cand_position, heading=cand_heading.astype(jnp.int32),
        budget=budget - cand_cost, reward=first, cost=cand_cost, path=path,
        path_valid=path_valid, depth=jnp.ones((n_cand,), jnp.int32),
        root_action=jnp.arange(n_cand, dtype=jnp.int32), valid=mask))

    def extend(r, tree: Tree) -> Tree:
        key_point, key_heading = jax.random.split(jax.random.fold_in(key, r))
        target = jnp.clip(origin + radius * jax.random.uniform(key_point, (3,), minval=-1.0),
                          0.0, 1.0)
        open_ = tree.valid & (tree.depth < depth_limit) & (tree.budget > 0)
        gap2 = jnp.sum(jnp.square(tree.position - target), axis=-1)
        parent = jnp.argmin(jnp.where(open_, gap2, jnp.inf))
        start = tree.position[parent]
        length = jnp.linalg.norm(target - start)
        step = jnp.minimum(length, reach)
        end = start + (target - start) * (step / jnp.maximum(length, 1e-9))
        h = jax.random.randint(key_heading, (), 0, geometry.N_HEADINGS, jnp.int32)
        turned = h != tree.heading[parent]
        cost = step + turn_cost * turned
        ok = (open_[parent] & (r < rounds) & geometry.inside_world(end)
              & (cost <= tree.budget[parent]) & ((step > 0) | turned) & clear(start, end))
        depth = tree.depth[parent]
        pose = geometry.pose(end, h)
        gain = score(pose[None], tree.path[parent], tree.path_valid[parent])[0]
        slot = jnp.minimum(depth, max_depth - 1)  # depth < depth_limit <= max_depth when ok
        node = Tree(position=end, heading=h, budget=tree.budget[parent] - cost,
                    reward=tree.reward[parent] + jnp.power(discount, depth) * gain,
                    cost=tree.cost[parent] + cost, path=tree.path[parent].at[slot].set(pose),
                    path_valid=tree.path_valid[parent].at[slot].set(True), depth=depth + 1,
                    root_action=tree.root_action[parent], valid=ok)
        return jax.tree.map(lambda a, v: a.at[n_cand + r].set(v), tree, node)

    return jax.lax.fori_loop(0, iterations, extend, tree)


def best_action(key, tree: Tree, mask) -> jax.Array:
    """The candidate that starts the path to the most informative node (ties: a tiny random
    jitter); with no feasible candidate, what `masked_argmax` gives."""
    reward = tree.reward + 1e-4 * jax.random.uniform(key, tree.reward.shape)
    best = tree.root_action[masked_argmax(reward, tree.valid)]
    return jnp.where(jnp.any(mask), best, masked_argmax(reward[:mask.shape[0]], mask))


def robot_tree(key, params, obs, state, dyn, i, peer_pose, peer_valid, iterations: int = 64,
               max_depth: int = 2, kappa: float = 0.3, discount: float = 0.9,
               novelty: bool = True, rounds=None, depth_limit=None) -> Tree:
    """Robot i's tree in the env's state, given the poses (N, 4) that the peers it hears
    (peer_valid (N,)) chose; arguments as in `rig_planner`."""
    c, size = state.candidates, params.size
    reach = params.candidates.shell[1]
    utility = jax.tree.map(lambda x: x[0 if params.gp.shared_utility else i], state.utility_gp)
    occupancy = state.occupancy[i]
    # scores reads the GP and the peers; the other fields as the tree search has them
    ctx = Context(utility=utility, occupancy=occupancy, offset=c.position[i] - state.position[i],
                  heading=c.heading[i], slot_kept=c.valid[i], peer_pose=peer_pose,
                  peer_valid=peer_valid, turn_cost=dyn.turn_cost)
    line_ok = geometry.line_rule(params.safety.flight)

    def score(poses, path, path_valid):
        return scores(ctx, poses, path, path_valid, params.gp, kappa, novelty)

    def clear(start, end):
        return line_ok(start, end[None], occupancy, size, reach)[0]

    return grow(key, state.position[i], state.budget_left[i], state.heading[i], c.position[i], c.heading[i],
                c.cost[i], obs.mask[i], score, clear, dyn.turn_cost, reach, iterations,
                max_depth, discount, rounds, depth_limit)


def rig_planner(params, iterations: int = 64, max_depth: int = 2, kappa: float = 0.3,
                discount: float = 0.9, novelty: bool = True, name: str = "rig",
                rounds=None, depth_limit=None) -> Planner:
    """The RIG baseline (module docstring); `params` is the env's static EnvParams, the
    turn cost and radio range come traced from `act`'s `dyn`. `rounds` / `depth_limit`:
    see `grow`."""

    def act(key, memory, obs, state, dyn):
        n = obs.mask.shape[0]
        c = state.candidates
        hears = comms.contacts(state.position, dyn.radio_range)
        keys = jax.random.split(key, n)

        def choose(carry, i):
            peer_pose, peer_chosen = carry
            key_tree, key_jitter = jax.random.split(keys[i])
            tree = robot_tree(key_tree, params, obs, state, dyn, i, peer_pose,
                              peer_chosen & hears[i], iterations, max_depth, kappa, discount,
                              novelty, rounds, depth_limit)
            a = best_action(key_jitter, tree, obs.mask[i])
            peer_pose = peer_pose.at[i].set(geometry.pose(c.position[i, a], c.heading[i, a]))
            peer_chosen = peer_chosen.at[i].set(jnp.any(obs.mask[i]))
            return (peer_pose, peer_chosen), a

        init = (jnp.zeros((n, 4), jnp.float32), jnp.zeros((n,), bool))
        _, actions = jax.lax.scan(choose, init, jnp.arange(n))
        return memory, actions

    return Planner(name, no_memory, act)
