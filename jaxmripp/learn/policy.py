"""Attention actor-critic over one robot's candidate set (CAtNIPP-style).

The module sees ONE robot's observation; callers `jax.vmap` `apply` over robots and
environments. Notation: L candidates, F features, S robot-state size, W width,
H heads, D = W // H.

    memory (W,), obs.features (L, F), obs.mask (L,), obs.robot_state (S,)
        -> new_memory (W,), logits (L,) with infeasible entries at finfo.min, value ()

Forward pass (parameter names in quotes; `flatten_params` joins them with "/"):

    E = "embed"(features)                                    (L, W)
    E = "encoder_i"(E) for i < layers                        pre-LN self-attention + FF
    E = "encoder_norm"(E)
    s = "state_embed"(robot_state)                           (W,)
    new_memory = "memory"(memory, s)                         GRU over the path so far
    d = "query"([s, new_memory])                             (W,)
    d = "decoder"(d, E)                                      pre-LN cross-attention + FF
    logits = CLIP * tanh("pointer_query"(d) . "pointer_key"(E) / sqrt(W)), masked
    value = "value_out"(relu("value_hidden"(d)))             IPPO
          = "value_out"(relu("value_hidden"([relu("global_embed"(global_state)),
                                             robot_state])))  central critic (MAPPO)
    q = "q_out"(relu("q_hidden"([E, d])))                    (L,) action values, sown as
                                      "intermediates"/"action_values" (training only)

Each block ("encoder_i", "decoder") holds "norm_attention", "attention" ("query",
"key", "value", "out"), "norm_ff" and "ff" ("hidden", "out"). Attention is written out
with Dense + einsum (not nn.MultiHeadDotProductAttention) so that the NumPy runtime in
`jaxmripp.runtime.policy` can mirror it line for line.
"""

from __future__ import annotations

import functools
import math

import chex
import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from jaxmripp.config import PolicyConfig
from jaxmripp.sim.observation import Observation
from jaxmripp.spec import layout

# Pointer-network logit clipping (Bello et al. 2017): bounded logits keep the policy
# from collapsing early and bound the PPO ratio's sensitivity to the pointer weights.
LOGIT_CLIP = 10.0
# The pointer query starts at 0.01 x the default (LeCun) weight scale, so the initial
# policy is near uniform over feasible candidates (the usual PPO last-layer choice).
POINTER_INIT_SCALE = 0.01


def masked_logits(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Infeasible entries -> the most negative finite value (not -inf).

    A finite floor keeps an all-infeasible row well defined: softmax becomes uniform and
    log-probabilities and entropy stay finite, so padded / finished robots never NaN the
    loss. With at least one feasible entry the infeasible ones get probability exactly 0.
    """
    return jnp.where(mask, logits, jnp.finfo(logits.dtype).min)


def distribution(logits: jax.Array, mask: jax.Array) -> distrax.Categorical:
    """(..., L) logits and feasibility mask -> categorical over the candidates."""
    return distrax.Categorical(logits=masked_logits(logits, mask))


def softmax(x: jax.Array) -> jax.Array:
    """Softmax over the last axis, normalised by multiplying with the reciprocal sum.

    `jax.nn.softmax` divides by the broadcast sum, and XLA rewrites that division into a
    multiplication in some programs and not in others (it did for a 1-device program and
    not for its 2-device partition), which changes the last bit; written as a product it
    is the same arithmetic in every program."""
    exp = jnp.exp(x - jax.lax.stop_gradient(x.max(axis=-1, keepdims=True)))
    return exp * (1.0 / exp.sum(axis=-1, keepdims=True))


def initial_memory(config: PolicyConfig) -> jax.Array:
    """The GRU memory at the start of an episode: (W,) zeros."""
    return jnp.zeros((config.width,), jnp.float32)


class Attention(nn.Module):
    """Multi-head scaled dot-product attention with a key padding mask.

    queries (..., Q, W), context (..., K, W), context_mask (..., K) -> (..., Q, W).
    """

    width: int
    heads: int

    @nn.compact
    def __call__(self, queries, context, context_mask):
        head_dim = self.width // self.heads

        def heads_first(x):  # (..., T, W) -> (..., H, T, D)
            return jnp.swapaxes(x.reshape(x.shape[:-1] + (self.heads, head_dim)), -3, -2)

        # Head-major operands: XLA:CPU's batched matmuls then run on contiguous blocks
        # (contracting over a strided head axis made the policy forward 2.2x slower).
        q = heads_first(nn.Dense(self.width, name="query")(queries))  # (..., H, Q, D)
        k = heads_first(nn.Dense(self.width, name="key")(context))  # (..., H, K, D)
        v = heads_first(nn.Dense(self.width, name="value")(context))  # (..., H, K, D)
        scores = jnp.einsum("...hqd,...hkd->...hqk", q, k) / np.sqrt(head_dim)
        # Masked keys get the finite floor rather than -inf: if every key is masked the
        # softmax is uniform (finite) instead of 0/0.
        scores = masked_logits(scores, context_mask[..., None, None, :])
        weights = softmax(scores)  # (..., H, Q, K)
        out = jnp.swapaxes(weights @ v, -3, -2)  # (..., Q, H, D)
        return nn.Dense(self.width, name="out")(out.reshape(queries.shape))


class FeedForward(nn.Module):
    """Position-wise MLP: (..., W) -> (..., W) through a ReLU layer of W * ff_mult."""

    width: int
    ff_mult: int

    @nn.compact
    def __call__(self, x):
        h = nn.relu(nn.Dense(self.width * self.ff_mult, name="hidden")(x))
        return nn.Dense(self.width, name="out")(h)


class Block(nn.Module):
    """Pre-LN transformer block: x + Attn(LN(x), context), then x + FF(LN(x)).

    x (..., Q, W). With `context` None it is self-attention over LN(x) (keys masked by
    `context_mask`, (..., Q)); otherwise x attends to context (..., K, W), which is
    expected to be normalised already. Pre-LN keeps the residual stream un-normalised,
    which trains stably without learning-rate warm-up.
    """

    config: PolicyConfig

    @nn.compact
    def __call__(self, x, context, context_mask):
        cfg = self.config
        # Exact two-pass variance: matches the NumPy runtime and is robust to large means.
        layer_norm = functools.partial(nn.LayerNorm, use_fast_variance=False)
        h = layer_norm(name="norm_attention")(x)
        context = h if context is None else context
        x = x + Attention(cfg.width, cfg.heads, name="attention")(h, context, context_mask)
        h = layer_norm(name="norm_ff")(x)
        return x + FeedForward(cfg.width, cfg.ff_mult, name="ff")(h)


class ActorCritic(nn.Module):
    """Actor (pointer over candidates) and critic for one robot; see the module doc."""

    config: PolicyConfig
    central_critic: bool = False  # MAPPO: value from global_state (+ own robot_state)
    # A value per candidate (ppo.search_value=learned, the search's learned values). Sown
    # rather than returned: callers that do not ask for it (the evaluation, the export)
    # see the actor-critic they always saw.
    action_values: bool = False

    @nn.compact
    def __call__(self, memory: jax.Array, obs: Observation):
        cfg = self.config
        width = cfg.width
        features = jnp.asarray(obs.features, jnp.float32)
        robot_state = jnp.asarray(obs.robot_state, jnp.float32)
        mask = jnp.asarray(obs.mask, bool)
        n_candidates = features.shape[0]
        chex.assert_rank([features, mask, robot_state], [2, 1, 1])
        chex.assert_shape(mask, (n_candidates,))
        chex.assert_shape(memory, (width,))

        # Infeasible candidates influence nothing (masked as keys and in the pointer), so
        # the env may pad them with anything; zeroing keeps non-finite padding out of the
        # 0 * value products of the attention.
        features = jnp.where(mask[:, None], features, 0.0)
        keep = input_keep(self.config)
        if not keep.all():  # ablation: the policy never sees the dropped input groups
            features = features * jnp.asarray(keep, features.dtype)

        # Encoder: candidates attend to each other (feasible ones only as keys).
        encoded = nn.Dense(width, name="embed")(features)  # (L, W)
        for i in range(cfg.layers):
            encoded = Block(cfg, name=f"encoder_{i}")(encoded, None, mask)
        encoded = nn.LayerNorm(use_fast_variance=False, name="encoder_norm")(encoded)

        # Query: current state and a recurrent summary of the path so far.
        state = nn.Dense(width, name="state_embed")(robot_state)  # (W,)
        new_memory, _ = nn.GRUCell(width, name="memory")(memory, state)
        query = nn.Dense(width, name="query")(jnp.concatenate([state, new_memory]))

        # Decoder: the query attends to the feasible candidates.
        decoded = Block(cfg, name="decoder")(query[None], encoded, mask)[0]  # (W,)

        # Pointer: one logit per candidate.
        pointer_query = nn.Dense(
            width,
            kernel_init=nn.initializers.variance_scaling(
                POINTER_INIT_SCALE**2, "fan_in", "truncated_normal"
            ),
            name="pointer_query",
        )(decoded)
        pointer_keys = nn.Dense(width, name="pointer_key")(encoded)  # (L, W)
        logits = LOGIT_CLIP * jnp.tanh(pointer_keys @ pointer_query / math.sqrt(width))
        logits = masked_logits(logits, mask)

        if self.central_critic:
            global_state = jnp.asarray(obs.global_state, jnp.float32)
            chex.assert_rank(global_state, 1)
            world = nn.relu(nn.Dense(width, name="global_embed")(global_state))
            critic_input = jnp.concatenate([world, robot_state])
        else:
            critic_input = decoded
        hidden = nn.relu(nn.Dense(width, name="value_hidden")(critic_input))
        value = nn.Dense(1, name="value_out")(hidden)[0]
        if self.action_values:
            pairs = jnp.concatenate([encoded, jnp.broadcast_to(decoded, encoded.shape)], -1)
            q = nn.Dense(1, name="q_out")(nn.relu(nn.Dense(width, name="q_hidden")(pairs)))
            self.sow("intermediates", "action_values", q[:, 0])

        chex.assert_shape([new_memory, logits, value], [(width,), (n_candidates,), ()])
        return new_memory, logits, value


def flatten_params(params) -> dict[str, np.ndarray]:
    """Flax params (with or without the outer "params" collection) -> {"a/b/kernel": array}.

    The names are the module paths documented at the top of this file, e.g.
    "encoder_0/attention/query/kernel" or "memory/hn/bias"; this is the export format
    read by `jaxmripp.runtime.NumpyPolicy`.
    """
    if set(params.keys()) == {"params"}:
        params = params["params"]
    flat = traverse_util.flatten_dict(params, sep="/")
    return {name: np.asarray(value, np.float32) for name, value in flat.items()}


def unflatten_params(flat: dict[str, np.ndarray]) -> dict:
    """The inverse of `flatten_params`: {"a/b/kernel": array} -> Flax params."""
    tree = traverse_util.unflatten_dict({tuple(k.split("/")): jnp.asarray(v)
                                         for k, v in flat.items()})
    return {"params": tree}


def runtime_config(config: PolicyConfig, central_critic: bool = False) -> dict:
    """The architecture description `NumpyPolicy` needs next to the weights."""
    return {
        "width": config.width,
        "heads": config.heads,
        "layers": config.layers,
        "ff_mult": config.ff_mult,
        "central_critic": central_critic,
        "comm_features": config.comm_features,
        "view_features": config.view_features,
        "intent_features": config.intent_features,
    }


def input_keep(config: PolicyConfig) -> np.ndarray:
    """(F,) 1/0 multipliers of the input columns (`jaxmripp.spec.layout.input_keep`)."""
    return layout.input_keep(config.comm_features, config.view_features, config.intent_features,
                             config.ahead_branches > 0, config.belief_features)
