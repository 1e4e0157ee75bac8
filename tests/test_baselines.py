"""Non-learning planners: coordination rules on hand-made states, and their ranking on
small worlds (the tree search beats random, the ground-truth oracle beats greedy)."""

import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import baselines, config, evaluate, geometry, world
from jaxmripp.config import WorldConfig
from jaxmripp.observation import FEATURES, Observation

ROOT = Path(__file__).resolve().parents[1]
FAST = {"xla_backend_optimization_level": 0}


def _observation(utility_mean, mask):
    """Observation whose only non-zero feature is the utility mean (n, L)."""
    utility_mean = jnp.asarray(utility_mean, jnp.float32)
    features = jnp.zeros((*utility_mean.shape, len(FEATURES)), jnp.float32)
    features = features.at[..., FEATURES.index("utility_mean")].set(utility_mean)
    n = utility_mean.shape[0]
    return Observation(features=features, mask=jnp.asarray(mask), robot_state=jnp.zeros((n, 9)),
                       global_state=jnp.zeros((n, 9 * n + 2)))


def _params(radio_range=np.inf, collision_distance=0.05):
    cfg = config.load(ROOT / "configs" / "smoke.yaml")
    params = evaluate.eval_params(cfg, 2.0, radio_range=radio_range)
    radio = params.radio.__class__(range=radio_range, collision_distance=collision_distance)
    return params.__class__(**{**params.__dict__, "radio": radio})


def _candidates(positions):
    """Two robots at the origin with the same candidate positions, heading 0."""
    positions = jnp.asarray(positions, jnp.float32)
    both = jnp.broadcast_to(positions, (2, *positions.shape))
    return types.SimpleNamespace(position=both,
                                 heading=jnp.zeros(both.shape[:2], jnp.int32))


@pytest.mark.parametrize("radio_range, expect_second", [(np.inf, 2), (0.0, 0)])
def test_coordinated_skips_what_a_heard_peer_chose(radio_range, expect_second):
    # candidate 1 is within d_c of candidate 0 (the best); candidate 2 is far from both
    positions = [[0.5, 0.5, 0.5], [0.52, 0.5, 0.5], [0.1, 0.9, 0.5]]
    utility = [[1.0, 0.95, 0.5]] * 2
    state = types.SimpleNamespace(candidates=_candidates(positions),
                                  position=jnp.full((2, 3), 0.5, jnp.float32))
    obs = _observation(utility, jnp.ones((2, 3), bool))
    planner = baselines.coordinated_planner(_params(radio_range), kappa=0.0, lam=0.0, mu=1.0)
    _, actions = jax.jit(planner.act)(jax.random.PRNGKey(0), planner.init(2), obs, state)
    assert actions.tolist() == [0, expect_second]  # out of radio range: no coordination


def test_coordinated_falls_back_when_everything_is_crowded():
    positions = [[0.5, 0.5, 0.5], [0.52, 0.5, 0.5], [0.1, 0.9, 0.5]]
    state = types.SimpleNamespace(candidates=_candidates(positions),
                                  position=jnp.full((2, 3), 0.5, jnp.float32))
    mask = jnp.array([[True, True, True], [True, True, False]])
    obs = _observation([[1.0, 0.9, 0.5]] * 2, mask)
    planner = baselines.coordinated_planner(_params(), kappa=0.0, lam=0.0, mu=0.0)
    _, actions = jax.jit(planner.act)(jax.random.PRNGKey(0), planner.init(2), obs, state)
    assert actions.tolist() == [0, 0]  # the only feasible poses are crowded: still act


def test_oracle_robots_do_not_claim_the_same_windows():
    """Two robots at one spot with the same candidates: the second one looks elsewhere."""
    size = 20
    wcfg = WorldConfig(size=size, buildings=25, targets=(200, 250), layout="random")
    params = _params()
    params = params.__class__(**{**params.__dict__, "world": wcfg})
    truth = jax.jit(world.generate, static_argnums=1)(jax.random.PRNGKey(3), wcfg)
    # candidates: one position, all four headings
    pos = jnp.full((4, 3), 0.5, jnp.float32).at[:, 2].set(0.2)
    cands = types.SimpleNamespace(position=jnp.broadcast_to(pos, (2, 4, 3)),
                                  heading=jnp.broadcast_to(jnp.arange(4, dtype=jnp.int32), (2, 4)))
    state = types.SimpleNamespace(world=truth, candidates=cands,
                                  discovered=jnp.zeros(truth.target_valid.shape, bool))
    obs = _observation(jnp.zeros((2, 4)), jnp.ones((2, 4), bool))
    planner = baselines.oracle_planner(params)
    _, actions = jax.jit(planner.act)(jax.random.PRNGKey(0), planner.init(2), obs, state)
    from jaxmripp import sensing

    seen = jax.vmap(lambda h: sensing.cast(truth, pos[0], h, params.sensor, size).seen)(
        jnp.arange(4, dtype=jnp.int32))
    counts = np.asarray(seen.sum(-1))
    assert counts.max() > 0, "test world must have windows in view"
    a0, a1 = actions.tolist()
    assert counts[a0] == counts.max()
    fresh = np.asarray((seen & ~seen[a0]).sum(-1))
    assert fresh[a1] == fresh.max() and (a1 != a0 or fresh.max() == 0)


# ---------------------------------------------------------------------------------------
# Ranking on small worlds: same worlds and trials for every planner (fixed seeds)

SMALL = ["world.size=30", "robots.start=[0.0, 0.0, 0.3]", "candidates.positions=8",
         "candidates.oversample=3", "gp.capacity=24", "gp.eval_grid=2"]
WORLDS = 24


@pytest.fixture(scope="module")
def ranking():
    cfg = config.load(ROOT / "configs" / "smoke.yaml", SMALL)
    shape = evaluate.Shape(n_robots=2, size=30, radio_range=float("inf"), budget=4.0)
    params = evaluate.eval_params(cfg, shape.budget, robots=2, size=30,
                                  radio_range=shape.radio_range)
    out = {}
    for name in ("random", "greedy", "mcts", "oracle"):
        planner = evaluate.baseline_planner(name, params, cfg.eval)
        out[name] = evaluate.run_shape(planner, params, shape, seed=11, worlds=WORLDS,
                                       trials=1, keep_pictures=False,
                                       compiler_options=FAST).discovered
    return out


def test_tree_search_beats_random(ranking):
    diff = ranking["mcts"] - ranking["random"]  # paired: same worlds
    assert diff.mean() > 0, {k: v.mean() for k, v in ranking.items()}


def test_oracle_at_least_greedy(ranking):
    assert ranking["oracle"].mean() >= ranking["greedy"].mean()
    assert ranking["oracle"].mean() >= ranking["mcts"].mean()
