"""NumPy mirror of `jaxmripp.learn.policy.ActorCritic`'s forward pass, for onboard inference.

Weights come from `jaxmripp.learn.policy.flatten_params` ("/"-joined module paths -> arrays);
the architecture description from `jaxmripp.learn.policy.runtime_config`. The functions below
follow the Flax code line for line (same names, same masking floor, same two-pass
LayerNorm), so both agree to float32 rounding. This module must import nothing but NumPy.

Shapes (one robot, unbatched): memory (W,), features (L, F), mask (L,), robot_state (S,),
global_state (N * S + 2,) -> new_memory (W,), logits (L,), value ().
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from jaxmripp.spec.layout import FEATURES, input_keep

LOGIT_CLIP = 10.0  # jaxmripp.learn.policy.LOGIT_CLIP
LAYER_NORM_EPS = 1e-6  # flax.linen.LayerNorm default
_FLOOR = np.finfo(np.float32).min  # jaxmripp.learn.policy.masked_logits


def _masked(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, x, _FLOOR).astype(np.float32)


def _softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # no overflow warnings for large |x|


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def _required_names(layers: int, central_critic: bool) -> list[str]:
    """Every weight name the forward pass reads (see jaxmripp.learn.policy's module doc)."""
    dense = lambda n: [f"{n}/kernel", f"{n}/bias"]  # noqa: E731
    norm = lambda n: [f"{n}/scale", f"{n}/bias"]  # noqa: E731

    def block(n):
        projections = ("query", "key", "value", "out")
        attention = [x for p in projections for x in dense(f"{n}/attention/{p}")]
        ff = dense(f"{n}/ff/hidden") + dense(f"{n}/ff/out")
        return norm(f"{n}/norm_attention") + attention + norm(f"{n}/norm_ff") + ff

    names = dense("embed") + norm("encoder_norm") + dense("state_embed") + dense("query")
    names += [x for i in range(layers) for x in block(f"encoder_{i}")] + block("decoder")
    names += [f"memory/{g}/kernel" for g in ("ir", "iz", "in", "hr", "hz", "hn")]
    names += [f"memory/{g}/bias" for g in ("ir", "iz", "in", "hn")]
    names += dense("pointer_query") + dense("pointer_key")
    names += dense("value_hidden") + dense("value_out")
    if central_critic:
        names += dense("global_embed")
    return names


class NumpyPolicy:
    """The trained actor-critic as plain NumPy; one robot's observation per call."""

    def __init__(self, weights: Mapping[str, np.ndarray], config: Mapping):
        self.width = int(config["width"])
        self.heads = int(config["heads"])
        self.layers = int(config["layers"])
        self.ff_mult = int(config["ff_mult"])
        self.central_critic = bool(config.get("central_critic", False))
        if config.get("view_prior", False):  # exported before the prior was removed
            raise ValueError("view_prior: a policy with the next-best-view prior, a removed "
                             "setting; allowed: one trained without it")
        if self.width % self.heads:
            raise ValueError(f"width {self.width} is not a multiple of heads {self.heads}")
        missing = [n for n in _required_names(self.layers, self.central_critic)
                   if n not in weights]
        if missing:
            raise KeyError(f"weights lack {len(missing)} arrays, e.g. {missing[:4]}")
        self.w = {name: np.asarray(value, np.float32) for name, value in weights.items()}
        self.n_features = self.w["embed/kernel"].shape[0]
        self.input_keep = input_keep(*(bool(config.get(f"{group}_features", True))
                                       for group in ("comm", "view", "intent")),
                                     ahead=self.n_features > len(FEATURES))

    def initial_memory(self) -> np.ndarray:
        return np.zeros(self.width, np.float32)

    def __call__(self, memory, features, mask, robot_state, global_state=None):
        """-> (new_memory (W,), logits (L,) with infeasible at finfo.min, value float32).

        With a central critic the value needs `global_state`; without one it is NaN (the
        critic only matters in training; the actor never reads global_state).
        """
        memory = np.asarray(memory, np.float32)
        features = np.asarray(features, np.float32)
        mask = np.asarray(mask, bool)
        robot_state = np.asarray(robot_state, np.float32)
        if features.ndim != 2 or features.shape[1] != self.n_features:
            raise ValueError(f"features: expected (L, {self.n_features}), got {features.shape}")
        if mask.shape != features.shape[:1] or memory.shape != (self.width,):
            raise ValueError(f"mask {mask.shape} / memory {memory.shape} do not match "
                             f"features {features.shape} / width {self.width}")

        features = np.where(mask[:, None], features, 0.0).astype(np.float32)
        if not self.input_keep.all():  # ablation: dropped input groups are not inputs
            features = features * self.input_keep
        encoded = self._dense("embed", features)
        for i in range(self.layers):
            encoded = self._block(f"encoder_{i}", encoded, None, mask)
        encoded = self._layer_norm("encoder_norm", encoded)

        state = self._dense("state_embed", robot_state)
        new_memory = self._gru("memory", memory, state)
        query = self._dense("query", np.concatenate([state, new_memory]))
        decoded = self._block("decoder", query[None], encoded, mask)[0]

        pointer_query = self._dense("pointer_query", decoded)
        pointer_keys = self._dense("pointer_key", encoded)
        logits = LOGIT_CLIP * np.tanh(pointer_keys @ pointer_query / math.sqrt(self.width))
        logits = _masked(logits, mask)

        if self.central_critic:
            if global_state is None:
                return new_memory, logits, np.float32(np.nan)
            world = _relu(self._dense("global_embed", np.asarray(global_state, np.float32)))
            critic_input = np.concatenate([world, robot_state])
        else:
            critic_input = decoded
        hidden = _relu(self._dense("value_hidden", critic_input))
        value = self._dense("value_out", hidden)[0]
        return new_memory.astype(np.float32), logits, np.float32(value)

    def act(self, memory, features, mask, robot_state) -> tuple[np.ndarray, int]:
        """Deployment rule: the most probable candidate -> (new_memory, index).

        If no candidate is feasible the index is meaningless (0); check `mask.any()`.
        """
        new_memory, logits, _ = self(memory, features, mask, robot_state)
        return new_memory, int(np.argmax(logits))

    # Layers, in jaxmripp.learn.policy's naming.

    def _dense(self, name, x, bias=True):
        y = x @ self.w[f"{name}/kernel"]
        return y + self.w[f"{name}/bias"] if bias else y

    def _layer_norm(self, name, x):
        mean = x.mean(axis=-1, keepdims=True)
        var = np.square(x - mean).mean(axis=-1, keepdims=True)
        y = (x - mean) / np.sqrt(var + LAYER_NORM_EPS)
        return y * self.w[f"{name}/scale"] + self.w[f"{name}/bias"]

    def _attention(self, name, queries, context, context_mask):
        """(Q, W), (K, W), (K,) -> (Q, W), multi-head, keys masked."""
        head_dim = self.width // self.heads
        split = lambda x: x.reshape(x.shape[:-1] + (self.heads, head_dim))  # noqa: E731
        q = split(self._dense(f"{name}/query", queries))
        k = split(self._dense(f"{name}/key", context))
        v = split(self._dense(f"{name}/value", context))
        # Batched matmuls over heads (np.einsum without optimize is several times slower):
        # scores[h] = q[:, h] k[:, h]^T, out[:, h] = weights[h] v[:, h].
        q, k, v = (x.transpose(1, 0, 2) for x in (q, k, v))  # (H, Q|K, D)
        scores = (q @ k.transpose(0, 2, 1)) / np.float32(np.sqrt(head_dim))  # (H, Q, K)
        weights = _softmax(_masked(scores, context_mask[None, None, :]))
        out = (weights @ v).transpose(1, 0, 2).reshape(queries.shape)
        return self._dense(f"{name}/out", out)

    def _block(self, name, x, context, context_mask):
        h = self._layer_norm(f"{name}/norm_attention", x)
        context = h if context is None else context
        x = x + self._attention(f"{name}/attention", h, context, context_mask)
        h = self._layer_norm(f"{name}/norm_ff", x)
        h = _relu(self._dense(f"{name}/ff/hidden", h))
        return x + self._dense(f"{name}/ff/out", h)

    def _gru(self, name, h, x):
        """flax.linen.GRUCell: biases on the input side, plus one on the h -> n path."""
        r = _sigmoid(self._dense(f"{name}/ir", x) + self._dense(f"{name}/hr", h, bias=False))
        z = _sigmoid(self._dense(f"{name}/iz", x) + self._dense(f"{name}/hz", h, bias=False))
        n = np.tanh(self._dense(f"{name}/in", x) + r * self._dense(f"{name}/hn", h))
        return (1.0 - z) * n + z * h
