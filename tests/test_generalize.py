"""benchmarks/generalize.py: its 12 cells are the settings the issue of record names, on
seeds no other protocol uses, and bad arguments are one error line."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scripts import load_script

ROOT = Path(__file__).resolve().parents[1]


def _module():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return load_script("benchmarks/generalize.py")


def test_cells_shift_the_table_i_setting_as_named():
    gen = _module()
    cfgs = {name: gen.cell_config(name, ["policy", "nbv_team"], 10, 5, []) for name in gen.CELLS}
    assert len(cfgs) == 12
    d = {name: (c.world.buildings, (c.world.footprint_min, c.world.footprint),
                c.eval.budgets, c.eval.team_sizes, c.eval.radio_ranges, c.eval.layout)
         for name, c in cfgs.items()}
    default = (25, (0, 3), (10.0,), (3,), (math.inf,), "random")
    assert d["grid"] == default[:5] + ("grid",)
    assert d["n6"] == (25, (0, 3), (20.0,), (6,), (math.inf,), "random")
    assert d["dense_short"] == (40, (2, 5), (7.0,), (6,), (0.1,), "random")
    assert d["sparse_pair"] == (15, (2, 5), (14.0,), (2,), (math.inf,), "grid")
    assert d["dense_long"] == (40, (2, 5), (14.0,), (3,), (0.3,), "random")
    # every cell differs from the default setting, and no two cells are the same setting
    assert default not in d.values() and len(set(d.values())) == 12
    seeds = {c.eval.seed for c in cfgs.values()}
    assert len(seeds) == 12 and not seeds & {1000, 2000}  # quality.py and scale.py use these
    assert {(c.eval.worlds, c.eval.trials) for c in cfgs.values()} == {(10, 5)}


def test_cell_figures_pick_the_best_classical_and_pair_by_world():
    gen = _module()
    worlds, trials = 4, 3
    rng = np.random.default_rng(0)
    world_effect = np.repeat(rng.normal(0, 5, worlds), trials)  # runs are world-major
    found = {p: 50 + world_effect + rng.normal(0, 1, worlds * trials) + shift
             for p, shift in [("policy", 2.0), ("nbv_targets", 0.5), ("nbv_ahead", 1.0),
                              ("nbv_team", -1.0), ("nbv", -3.0), ("random", -30.0)]}
    line = gen.cell_figures(found, worlds)
    assert line["best"] == "nbv_ahead"  # the largest mean among the classical planners
    assert line["value"] == pytest.approx(found["policy"].mean() / found["nbv_ahead"].mean())
    per_world = [found[p].reshape(worlds, trials).mean(axis=1) for p in ("policy", "nbv_ahead")]
    assert line["p"] == pytest.approx(stats.ttest_rel(*per_world).pvalue, rel=1e-2)
    assert not {"rate_ceiling_pct", "city_ceiling_pct"} & set(line)  # only where they ran
    # References never count as the best, however much they find.
    found |= {"oracle_rate": found["policy"] + 5, "oracle_city": found["policy"] + 9}
    line = gen.cell_figures(found, worlds)
    assert line["best"] == "nbv_ahead"
    assert line["city_ceiling_pct"] == pytest.approx(found["policy"].mean() + 9)
    assert line["rate_ceiling_pct"] == pytest.approx(found["policy"].mean() + 5)
    assert gen.geometric_mean([2.0, 8.0]) == pytest.approx(4.0)


def _cell_line(cell: str, **fields) -> dict:
    line = dict(name=f"generalize.cell.{cell}", value=1.02, policy_pct=51.0, best_pct=50.0,
                policy_sha256="ab", worlds=10, trials=5, overrides=[])
    return line | fields


def test_resume_reuses_only_cells_of_the_same_policy_and_protocol(tmp_path):
    gen = _module()
    identity = dict(policy_sha256="ab", worlds=10, trials=5, overrides=[])
    lines = [{"name": "generalize.command", "value": "python benchmarks/generalize.py"},
             _cell_line("n2"), _cell_line("n6", policy_sha256="cd"),
             _cell_line("grid", worlds=2), _cell_line("budget7", overrides=["x.y=1"]),
             _cell_line("budget14", rate_ceiling_pct=55.0),
             {"name": "generalize.geomean_ratio", "value": 1.02}]
    previous = tmp_path / "previous.jsonl"
    previous.write_text("".join(json.dumps(line) + "\n" for line in lines))
    assert set(gen.reusable_cells(previous, identity, ["policy_pct", "best_pct"])) == {
        "n2", "budget14"}
    assert set(gen.reusable_cells(previous, identity, ["policy_pct", "rate_ceiling_pct"])) == {
        "budget14"}
    previous.write_text(previous.read_text() + "compiling ...\n")
    with pytest.raises(gen.cfgmod.ConfigError, match="line 8"):
        gen.reusable_cells(previous, identity, [])


def test_resume_prints_a_measured_cell_again_and_sums_up_over_it(tmp_path, capsys,
                                                                  monkeypatch):
    from jaxmripp import pipeline
    from jaxmripp.learn.policy import flatten_params
    from jaxmripp.runtime.weights import weights_sha256

    monkeypatch.chdir(ROOT)
    sha = weights_sha256(flatten_params(pipeline.trained_params(ROOT / "pretrained/default")))
    measured = _cell_line("n2", policy_sha256=sha, worlds=3, trials=1, policy_pct=40.0,
                          best_pct=50.0, device="somewhere")
    previous = tmp_path / "previous.jsonl"
    previous.write_text(json.dumps(measured) + "\n")
    assert _module().main(["--cells", "n2", "--worlds", "3", "--trials", "1", "--resume",
                           str(previous), "--quiet"]) == 0
    printed = {r["name"]: r for r in map(json.loads, capsys.readouterr().out.splitlines())}
    assert printed["generalize.cell.n2"] == measured  # as it stands, not measured again
    assert printed["generalize.cells_won"]["value"] == 0
    assert printed["generalize.geomean_ratio"]["value"] == pytest.approx(0.8)


@pytest.mark.parametrize("arguments", [["--cells", "nope"], ["--worlds", "1"],
                                       ["--policy", "configs"], ["world.buildings=0"],
                                       ["--resume", "no/such/file.jsonl"]])
def test_bad_arguments_are_one_error_line(arguments, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    try:
        status = _module().main(arguments)
    except SystemExit as stop:  # usage mistakes leave through the argument parser
        status = stop.code
    assert status == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: "), err


@pytest.mark.slow
def test_one_cell_prints_its_figures():
    done = subprocess.run([sys.executable, "benchmarks/generalize.py", "--cells", "budget7",
                           "--worlds", "2", "--trials", "1", "--ceilings"], cwd=ROOT,
                          capture_output=True, text=True, check=True)
    figures = {r["name"]: r for r in map(json.loads, done.stdout.splitlines())}
    cell = figures["generalize.cell.budget7"]
    assert cell["value"] == pytest.approx(cell["policy_pct"] / cell["best_pct"], rel=1e-3)
    assert cell["best"] in ("nbv_targets", "nbv_ahead", "nbv_team", "nbv")
    assert figures["generalize.cells_won"]["value"] == int(cell["value"] > 1)
    for field in ("rate_ceiling", "city_ceiling"):
        assert figures[f"generalize.geomean_{field}_ratio"]["value"] == pytest.approx(
            cell[f"{field}_pct"] / cell["best_pct"], rel=1e-3)
