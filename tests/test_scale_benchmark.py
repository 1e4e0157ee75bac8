"""benchmarks/scale.py: the grid's tables from JSON lines collected over runs (--collected)
and, slow, the --eval cell's figures and curves."""

import functools
import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scripts import load_script
from scipy import stats

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "scale.py"


@functools.cache
def _scale_module():
    return load_script("benchmarks/scale.py")


def run_script(capsys, *argv: str) -> SimpleNamespace:
    """The script's main in this process on the command line `argv` (the slow tests run
    it as a program): its exit status and what it printed."""
    try:
        status = _scale_module().main(list(argv))
    except SystemExit as exit_:  # argparse's own errors
        status = exit_.code
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=status, stdout=out, stderr=err)


def collected(capsys, path: Path, *extra: str) -> SimpleNamespace:
    return run_script(capsys, "--collected", str(path), *extra)


def test_tables_from_lines_collected_over_runs(tmp_path, capsys):
    def line(name, value, std):
        return json.dumps({"name": f"scale.grid.{name}", "value": value, "unit": "%",
                           "std": std, "worlds": 100})

    lines = [line("policy.relay.g125.n16", 60.0, 9.0),
             "not a JSON line",
             json.dumps({"name": "scale.relay_vs_best_global_16x", "value": 0.9}),
             line("nbv_team.global.g125.n64", 97.97, 0.58),
             line("nbv_team.relay.g125.n16", 80.0, 1.0),  # not the policy's: no ratio
             line("policy.relay.g125.n16", 68.96, 3.15),  # a later run of the same cell wins
             line("policy.global.g75.n32", 92.1, 2.04),
             line("policy.global.g125.n16", 74.21, 2.39)]
    path = tmp_path / "grid.jsonl"
    path.write_text("\n".join(lines) + "\n")
    figure = tmp_path / "grid.png"
    done = collected(capsys, path, "--figure", str(figure))
    assert done.returncode == 0, done.stderr
    out = done.stdout.splitlines()
    g75 = out.index("3x world (G = 75, rho = 0.2):")
    g125 = out.index("16x world (G = 125, rho = 0.12):")
    assert out[g75 + 2] == "| planner, exchange | N = 32 |"
    # every table has the same rows: those with a figure in some world, in a fixed order
    assert out[g75 + 4:g75 + 8] == ["| policy, relay | - |", "| policy, global | 92.10 (2.04) |",
                                    "| nbv_team, relay | - |", "| nbv_team, global | - |"]
    assert out[g125 + 2] == "| planner, exchange | N = 16 | N = 64 |"
    # "-" where a cell has no figure
    assert out[g125 + 4:g125 + 8] == ["| policy, relay | 68.96 (3.15) | - |",
                                      "| policy, global | 74.21 (2.39) | - |",
                                      "| nbv_team, relay | 80.00 (1.00) | - |",
                                      "| nbv_team, global | - | 97.97 (0.58) |"]
    # Welch's test by hand: t = -13.29 on 184.6 degrees of freedom
    va, vb = 3.15**2 / 100, 2.39**2 / 100
    t = (68.96 - 74.21) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / 99 + vb**2 / 99)
    p = 2 * stats.t.sf(abs(t), df)
    assert out[g125 + 8] == f"| relay / best global | {68.96 / 74.21:.3f} (p {p:.1g}) | - |"
    assert out[g75 + 8] == "| relay / best global | - |"
    # the ratios of every world in one table, over the team sizes of any world
    summary = out.index("The policy over the best planner with global communication:")
    assert out[summary + 2] == "| world, exchange | N = 16 | N = 32 | N = 64 |"
    assert out[summary + 4:summary + 8] == [
        "| 3x world (G = 75, rho = 0.2), single hop | - | - | - |",
        "| 3x world (G = 75, rho = 0.2), relay | - | - | - |",
        "| 16x world (G = 125, rho = 0.12), single hop | - | - | - |",
        f"| 16x world (G = 125, rho = 0.12), relay | {68.96 / 74.21:.3f} | - | - |"]
    assert figure.stat().st_size > 0


def test_tables_from_several_files_keep_the_last_file_of_a_cell(tmp_path, capsys):
    def write(name, *cells):
        path = tmp_path / name
        path.write_text("".join(json.dumps({"name": f"scale.grid.{c}", "value": v, "std": 1.0,
                                            "worlds": 10}) + "\n" for c, v in cells))
        return path

    first = write("a.jsonl", ("policy.relay.g100.n16", 50.0), ("nbv.global.g100.n16", 80.0),
                  ("policy.single_hop.g100.n16", 40.0))
    second = write("b.jsonl", ("policy.relay.g100.n16", 60.0), ("nbv.global.g75.n32", 90.0),
                   ("policy.single_hop.g75.n32", 45.0))
    done = collected(capsys, first, str(second))
    assert done.returncode == 0, done.stderr
    out = done.stdout.splitlines()
    summary = out.index("The policy over the best planner with global communication:")
    assert out[summary + 4:summary + 8] == [
        "| 3x world (G = 75, rho = 0.2), single hop | - | 0.500 |",
        "| 3x world (G = 75, rho = 0.2), relay | - | - |",
        "| 8x world (G = 100, rho = 0.15), single hop | 0.500 | - |",
        "| 8x world (G = 100, rho = 0.15), relay | 0.750 | - |"]
    missing = collected(capsys, first, str(tmp_path / "none.jsonl"))
    assert missing.returncode == 2
    assert f"--collected {tmp_path / 'none.jsonl'}: no such file" in missing.stderr


def test_no_grid_lines_is_an_error(tmp_path, capsys):
    path = tmp_path / "other.jsonl"
    path.write_text(json.dumps({"name": "scale.peak_rss_mb", "value": 1.0}) + "\n")
    done = collected(capsys, path)
    assert done.returncode == 2
    assert f"--collected {path}: no scale.grid.<planner>.<exchange>.g<G>.n<N> lines" in done.stderr


def test_a_planner_outside_the_allowed_is_an_error(capsys):
    done = run_script(capsys, "--grid", "--policy", str(SCRIPT.parents[1] / "pretrained" / "scale"),
                      "--range-planners", "policy,oracle")
    assert done.returncode == 2
    assert "--range-planners ['oracle']: allowed policy, coordinated, nbv, nbv_team" in done.stderr


@pytest.mark.slow  # six evaluations, each compiled on its own: about 2 minutes
def test_eval_cell_prints_the_ratio_of_its_own_figures_and_draws_the_curves(tmp_path):
    figure = tmp_path / "cell.png"
    done = subprocess.run([sys.executable, str(SCRIPT), "--teams", "2,3", "--size", "30",
                           "--radio-range", "0.3", "--envs", "1", "--repeats", "1", "--eval",
                           "--worlds", "2", "--policy", str(SCRIPT.parents[1] / "pretrained" /
                                                            "default"),
                           "--figure", str(figure), "eval.sectors=true"],
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    lines = {r["name"]: r for r in map(json.loads, done.stdout.splitlines())}
    pct = {name.split(".", 2)[2]: r["value"] for name, r in lines.items()
           if name.startswith("scale.pct.")}
    assert set(pct) == {"policy.single_hop", "policy.relay", "policy.global",
                        "coordinated.global", "nbv.global", "nbv_team.global"}
    best = max((v, k.split(".")[0]) for k, v in pct.items() if k.endswith(".global"))
    ratio = lines["scale.relay_vs_best_global_0x"]
    assert math.isclose(ratio["value"], pct["policy.relay"] / best[0], rel_tol=1e-3)
    assert ratio["best_global"] == best[1]
    assert figure.stat().st_size > 0


@pytest.mark.parametrize("ranges", ["0.12,x", "0.12,inf", "0,0.2", ""])
def test_radio_ranges_that_are_not_finite_positive_numbers_are_an_error(ranges, capsys):
    done = run_script(capsys, "--ranges", ranges, "--policy",
                      str(SCRIPT.parents[1] / "pretrained" / "scale"))
    assert done.returncode == 2
    assert f"--ranges {ranges}: allowed a comma-separated list of finite positive" in done.stderr


def test_ranges_need_the_policy_among_the_range_planners(capsys):
    done = run_script(capsys, "--ranges", "0.12", "--policy",
                      str(SCRIPT.parents[1] / "pretrained" / "scale"), "--range-planners", "nbv")
    assert done.returncode == 2
    assert "--ranges compares the policy with relay" in done.stderr


@pytest.mark.slow  # two evaluations: about a minute
def test_ranges_print_each_range_and_the_ratio_of_their_own_figures(tmp_path):
    figure = tmp_path / "ranges.png"
    done = subprocess.run([sys.executable, str(SCRIPT), "--teams", "3", "--size", "30",
                           "--ranges", "0.3,0.15", "--worlds", "2", "--policy",
                           str(SCRIPT.parents[1] / "pretrained" / "default"),
                           "--global-planners", "nbv", "--figure", str(figure)],
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    lines = {r["name"]: r for r in map(json.loads, done.stdout.splitlines())}
    assert set(lines) == {"scale.range.policy.single_hop.r0.15", "scale.range.policy.relay.r0.15",
                          "scale.range.policy.single_hop.r0.3", "scale.range.policy.relay.r0.3",
                          "scale.range.nbv.global", "scale.range.relay_vs_best_global.r0.15",
                          "scale.range.relay_vs_best_global.r0.3", "scale.command",
                          "scale.rules"}
    # The rules name each sweep's settings: relay on, both ranges, the policy alone.
    relay = lines["scale.rules"]["value"]["sweeps"]["relay"]
    assert {"radio.relay=true", "eval.radio_ranges=[0.15, 0.3]", "eval.planners=[policy]",
            "eval.worlds=2"} <= set(relay)
    for rho in ("0.15", "0.3"):
        ratio = lines[f"scale.range.relay_vs_best_global.r{rho}"]
        assert math.isclose(ratio["value"], lines[f"scale.range.policy.relay.r{rho}"]["value"]
                            / lines["scale.range.nbv.global"]["value"], rel_tol=1e-3)
        assert ratio["best_global"] == "nbv" and 0 <= ratio["p"] <= 1
    assert figure.stat().st_size > 0


def test_ranges_figures_come_from_the_runs_of_each_range(tmp_path, monkeypatch, capsys):
    """--ranges' lines and ratios from hand-made runs (the sweep itself is the slow test's):
    each relay range over the best global planner, with Welch's p by scipy."""
    scale = _scale_module()
    found = {("policy", "relay", 64, 0.12): [95.0, 96.0, 97.0],
             ("policy", "relay", 64, 0.25): [98.5, 99.0, 99.5],
             ("policy", "single_hop", 64, 0.12): [94.0, 95.0, 95.5],
             ("policy", "global", 64, float("inf")): [98.0, 98.5, 98.6],
             ("nbv", "global", 64, float("inf")): [98.8, 99.0, 98.9]}
    runs = {key: SimpleNamespace(planner=key[0], discovered=np.asarray(v))
            for key, v in found.items()}
    monkeypatch.setattr(scale, "sweep_exchanges", lambda *args: runs)
    figure = tmp_path / "ranges.png"
    scale.evaluate_ranges(Path("unused"), 64, 125, [0.12, 0.25], 3, [], figure)
    lines = {r["name"]: r for r in map(json.loads, capsys.readouterr().out.splitlines())}
    assert lines["scale.range.policy.single_hop.r0.12"]["value"] == pytest.approx(94.8333, abs=1e-3)
    assert lines["scale.range.nbv.global"]["std"] == pytest.approx(0.1)
    assert "scale.range.policy.single_hop.r0.25" not in lines
    for rho in ("0.12", "0.25"):
        relay = found["policy", "relay", 64, float(rho)]
        ratio = lines[f"scale.range.relay_vs_best_global.r{rho}"]
        assert ratio["value"] == pytest.approx(np.mean(relay) / 98.9, abs=1e-4)
        assert ratio["best_global"] == "nbv"
        p = stats.ttest_ind(relay, found["nbv", "global", 64, float("inf")], equal_var=False).pvalue
        assert ratio["p"] == pytest.approx(p, rel=1e-2)
    assert figure.stat().st_size > 0


def test_tight_cell_is_the_eval_cell_at_the_tight_budget(monkeypatch, capsys):
    """--tight: the --eval cell's sweeps at the per-robot budget TIGHT_BUDGET (below the
    paper's 10 / 3), every figure's name ending in _tight."""
    scale = _scale_module()
    budget = scale.TIGHT_BUDGET
    assert budget < scale.PER_ROBOT_BUDGET
    search = json.loads((SCRIPT.parents[1] / "docs" / "results" / "scale_tight_search" /
                         "summary.json").read_text())["summary"]
    # the search it was read from: nbv_team with global communication, 64 robots in the
    # 16x world, finds 50-80% of the windows at that budget
    (row,) = [r for r in search if math.isclose(r["budget"], 64 * budget)]
    assert (row["planner"], row["n_robots"], row["world_size"]) == ("nbv_team", 64, 125)
    assert 50 <= row["mean"] <= 80
    sweeps = {}
    found = {("policy", "relay", 64): [60.0, 62.0], ("policy", "single_hop", 64): [55.0, 57.0],
             ("nbv_team", "global", 64): [70.0, 72.0], ("nbv", "global", 64): [66.0, 68.0]}

    def fake(policy, settings):
        sweeps.update(settings)
        return {(*key, 0.12): SimpleNamespace(discovered=np.asarray(v))
                for key, v in found.items()}

    monkeypatch.setattr(scale, "sweep_exchanges", fake)
    scale.evaluate_cell(Path("unused"), 64, 125, 0.12, 2, [], budget=budget, tag="_tight")
    assert all(f"eval.budgets=[{budget:.8g}]" in settings for settings in sweeps.values())
    lines = {r["name"]: r for r in map(json.loads, capsys.readouterr().out.splitlines())}
    ratio = lines["scale.relay_vs_best_global_16x_tight"]
    assert ratio["value"] == pytest.approx(61.0 / 71.0, abs=1e-4)
    assert ratio["best_global"] == "nbv_team"
    assert lines["scale.pct.nbv.global_tight"]["value"] == pytest.approx(67.0)
    assert "scale.relay_vs_best_global_p_tight" in lines
    assert not any(name.startswith("scale.pct.") and not name.endswith("_tight")
                   for name in lines)


def test_tight_without_eval_is_an_error(capsys):
    done = run_script(capsys, "--tight")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip() == ("error: --tight: allowed only with --eval (it sets the "
                                   "--eval cell's budget)")
