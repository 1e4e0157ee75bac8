"""Evaluation sweeps: one compilation per team and world size, determinism, statistics, written
outputs."""

import csv
import dataclasses
import json
import math
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from jaxmripp import config
from jaxmripp.evaluation import cells, outputs, stats as evalstats, sweep
from jaxmripp.parallel.local import host_devices_env

ROOT = Path(__file__).resolve().parents[1]
FAST = {"xla_backend_optimization_level": 0}  # compile fast; these tests run tiny worlds
TINY = ["world.size=20", "robots.start=[0.0, 0.0, 0.5]", "candidates.positions=4",
        "candidates.oversample=3", "eval.planners=[random]", "eval.team_sizes=[2]",
        "eval.world_sizes=[20]", "eval.radio_ranges=[.inf]", "eval.budgets=[1.5, 2.0]",
        "eval.worlds=3", "eval.trials=2", "eval.seed=7"]


# ---------------------------------------------------------------------------------------
# Statistics


@pytest.mark.parametrize("sizes", [(5, 5), (7, 30), (250, 250), (2, 3)])
def test_welch_ttest_matches_scipy(sizes):
    rng = np.random.default_rng(sum(sizes))
    a = rng.normal(50, 8, sizes[0])
    b = rng.normal(46, 13, sizes[1])
    t, df, p = evalstats.welch_ttest(a, b)
    ref = stats.ttest_ind(a, b, equal_var=False)
    assert t == pytest.approx(ref.statistic, rel=1e-10)
    assert p == pytest.approx(ref.pvalue, rel=1e-8, abs=1e-300)
    if hasattr(ref, "df"):
        assert df == pytest.approx(ref.df, rel=1e-10)


def test_welch_ttest_degenerate_samples():
    assert evalstats.welch_ttest([3.0, 3.0], [3.0, 3.0])[2] == 1.0
    t, _, p = evalstats.welch_ttest([4.0, 4.0, 4.0], [3.0, 3.0])
    assert t == math.inf and p == 0.0
    p_far = evalstats.welch_ttest(np.arange(30.0), np.arange(30.0) + 100)[2]
    assert 0.0 <= p_far < 1e-20


def test_mean_ci_is_student_t():
    x = np.array([1.0, 2.0, 4.0, 7.0])
    mean, std, half = evalstats.mean_ci(x)
    lo, hi = stats.t.interval(0.95, len(x) - 1, loc=x.mean(), scale=stats.sem(x))
    assert (mean - half, mean + half) == pytest.approx((lo, hi))
    assert std == pytest.approx(x.std(ddof=1))


# ---------------------------------------------------------------------------------------
# Keys and shapes


def test_world_and_trial_keys_are_fixed_and_distinct():
    w1, w2 = cells.world_keys(3, 4), cells.world_keys(3, 6)
    np.testing.assert_array_equal(w1, w2[:4])  # world w does not depend on the sweep size
    t = np.asarray(cells.trial_keys(3, 4, 5)).reshape(-1, 2)
    assert len({tuple(k) for k in t}) == 20
    assert not set(map(tuple, t)) & set(map(tuple, np.asarray(w2)))
    assert not np.array_equal(cells.world_keys(4, 4), w1)


def _fake_cfg(**eval_fields):
    base = dict(team_sizes=(16, 32), world_sizes=(75, 100), radio_ranges=(0.2, 0.15),
                budgets=(3.0,))
    base.update(eval_fields)
    return types.SimpleNamespace(eval=types.SimpleNamespace(**base))


def test_shapes_cross_zip_and_per_robot_budget():
    crossed = sweep.shapes_of(_fake_cfg())
    assert len(crossed) == 2 * 2 * 2
    zipped = sweep.shapes_of(_fake_cfg(zip_with_size=("radio_ranges",), budget_mode="per_robot"))
    assert [(s.size, s.n_robots, s.radio_range, s.budget) for s in zipped] == [
        (75, 16, 0.2, 48.0), (75, 32, 0.2, 96.0), (100, 16, 0.15, 48.0), (100, 32, 0.15, 96.0)]
    with pytest.raises(ValueError, match="radio_ranges"):
        sweep.shapes_of(_fake_cfg(zip_with_size=("radio_ranges",), radio_ranges=(0.2,)))


def test_pairs_and_planner_names():
    assert sweep.default_pairs(["a", "b", "c"], []) == [("a", "b"), ("a", "c")]
    assert sweep.default_pairs(["a", "b"], ["b : a"]) == [("b", "a")]
    with pytest.raises(ValueError, match="eval.pairs"):
        sweep.default_pairs(["a"], ["ab"])
    cfg = config.load(None, ["eval.planners=[greedy, policy, random]"])
    assert sweep.planner_names(cfg, {}) == ["greedy", "random"]
    assert sweep.planner_names(cfg, {"full": None, "g0": None}) == ["greedy", "full", "g0", "random"]


@pytest.mark.parametrize("name", ["protocol_table1", "protocol_table1_paper_world",
                                  "protocol_scale"])
def test_presets_load(name):
    cfg = config.load(ROOT / "configs" / f"{name}.yaml")
    shapes = sweep.shapes_of(cfg)
    if name == "protocol_scale":
        assert {(s.size, s.radio_range) for s in shapes} == {(75, 0.2), (100, 0.15), (125, 0.12)}
        assert len(shapes) == 12
    else:
        assert {s.radio_range for s in shapes} == {math.inf, 0.1}
        assert cfg.eval.worlds * cfg.eval.trials == 250
        # Table I is reported with both short-range rules (the ablations add the paper's).
        assert (cfg.eval.sectors, cfg.safety.escape) == (True, True)


def test_evaluations_of_a_shipped_policy_leave_its_folder_as_shipped(tmp_path):
    from jaxmripp.pipeline import eval_dir

    run = tmp_path / "runs" / "mine"
    (run / "checkpoints" / "last" / "10").mkdir(parents=True)  # a saved step: a run
    assert eval_dir("configs/protocol_table1.yaml",
                    [run, ROOT / "pretrained/paper"]) == run / "eval"
    assert eval_dir("configs/protocol_table1.yaml", [ROOT / "pretrained/scale"]) == \
        Path("runs/scale/eval")
    assert eval_dir("configs/protocol_table1.yaml", []) == Path("runs/protocol_table1/eval")


# ---------------------------------------------------------------------------------------
# A tiny sweep: 2 shapes (two budgets: one program) x 1 planner, 6 episodes each in
# chunks of 4 (one padded chunk)


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
    cfg = config.load(ROOT / "tests" / "smoke.yaml", TINY)
    cells.TRACES.clear()
    lines = []
    result = sweep.run_sweep(cfg, log=lines.append, batch=4, time_planning=True,
                             compiler_options=FAST)
    out = tmp_path_factory.mktemp("eval")
    paths = outputs.write_outputs(result, out, cfg, command="pytest")
    return cfg, result, lines, out, paths


def test_one_compile_per_team_and_world_size(tiny_sweep):
    cfg, result, lines, _, _ = tiny_sweep
    shapes = sweep.shapes_of(cfg)
    assert len(shapes) == 2 and len(lines) == 2
    # One trace for both budgets (the budget is a traced value), though each ran in 2 chunks.
    assert dict(cells.TRACES) == {("random", 2, 20): 1}
    for run in result.runs:
        assert len(run.discovered) == 6 and run.discovered.shape == run.steps.shape
        assert np.all((run.discovered >= 0) & (run.discovered <= 100))
        assert np.isfinite(run.plan_ms_per_robot_step) and run.ms_per_robot_step > 0
    assert "compile" in lines[0] and "N = 2, G = 20" in lines[0]


def test_static_groups_split_by_team_and_world_size_in_order_of_appearance():
    """What each compilation covers: the shapes of one team and world size (the sweep's
    other cells run in the same program, tests/test_sweep_dynamic.py)."""
    shape = lambda n, g, b: cells.Shape(n_robots=n, size=g, radio_range=0.1, budget=b)  # noqa: E731
    shapes = [shape(2, 20, 1.0), shape(1, 20, 1.0), shape(2, 30, 1.0), shape(2, 20, 2.0),
              shape(1, 20, 3.0)]
    assert sweep.static_groups(shapes) == [[shapes[0], shapes[3]], [shapes[1], shapes[4]],
                                           [shapes[2]]]


def test_worlds_shared_across_shapes(tiny_sweep):
    _, result, _, _, _ = tiny_sweep
    one, two = result.runs
    np.testing.assert_array_equal(one.snapshot.height, two.snapshot.height)
    np.testing.assert_array_equal(one.targets, two.targets)
    # trials of a world share it; different worlds differ
    assert np.array_equal(one.snapshot.height[0], one.snapshot.height[1])
    assert not np.array_equal(one.snapshot.height[0], one.snapshot.height[2])


def test_outputs_written(tiny_sweep):
    _, result, _, out, paths = tiny_sweep
    for key in ("table", "csv", "json", "summary", "discovered_vs_budget_0.png",
                "discovered_vs_budget_1.png", "episode_random", "gif_random",
                "missed_windows_0.png", "missed_windows_1.png"):
        assert paths[key].is_file() and paths[key].stat().st_size > 0, key
    table = (out / "results.md").read_text()
    assert "| random |" in table and "95% CI" in table
    rows = list(csv.DictReader((out / "runs.csv").open()))
    assert len(rows) == 2 * 6
    assert json.loads((out / "runs.json").read_text()) == json.loads(json.dumps(
        result.records()))
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["summary"]) == 2 and summary["eval"]["planners"] == ["random"]
    from PIL import Image
    with Image.open(paths["gif_random"]) as gif:
        assert gif.n_frames >= 1
    assert "team_size" not in paths  # one team size: no plot over team sizes


def test_a_sweep_over_team_sizes_plots_the_discovery_by_team_size(tiny_sweep, tmp_path):
    """The same runs relabelled as a second team size (the plot reads only the labels and
    the figures): the plot over team sizes appears, and the table has a row per size."""
    _, result, _, _, _ = tiny_sweep
    relabelled = [dataclasses.replace(run, shape=dataclasses.replace(run.shape, n_robots=1))
                  for run in result.runs]
    paths = outputs.write_outputs(sweep.SweepResult(result.runs + relabelled, result.pairs),
                                  tmp_path, render=False)
    assert paths["team_size"].is_file() and paths["team_size"].stat().st_size > 0
    table = (tmp_path / "results.md").read_text()
    assert "N = 1, G = 20" in table and "N = 2, G = 20" in table


def _cli():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import eval as cli

    return cli


@pytest.mark.slow
def test_cli_on_two_devices_reproduces_the_sweep(tiny_sweep, tmp_path):
    """eval.py on one shape of the sweep, its episodes split over 2 devices (a padded
    chunk included), reproduces the 1-device numbers and table rows exactly."""
    _, result, _, _, _ = tiny_sweep
    done = subprocess.run(
        [sys.executable, str(ROOT / "eval.py"), "--config", str(ROOT / "tests" / "smoke.yaml"),
         "--out", str(tmp_path), "--no-render", "--no-timing", *TINY, "eval.team_sizes=[2]",
         "eval.batch=4"],
        cwd=ROOT, env=host_devices_env(2), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader((tmp_path / "runs.csv").open()))
    two = [r for r in result.records() if r["n_robots"] == 2]
    assert rows == [{k: str(v) for k, v in r.items()} for r in two]
    text = (tmp_path / "results.md").read_text()
    again = sweep.SweepResult([r for r in result.runs if r.shape.n_robots == 2], result.pairs)
    rows_md = [line for line in again.table(timing=False).splitlines() if line.startswith("| random")]
    assert rows_md
    for line in rows_md:  # planner, % targets and CI columns are identical
        assert " | ".join(line.split(" | ")[:3]) in text


def test_cli_rejects_bad_arguments(tmp_path, capsys):
    cli = _cli()
    assert cli.main(["--config", str(tmp_path / "missing.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().err
    assert cli.main(["--config", str(ROOT / "tests" / "smoke.yaml"),
                     "--policy", f"p={tmp_path}"]) == 2
    assert "an empty folder; allowed: a training run" in capsys.readouterr().err


def test_missed_windows_pools_the_episodes_and_counts_by_region():
    from types import SimpleNamespace

    from jaxmripp.evaluation import plots

    # G = 20, two episodes of three window slots; the third slot of episode 0 is unused.
    voxel = np.array([[[0, 10, 2], [10, 10, 15], [5, 5, 5]],
                      [[10, 19, 10], [10, 10, 2], [3, 3, 3]]])
    snapshot = SimpleNamespace(
        height=np.zeros((2, 20, 20)), target_voxel=voxel,
        target_valid=np.array([[True, True, False], [True, True, True]]),
        found_at=np.array([[-1, -1, -1], [-1, 4, 0]]))
    centres, counts = plots.missed_windows(SimpleNamespace(snapshot=snapshot))
    # Missed: (0, 10, 2) at the x = 0 side and low; (10, 10, 15) inside and high;
    # (10, 19, 10) at the y = 1 side, not low. The unused slot is not a window.
    np.testing.assert_allclose(centres, (np.array([[0, 10, 2], [10, 10, 15], [10, 19, 10]])
                                         + 0.5) / 20)
    # Flat ground (no buildings): the one interior miss faces every way.
    assert counts == {"windows": 5, "missed": 3, "edge": 2, "low": 1,
                      "+x": 1, "-x": 1, "+y": 1, "-y": 1}


def test_window_facing_follows_the_free_columns_beside_each_window():
    from jaxmripp.evaluation import plots

    # G = 10: a 3 x 3 building of height 8 at x, y in 4..6, a height-2 neighbour at x = 7,
    # y in 4..6, and a height-5 building in the corner x, y in 0..1.
    height = np.zeros((10, 10), int)
    height[4:7, 4:7] = 8
    height[7, 4:7] = 2
    height[0:2, 0:2] = 5
    voxel = np.array([[4, 5, 2],   # west face only
                      [6, 6, 3],   # north-east corner above the low neighbour: +x and +y
                      [5, 4, 7],   # south face only
                      [6, 5, 1],   # east face, below the neighbour's roof: faces nothing
                      [6, 5, 3],   # east face above that roof
                      [0, 1, 4]])  # at the grid's edge: -x is outside, +y free
    faces = plots.window_facing(height, voxel)
    labels = [label for label, _, _ in plots.FACINGS]
    got = [[labels[k] for k in np.flatnonzero(row)] for row in faces]
    assert got == [["-x"], ["+x", "+y"], ["-y"], [], ["+x"], ["+y"]]
