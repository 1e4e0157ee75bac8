"""Non-learning planners: coordination rules on hand-made states, and their ranking on
small worlds (the tree search beats random, the ground-truth oracle beats greedy)."""

import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.evaluation import baselines, cells, evaluate, planners
from jaxmripp import config
from jaxmripp.sim import geometry, world
from jaxmripp.config import WorldConfig
from jaxmripp.sim.observation import FEATURES, Observation

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


def _act(planner, obs, state, dyn=None):
    """planner.act jitted with the hand-made state (not a pytree) closed over."""
    act = jax.jit(lambda key, obs, dyn: planner.act(key, planner.init(2), obs, state, dyn)[1])
    return act(jax.random.PRNGKey(0), obs, dyn)


SMOKE = config.load(ROOT / "tests" / "smoke.yaml")


def _params():
    return evaluate.eval_params(SMOKE, 2.0)


def _dyn(radio_range=np.inf, collision_distance=0.05):
    return evaluate.eval_dynamic(SMOKE, 2.0, radio_range=radio_range).with_values(
        collision_distance=collision_distance)


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
    planner = baselines.coordinated_planner(_params(), kappa=0.0, lam=0.0, mu=1.0,
                                              novelty=False)
    assert _act(planner, obs, state, _dyn(radio_range)).tolist() == [0, expect_second]  # out of radio range: no coordination


def test_coordinated_falls_back_when_everything_is_crowded():
    positions = [[0.5, 0.5, 0.5], [0.52, 0.5, 0.5], [0.1, 0.9, 0.5]]
    state = types.SimpleNamespace(candidates=_candidates(positions),
                                  position=jnp.full((2, 3), 0.5, jnp.float32))
    mask = jnp.array([[True, True, True], [True, True, False]])
    obs = _observation([[1.0, 0.9, 0.5]] * 2, mask)
    planner = baselines.coordinated_planner(_params(), kappa=0.0, lam=0.0, mu=0.0,
                                              novelty=False)
    assert _act(planner, obs, state, _dyn()).tolist() == [0, 0]  # the only feasible poses are crowded: still act


def test_oracle_robots_do_not_claim_the_same_windows():
    """Two robots at one spot with the same candidates (one position, four headings): the
    first takes the heading that sees most windows, the second the one that sees most of
    the rest."""
    from jaxmripp.sim import sensing

    size = 20
    wcfg = WorldConfig(size=size, buildings=25, targets=(200, 250), layout="random")
    params = _params()
    params = params.__class__(**{**params.__dict__, "world": wcfg})
    truth = jax.jit(world.generate, static_argnums=1)(jax.random.PRNGKey(3), wcfg)
    headings = jnp.arange(4, dtype=jnp.int32)
    look = jax.jit(jax.vmap(jax.vmap(
        lambda p, h: sensing.cast(truth, p, h, params.sensor, size).seen, (None, 0)), (0, None)))
    grid = np.linspace(0.1, 0.9, 5)
    spots = jnp.asarray([(x, y, 0.15) for x in grid for y in grid], jnp.float32)
    seen_all = np.asarray(look(spots, headings))  # (spots, 4, T)
    free = ~np.asarray(world.occupied(truth, geometry.voxel_of(spots, size)))
    useful = free & ((seen_all.sum(-1) > 0).sum(-1) >= 2)
    assert useful.any(), "test world must have a spot with windows in two directions"
    spot = int(np.argmax(useful))
    seen = seen_all[spot]
    pos = jnp.broadcast_to(spots[spot], (4, 3))
    # One cost for all four (the oracle scores windows per unit of cost).
    cands = types.SimpleNamespace(position=jnp.broadcast_to(pos, (2, 4, 3)),
                                  heading=jnp.broadcast_to(headings, (2, 4)),
                                  cost=jnp.full((2, 4), 0.2, jnp.float32))
    state = types.SimpleNamespace(world=truth, candidates=cands,
                                  discovered=jnp.zeros(truth.target_valid.shape, bool))
    obs = _observation(jnp.zeros((2, 4)), jnp.ones((2, 4), bool))
    a0, a1 = _act(baselines.oracle_planner(params), obs, state).tolist()
    counts = seen.sum(-1)
    assert counts[a0] == counts.max()
    fresh = (seen & ~seen[a0]).sum(-1)
    assert fresh[a1] == fresh.max() > 0 and a1 != a0


# ---------------------------------------------------------------------------------------
# Ranking on small worlds: same worlds and trials for every planner (fixed seeds)

SMALL = ["world.size=30", "robots.start=[0.0, 0.0, 0.3]", "candidates.positions=8",
         "candidates.oversample=3", "gp.capacity=24", "gp.eval_grid=2"]
WORLDS = 192  # compiling dominates; many worlds make the paired comparison tight


@pytest.fixture(scope="module")
def ranking():
    cfg = config.load(ROOT / "tests" / "smoke.yaml", SMALL)
    shape = cells.Shape(n_robots=2, size=30, radio_range=float("inf"), budget=6.0)
    params = evaluate.eval_params(cfg, shape.budget, robots=2, size=30)
    dyn = evaluate.eval_dynamic(cfg, shape.budget, radio_range=shape.radio_range)
    out = {}
    for name in ("random", "greedy", "mcts", "oracle"):
        planner = planners.baseline_planner(name, params, cfg.eval)
        out[name] = cells.run_shapes(planner, params, [shape], [dyn], seed=11, worlds=WORLDS,
                                     trials=1, keep_pictures=False,
                                     compiler_options=FAST)[0].discovered
    return out


@pytest.mark.slow  # the ranking compiles four planners over 20 worlds: about 2 minutes
def test_tree_search_beats_random(ranking):
    diff = ranking["mcts"] - ranking["random"]  # paired: same worlds and start
    t = diff.mean() / (diff.std(ddof=1) / np.sqrt(len(diff)))
    assert t > 2.0, ({k: v.mean() for k, v in ranking.items()}, t)


@pytest.mark.slow
def test_oracle_at_least_greedy(ranking):
    assert ranking["oracle"].mean() >= ranking["greedy"].mean()
    assert ranking["oracle"].mean() >= ranking["mcts"].mean()


def test_novelty_scores_discount_seen_regions():
    obs = _observation([[2.0, 2.0, 0.0]], jnp.ones((1, 3), bool))
    std = FEATURES.index("utility_std")
    obs = obs.replace(features=obs.features.at[0, :, std].set(jnp.array([1.0, 0.5, 1.0])))
    scores = baselines.novelty_scores(obs, kappa=0.3, lam=0.0)
    np.testing.assert_allclose(scores[0], [2.0 + 0.3, 2.0 * 0.25 + 0.15, 0.3], rtol=1e-6)
