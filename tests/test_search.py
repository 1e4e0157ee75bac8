"""Search-based policy improvement (jaxmripp.learn.search); its part of the PPO loss is
checked beside kickstarting's in tests/test_train.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config as cfgmod
from jaxmripp.config import ConfigError
from jaxmripp.learn import search


# Compiled once per shape: op by op the search takes seconds.
_improved = jax.jit(search.improved_policy, static_argnums=4)


def _draw(rows, candidates, seed):
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    logits = jax.random.normal(keys[0], (rows, candidates))
    mask = jax.random.bernoulli(keys[1], 0.5, (rows, candidates)).at[:, 0].set(True)
    values = jax.random.uniform(keys[2], (rows, candidates))
    return logits, mask, values


def test_every_candidate_searched_moves_the_logits_by_a_rising_line_in_its_value():
    """With every feasible candidate considered (fewer than the simulations), Gumbel
    MuZero's improved policy is softmax(logits + s (value - min) / (max - min)) with one
    s > 0 per row: log pi' - logits lies on a rising line in the value, and infeasible
    candidates get weight 0."""
    logits, mask, values = _draw(6, 10, seed=0)
    weights = np.asarray(_improved(jax.random.PRNGKey(1), logits, mask, values, 16))
    m = np.asarray(mask)
    assert np.all(weights[~m] == 0)
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-5)
    for row in range(len(m)):
        if m[row].sum() < 3:
            continue
        q = np.asarray(values[row], np.float64)[m[row]]
        shift = np.log(weights[row][m[row]].astype(np.float64)) - np.asarray(logits[row])[m[row]]
        slope, intercept = np.polyfit(q, shift, 1)
        np.testing.assert_allclose(shift, slope * q + intercept, atol=1e-3)
        assert slope > 1.0


def test_equal_values_leave_the_policy_as_it_is_and_a_dominant_one_takes_the_weight():
    logits, mask, values = _draw(6, 10, seed=2)
    same = _improved(jax.random.PRNGKey(3), logits, mask,
                                  jnp.full(values.shape, 0.4), 16)
    prior = jax.nn.softmax(jnp.where(mask, logits, -jnp.inf))
    np.testing.assert_allclose(np.asarray(same), np.asarray(prior), atol=1e-5)
    # Equal logits and one value far above the rest (2 against [0, 1)): that candidate
    # gets most of the weight.
    best = np.asarray(jax.random.categorical(jax.random.PRNGKey(5), jnp.where(mask, 0.0, -jnp.inf)))
    values = values.at[jnp.arange(len(best)), best].set(2.0)
    flat = _improved(jax.random.PRNGKey(3), jnp.zeros_like(logits), mask, values, 16)
    assert np.all(np.asarray(flat).argmax(-1) == best)
    assert np.all(np.take_along_axis(np.asarray(flat), best[:, None], -1) > 0.5)


def test_the_root_value_completes_the_candidates_not_visited():
    """4 simulations over 10 feasible candidates visit 4 of them; the other 6 take a mix of
    the root's value and the visited values. A root value above every candidate's lifts
    the unvisited ones above every visited one (relative to the prior), one below sinks
    them; without a root value the search uses the policy's mean of the values."""
    logits, _, values = _draw(6, 10, seed=6)
    mask = jnp.ones(values.shape, bool)
    key = jax.random.PRNGKey(7)
    shift = lambda w: np.log(np.asarray(w, np.float64)) - np.asarray(  # noqa: E731
        jax.nn.log_softmax(logits), np.float64)
    high = shift(_improved(key, logits, mask, values, 4, jnp.full(6, 100.0)))
    low = shift(_improved(key, logits, mask, values, 4, jnp.full(6, -100.0)))
    mean = _improved(key, logits, mask, values, 4, None)
    # The same key draws the same Gumbel noise, so the same 4 candidates are visited: the
    # 4 lowest shifts under the high root value, the 4 highest under the low one.
    for h, lo in zip(high, low):
        visited = np.argsort(h)[:4]
        unvisited = np.setdiff1d(np.arange(10), visited)
        assert set(visited) == set(np.argsort(lo)[-4:])
        assert h[unvisited].min() > h[visited].max()
        assert lo[unvisited].max() < lo[visited].min()
    policy_mean = (jax.nn.softmax(logits) * values).sum(-1)
    np.testing.assert_allclose(np.asarray(mean),
                               np.asarray(_improved(key, logits, mask, values, 4, policy_mean)),
                               atol=1e-6)


def test_the_search_needs_the_lookahead_input_or_learned_values():
    with pytest.raises(ConfigError, match="ppo.search_coef"):
        cfgmod.load("tests/smoke.yaml", ["ppo.search_coef=1"])
    learned = cfgmod.load("tests/smoke.yaml", ["ppo.search_coef=1", "ppo.search_value=learned"])
    assert learned.policy.ahead_branches == 0 and learned.ppo.search_value == "learned"
    with pytest.raises(ConfigError, match="ppo.search_value"):
        cfgmod.load("tests/smoke.yaml", ["ppo.search_value=critic"])
    with pytest.raises(ConfigError, match="ppo.search_simulations"):
        cfgmod.load("tests/smoke.yaml", ["ppo.search_simulations=1"])
