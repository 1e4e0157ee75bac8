"""Search-based policy improvement (`ppo.search_coef`): a Gumbel MuZero search (`mctx`)
over each robot's candidates whose improved policy the loss pulls the policy toward.

The model is the robot's own: a candidate's value is its lookahead input `ahead_rate`
(`jaxmripp.spec.layout`: the two-flight value of the view gain on the robot's map, each
facade weighed by its target belief with `policy.ahead_rated`), reached in one step
(depth 1, discount 0: the value already counts the second flight). The search starts from
the policy's own logits; its improved policy (`PolicyOutput.action_weights`) is
softmax(logits + sigma(completed values)), which keeps what the policy learned from its
returns and moves it toward what the model rates higher. Unlike a fixed teacher's choice,
the target moves with the policy, so the policy can leave the planner it started from.
The root's value, which completes the values of candidates the search did not visit, is
the model's value under the policy (its probabilities times `ahead_rate`), so values and
completions share one scale.

With `ppo.search_value=learned` the values are the network's own instead: an action-value
head (`ActorCritic.action_values`) trained toward the return that followed each action
taken, and the critic's value of the state at the root, both on the scale of the returns.
Depth 1 with a learned Q(s, a) is the learned value at the leaf each candidate leads to.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mctx

from jaxmripp.config import Config
from jaxmripp.learn.policy import masked_logits, softmax
from jaxmripp.sim.observation import Observation
from jaxmripp.spec import layout


def improved_policy(key, logits, mask, values, simulations: int, root_value=None):
    """(B, L) logits, feasibility mask and candidate values -> (B, L) float32 improved
    policy, 0 on infeasible candidates (a row with none feasible gives finite weights,
    which the loss leaves out with the rest of that robot's sample). `root_value` (B,)
    completes the candidates the search did not visit; None: the policy-weighted mean of
    the candidates' values."""
    invalid = ~mask & jnp.any(mask, axis=-1, keepdims=True)  # none feasible: any
    candidate_value = jnp.where(mask, values, 0.0)
    if root_value is None:
        root_value = (softmax(masked_logits(logits, mask)) * candidate_value).sum(-1)
    root = mctx.RootFnOutput(prior_logits=logits, value=root_value,
                             embedding=candidate_value)

    def recurrent_fn(_, __, action, embedding):
        batch = jnp.arange(action.shape[0])
        out = mctx.RecurrentFnOutput(
            reward=embedding[batch, action], discount=jnp.zeros_like(action, jnp.float32),
            prior_logits=jnp.zeros_like(embedding), value=jnp.zeros_like(action, jnp.float32))
        return out, embedding

    out = mctx.gumbel_muzero_policy(
        (), key, root, recurrent_fn, simulations, invalid_actions=invalid, max_depth=1,
        max_num_considered_actions=min(simulations, logits.shape[-1]))
    return jax.lax.stop_gradient(out.action_weights)


def search_targets(key, cfg: Config, obs: Observation, logits, value, action_values):
    """The improved policy (E, N, L) of every robot at a rollout step: obs (E, N, ...), the
    policy's masked logits (E, N, L), the critic's value (E, N) and the network's action
    values (E, N, L), or None to value candidates by the model (`ppo.search_value`)."""
    rows = lambda x: x.reshape(-1, x.shape[-1])  # noqa: E731
    if action_values is None:  # the model: the lookahead input, the policy's mean at the root
        ahead = layout.features(ahead=True, belief=cfg.policy.belief_features).index(
            "ahead_rate")
        candidates, root = obs.features[..., ahead], None
    else:  # learned: the action values, the critic's value at the root
        candidates, root = action_values, value.reshape(-1)
    return improved_policy(key, rows(logits), rows(obs.mask), rows(candidates),
                           cfg.ppo.search_simulations, root).reshape(logits.shape)
