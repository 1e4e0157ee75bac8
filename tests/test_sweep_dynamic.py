"""A sweep over radio ranges x budgets for one team and world size: the cells differ only
in DynamicParams, so they are traced and compiled once and run vmapped over the stacked
values, and every cell's episodes equal those of a run of that cell alone."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config
from jaxmripp.evaluation import cells, evaluate, planners, sweep

ROOT = Path(__file__).resolve().parents[1]
FAST = {"xla_backend_optimization_level": 0}
RANGES, BUDGETS = (0.1, 0.3, float("inf")), (1.0, 2.0)
CFG = config.load(ROOT / "tests" / "smoke.yaml", [
    "world.size=20", "robots.start=[0.0, 0.0, 0.5]", "candidates.positions=4",
    "candidates.oversample=3", "eval.planners=[coordinated]", "eval.team_sizes=[2]",
    "eval.world_sizes=[20]", "eval.radio_ranges=[0.1, 0.3, .inf]", "eval.budgets=[1.0, 2.0]",
    "eval.worlds=2", "eval.trials=2", "eval.seed=5"])


@pytest.fixture(scope="module")
def swept():
    cells.TRACES.clear()
    lines = []
    result = sweep.run_sweep(CFG, log=lines.append, time_planning=False, keep_pictures=False,
                             compiler_options=FAST)
    return result, lines


def test_six_cells_are_traced_once(swept):
    result, lines = swept
    assert len(lines) == 6 and "shared by 6 cells" in lines[0]
    assert dict(cells.TRACES) == {("coordinated", 2, 20): 1}
    assert [(r.shape.radio_range, r.shape.budget) for r in result.runs] == [
        (rho, b) for rho in RANGES for b in BUDGETS]
    # One static shape: max_steps covers the largest budget for every cell.
    assert {r.max_steps for r in result.runs} == {
        evaluate.eval_params(CFG, max(BUDGETS), robots=2, size=20).max_steps}


def _same_episodes(run, alone):
    alone = jax.tree.map(np.asarray, alone)
    np.testing.assert_array_equal(run.discovered,
                                  alone.discovered_fraction.astype(np.float64) * 100)
    for field in ("steps", "distance", "contacts"):
        np.testing.assert_array_equal(getattr(run, field), getattr(alone, field), field)
    for field, count in run.safety.items():
        np.testing.assert_array_equal(count, getattr(alone, field), field)
    np.testing.assert_array_equal(run.curve_budget, alone.trajectory.budget_used)


def test_the_traced_values_reach_the_episodes(swept):
    """rho sets the contacts, B the distance flown."""
    result, _ = swept
    by_cell = {(r.shape.radio_range, r.shape.budget): r for r in result.runs}
    assert by_cell[(0.1, 2.0)].contacts.sum() < by_cell[(float("inf"), 2.0)].contacts.sum()
    assert by_cell[(0.3, 1.0)].distance.sum() < by_cell[(0.3, 2.0)].distance.sum()


@pytest.mark.slow  # a second program (about 14 s); the values traced are what JAX vmaps
def test_each_cell_equals_a_run_of_its_own(swept):
    """Each cell again in a call of its own (one compilation with the values traced)."""
    result, _ = swept
    params = evaluate.eval_params(CFG, BUDGETS, robots=2, size=20)
    planner = planners.baseline_planner("coordinated", params, CFG.eval)
    e = CFG.eval
    wk = jnp.repeat(cells.world_keys(e.seed, e.worlds), e.trials, axis=0)
    tk = cells.trial_keys(e.seed, e.worlds, e.trials).reshape(-1, 2)
    episodes = lambda w, t, d: cells.run_trial(w, t, params, d, planner)[0]  # noqa: E731
    one_cell = jax.jit(jax.vmap(episodes, in_axes=(0, 0, None)), compiler_options=FAST)
    for run in result.runs:
        _same_episodes(run, one_cell(wk, tk, evaluate.eval_dynamic(
            CFG, run.shape.budget, run.shape.radio_range)))
