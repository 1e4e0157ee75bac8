"""nbv_targets and the upper references (oracle per cost, oracle_ahead, oracle_rate,
oracle_city) in their limits, and comparisons paired by world (jaxmripp.evaluation.stats) against scipy.

Episodes run on the smoke world (G = 20, 6 positions, 2 robots); they compile whole
episodes, so they are in the slow suite."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as scipy_stats

from jaxmripp import config
from jaxmripp.evaluation import baselines, evaluate, planners
from jaxmripp.evaluation import stats
from jaxmripp.sim import belief, env as envmod, episode, oracle, sensing, view
from jaxmripp.sim import world as worldmod
from jaxmripp.sim.geometry import UNKNOWN
from jaxmripp.spec import belief as belief_spec

ROOT = Path(__file__).resolve().parents[1]
CFG = config.load(ROOT / "tests" / "smoke.yaml", ["safety.flight=truncate"])
PARAMS = evaluate.eval_params(CFG, 4.0)
BRANCHES = 4


def _episodes(planner, radio_range=math.inf, count=3):
    dyn = evaluate.eval_dynamic(CFG, 4.0, radio_range=radio_range)
    run = jax.jit(jax.vmap(lambda k: episode.run(k, PARAMS, dyn, planner).trajectory))
    return jax.tree.map(np.asarray, run(jax.random.split(jax.random.PRNGKey(11), count)))


@pytest.mark.slow
def test_nbv_targets_with_an_unshakable_prior_chooses_as_nbv_ahead():
    # A prior no window moves puts every building at rho = 1 (q = RATE_SCALE): the
    # rate-weighted facade is the facade, so the two search the same values.
    ahead = baselines.nbv_ahead_planner(PARAMS, 2.0, 3.0, BRANCHES)
    targets = baselines.nbv_targets_planner(PARAMS, 1e9, 2.0, 3.0, BRANCHES)
    a, b = _episodes(ahead), _episodes(targets)
    assert a.active.sum() > 4
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.heading, b.heading)


@pytest.mark.slow
def test_every_new_planner_runs_by_name_with_feasible_choices():
    for name in ("nbv_targets", "oracle", "oracle_ahead", "oracle_rate", "oracle_city"):
        overrides = {"eval": {"nbv_targets_branches": BRANCHES, "oracle_ahead_branches": 3}}
        cfg = config.from_dict(overrides, CFG)
        trajectory = _episodes(planners.baseline_planner(name, PARAMS, cfg.eval), count=2)
        # Some episode finds windows (in 8 steps oracle_city may spend one's budget
        # turning at the start: turns are cheap and every window voxel in view counts).
        assert trajectory.discovered_fraction[:, -1].max() > 0, name
        assert trajectory.active.any(), name


def _after_random_steps(rho, steps):
    """(obs, state, dyn) after `steps` steps of random choices at radio range rho."""
    dyn = evaluate.eval_dynamic(CFG, 4.0, radio_range=rho)
    obs, state = jax.jit(envmod.reset, static_argnums=1)(jax.random.PRNGKey(4), PARAMS, dyn)
    step = jax.jit(envmod.step, static_argnums=3)
    for t in range(steps):
        act = baselines.random_planner().act(jax.random.PRNGKey(t), None, obs)[1]
        obs, state, *_ = step(jax.random.PRNGKey(10 + t), state, act, PARAMS, dyn)
    return obs, state, dyn


@pytest.fixture(scope="module")
def stepped():
    """A state after two steps of random choices (its candidates, windows, maps), at rho =
    inf and at rho = 0 (nobody hears anybody)."""
    return {rho: _after_random_steps(rho, 2) for rho in (math.inf, 0.0)}


def _fresh_per_cost(state, robot, covered):
    """(L,) the windows in view of each of the robot's candidates that `covered` does not
    hold, per unit of cost (brute force over the candidates)."""
    c = state.candidates
    fresh = []
    for p, h in zip(np.asarray(c.position[robot]), np.asarray(c.heading[robot])):
        seen = np.asarray(sensing.cast(state.world, jnp.asarray(p), jnp.asarray(h),
                                       PARAMS.sensor, PARAMS.size).seen)
        fresh.append((seen & ~covered).sum())
    return np.asarray(view.per_cost(jnp.asarray(fresh, jnp.float32), c.cost[robot],
                                    PARAMS.candidates.shell[1]))


@pytest.mark.slow
def test_oracle_ahead_without_discount_is_the_oracle_per_cost_in_range(stepped):
    obs, state, dyn = stepped[math.inf]
    tie = 0.01 * jax.random.uniform(jax.random.PRNGKey(2), obs.mask.shape)
    ahead = oracle.choose_ahead(jax.random.PRNGKey(3), obs.mask, state, dyn, PARAMS, tie,
                                0.0, BRANCHES)
    greedy = oracle.choose_in_turn(obs.mask, state, PARAMS, tie, per_cost=True)
    np.testing.assert_array_equal(np.asarray(ahead), np.asarray(greedy))
    # Robot 0 takes the most windows per cost (brute force); so does the per-cost oracle.
    score = _fresh_per_cost(state, 0, np.asarray(state.discovered)) + np.asarray(tie[0])
    assert int(greedy[0]) == int(np.argmax(np.where(obs.mask[0], score, -np.inf)))


@pytest.mark.slow
def test_oracle_ahead_robots_out_of_range_ignore_each_others_claims(stepped):
    obs, state, dyn = stepped[0.0]
    assert not np.asarray(state.heard & ~np.eye(2, dtype=bool)).any()
    tie = 0.01 * jax.random.uniform(jax.random.PRNGKey(2), obs.mask.shape)
    ahead = oracle.choose_ahead(jax.random.PRNGKey(3), obs.mask, state, dyn, PARAMS, tie,
                                0.0, BRANCHES)
    for robot in range(2):
        score = _fresh_per_cost(state, robot, np.asarray(state.discovered))
        score = np.where(obs.mask[robot], score + np.asarray(tie[robot]), -np.inf)
        assert int(ahead[robot]) == int(np.argmax(score))


def _open_sided(height: np.ndarray) -> np.ndarray:
    """(G, G, G) bool, brute force: building voxels with a horizontal neighbour (or the
    grid's edge) that is not a building at the same height."""
    size = height.shape[0]
    solid = np.arange(size)[None, None, :] < height[:, :, None]
    padded = np.pad(solid, ((1, 1), (1, 1), (0, 0)), constant_values=False)
    beside = [padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]]
    return solid & ~np.logical_and.reduce(beside)


@pytest.mark.parametrize("overrides", [[], ["world.footprint_min=2", "world.footprint=4"]])
def test_window_voxels_are_the_open_sides_and_hold_every_window(overrides):
    world_cfg = config.load(None, overrides).world
    for seed in range(3):
        world = worldmod.generate(jax.random.PRNGKey(seed), world_cfg)
        height = np.asarray(world.height)
        slots = np.asarray(belief.window_voxels(world.height, world_cfg))
        np.testing.assert_array_equal(slots, _open_sided(height))
        x, y, z = np.asarray(world.target_voxel)[np.asarray(world.target_valid)].T
        assert slots[x, y, z].all()
    inside = dataclasses.replace(world_cfg, target_placement="footprint")  # windows anywhere
    solid = np.arange(world_cfg.size)[None, None, :] < height[:, :, None]
    np.testing.assert_array_equal(np.asarray(belief.window_voxels(world.height, inside)), solid)


@pytest.mark.slow
def test_the_city_oracle_takes_the_most_expected_new_windows_per_cost():
    """Brute force over each robot's candidates, in turn: the windows a pose is expected
    to reveal are its observed open-sided building voxels that the robot's map lacks and
    the earlier robot's choice does not observe, each its building's true rate x m. After
    five steps (before, the tiny world's short sensor sees no building from most poses)."""
    obs, state, _ = _after_random_steps(math.inf, 5)
    tie = 0.01 * jax.random.uniform(jax.random.PRNGKey(2), obs.mask.shape)
    rates = belief.true_rates(state, PARAMS.sensor, PARAMS.world)
    actions = oracle.choose_city_in_turn(obs.mask, state, PARAMS, tie, rates)
    size, c = PARAMS.size, state.candidates
    slots = _open_sided(np.asarray(state.world.height)).reshape(-1)
    scale = belief.prior(PARAMS.world) / belief_spec.RATE_SCALE
    covered = np.zeros(size**3, bool)
    expected_any = False
    for robot in range(2):
        unknown = np.asarray(state.occupancy[robot]).reshape(-1) == UNKNOWN
        rate = np.asarray(rates[robot]).reshape(-1)
        observed, expected = [], []
        for p, h in zip(np.asarray(c.position[robot]), np.asarray(c.heading[robot])):
            flat = np.asarray(sensing.cast(state.world, jnp.asarray(p), jnp.asarray(h),
                                           PARAMS.sensor, size).voxels)
            flat = flat[flat < size**3]
            fresh = flat[slots[flat] & unknown[flat] & ~covered[flat]]
            observed.append(flat)
            expected.append(np.float32(rate[fresh // size].sum() * scale))
        score = np.asarray(view.per_cost(jnp.asarray(expected, jnp.float32), c.cost[robot],
                                         PARAMS.candidates.shell[1])) + np.asarray(tie[robot])
        expected_any |= max(expected) > 0
        best = int(np.argmax(np.where(obs.mask[robot], score, -np.inf)))
        assert int(actions[robot]) == best, robot
        covered[observed[best]] = True
    assert expected_any


# ---------------------------------------------------------------------------------------
# Statistics


def test_paired_by_world_matches_scipy_on_the_per_world_means():
    rng = np.random.default_rng(0)
    worlds, trials = 12, 5
    world_effect = np.repeat(rng.normal(50, 8, worlds), trials)
    a = world_effect + rng.normal(1.5, 1.0, worlds * trials)
    b = world_effect + rng.normal(0.0, 1.0, worlds * trials)
    test = stats.paired_by_world(a, b, worlds)
    mean_a, mean_b = a.reshape(worlds, trials).mean(1), b.reshape(worlds, trials).mean(1)
    t, p = scipy_stats.ttest_rel(mean_a, mean_b)
    assert test["t"] == pytest.approx(t) and test["p"] == pytest.approx(p)
    assert test["p_wilcoxon"] == pytest.approx(scipy_stats.wilcoxon(mean_a - mean_b).pvalue)
    diff = mean_a - mean_b
    assert test["diff"] == pytest.approx(diff.mean())
    assert test["dz"] == pytest.approx(diff.mean() / diff.std(ddof=1))
    half = scipy_stats.t.ppf(0.975, worlds - 1) * diff.std(ddof=1) / math.sqrt(worlds)
    assert test["ci"] == pytest.approx([diff.mean() - half, diff.mean() + half])
    # The worlds' spread hides the difference from a test that ignores the pairing.
    assert test["p"] < 0.01 < stats.welch_ttest(a, b)[2]


def test_paired_by_world_degenerate_and_mismatched_inputs():
    same = stats.paired_by_world([3.0, 4.0, 5.0, 6.0], [3.0, 4.0, 5.0, 6.0], 2)
    assert same["p"] == 1.0 and same["p_wilcoxon"] == 1.0 and same["diff"] == 0.0
    shifted = stats.paired_by_world([4.0, 5.0, 6.0, 7.0], [3.0, 4.0, 5.0, 6.0], 2)
    assert shifted["p"] == 0.0 and shifted["diff"] == 1.0
    with pytest.raises(ValueError, match="same worlds"):
        stats.paired_by_world([1.0, 2.0], [1.0], 1)
    with pytest.raises(ValueError, match="worlds"):
        stats.world_means([1.0, 2.0, 3.0], 2)


def test_quality_refuses_a_policy_given_twice():
    shipped = str(ROOT / "pretrained" / "default")
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "quality.py"),
                           "--policy", shipped, "--seeds", shipped],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip().startswith("error: --policy / --seeds") and done.stdout == ""
