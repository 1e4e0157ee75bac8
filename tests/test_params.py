"""Static EnvParams (shapes, code paths) apart from traced DynamicParams (values)."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config
from jaxmripp.sim.params import DynamicParams, EnvParams, stack

ROOT = Path(__file__).resolve().parents[1]
CFG = config.load(ROOT / "tests" / "smoke.yaml", [
    "radio.range=.inf", "radio.collision_distance=0.07", "robots.pad_spacing=0.08",
    "robots.budget=[3.0, 5.0]",
    "robots.turn_cost=0.03", "robots.start=[0.1, 0.2, 0.3]", "reward.alpha=7.5",
    "reward.beta=0.25", "reward.gamma=1.5",
    "reward.utility_norm=10.0"])


def test_dynamic_values_come_from_the_config_as_float32():
    d = DynamicParams.from_config(CFG)
    expected = dict(radio_range=math.inf, collision_distance=0.07, budget=[3.0, 5.0],
                    turn_cost=0.03, start=[0.1, 0.2, 0.3], pad_spacing=0.08, alpha=7.5,
                    beta=0.25, gamma=1.5, utility_norm=10.0)
    for name, value in expected.items():
        leaf = getattr(d, name)
        assert leaf.dtype == jnp.float32 and not leaf.weak_type, name
        np.testing.assert_array_equal(leaf, np.float32(value), name)
    assert d.budget.shape == (2,) and d.start.shape == (3,) and d.alpha.shape == ()


def test_static_params_hold_no_dynamic_value():
    p = EnvParams.from_config(CFG)
    hash(p)  # a jit static argument
    assert (p.n_robots, p.robots.start_heading, p.radio.relay) == (2, 1, False)
    assert p.max_steps == CFG.episode.max_steps and p.size == CFG.world.size
    for path in ("radio.range", "radio.collision_distance", "robots.budget",
                 "robots.turn_cost", "robots.start", "robots.pad_spacing", "reward"):
        obj = p
        with pytest.raises(AttributeError):
            for part in path.split("."):
                obj = getattr(obj, part)
    # Two configs that differ only in dynamic values share their static params.
    other = config.load(ROOT / "tests" / "smoke.yaml", ["radio.range=0.2"])
    assert EnvParams.from_config(other) == p


def test_with_values_and_stack_keep_one_trace():
    d = DynamicParams.from_config(CFG)
    traces = []

    @jax.jit
    def f(d):
        traces.append(1)
        return d.radio_range + d.budget.sum()

    f(d)
    f(d.with_values(radio_range=0.1, budget=(1.0, 2.0)))
    f(d.with_budget(4.0))
    assert len(traces) == 1
    np.testing.assert_array_equal(d.with_budget(4.0).budget, [4.0, 4.0])
    stacked = stack([d, d.with_values(radio_range=0.1)])
    assert stacked.radio_range.shape == (2,) and stacked.start.shape == (2, 3)
    np.testing.assert_array_equal(jax.vmap(f)(stacked), [math.inf, np.float32(0.1) + 8.0])
