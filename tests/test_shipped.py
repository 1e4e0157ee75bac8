"""The shipped policies (pretrained/*): every figure their metadata.json gives comes from a
file a command wrote, and the default policy plans better than the simple planners. The
same holds of the alternatives measured that no longer ship (docs/results/alternatives/*:
their metadata.json, config.yaml and result files, without the weights).

metadata.json is written by `python -m jaxmripp.ship` (or `--metadata` from the folder's
own files); each check below reads the source files itself.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from jaxmripp import config as cfgmod, demo
from jaxmripp.config import presets

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p.name for p in (REPO / "pretrained").iterdir() if p.is_dir())
ALTERNATIVES = REPO / "docs" / "results" / "alternatives"
MEASURED = [REPO / "pretrained" / name for name in SHIPPED] + sorted(
    p for p in ALTERNATIVES.iterdir() if p.is_dir())
NOT_FIGURES = (".command", ".rules", ".train_minutes")  # ship.py's; checked separately


def lines(path: Path) -> dict[str, object]:
    """name -> value of a benchmark's JSON lines."""
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {r["name"]: r["value"] for r in records}


@pytest.mark.parametrize("name", SHIPPED)
def test_training_figures_are_the_folders_own(name):
    """Minutes, updates and steps are those of the folder's metrics.jsonl; the command
    trains with a config that loads to the folder's config.yaml; init_from is its own."""
    folder = REPO / "pretrained" / name
    meta = json.loads((folder / "metadata.json").read_text())
    records = [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()
               if line.strip()]
    assert meta["train_minutes"] == round(sum(r["seconds"] for r in records) / 60, 1)
    assert meta["updates"] == records[-1]["update"]
    assert meta["agent_steps"] == records[-1]["env_steps"]
    cfg = cfgmod.load(folder / "config.yaml")
    # The last chunk's records (one per update, or one for the chunk), episodes weighted.
    first = records[-1]["update"] - cfg.train.updates_per_chunk
    last = [r for r in records if r["update"] > first]
    ended = sum(r.get("episodes", 1) for r in last)
    found = sum(r["discovered"] * r.get("episodes", 1) for r in last)
    assert meta["training_discovered"] == round(found / ended, 4)
    prefix = "jaxmripp train --config "
    assert meta["command"].startswith(prefix)
    # a preset's name or a path, then the seed and start as overrides
    source, *overrides = meta["command"][len(prefix):].split()
    trained = cfgmod.load(source if presets.is_name(source) else REPO / source, overrides)
    # but for train.name, which only names the run's folder
    assert dataclasses.replace(trained, train=dataclasses.replace(
        trained.train, name=cfg.train.name)) == cfg
    assert meta.get("init_from", "") == cfg.train.init_from
    header = json.loads((folder / "policy.json").read_text())
    assert meta["checkpoint"] == header["source"]["checkpoint"]


def test_four_policies_ship_and_the_others_keep_their_figures():
    assert SHIPPED == ["default", "default_fast", "paper", "scale"]
    for folder in ALTERNATIVES.iterdir():
        assert sorted(p.name for p in folder.iterdir()) == sorted(
            ["config.yaml", "metadata.json", "quality.jsonl" if (folder / "quality.jsonl")
             .is_file() else "scale.jsonl"]), folder.name
        assert not (REPO / "pretrained" / folder.name).exists()
        evaluations = json.loads((folder / "metadata.json").read_text())["evaluations"]
        assert {(REPO / e["results"]).parent for e in evaluations} == {folder}


@pytest.mark.parametrize("folder", MEASURED, ids=lambda path: path.name)
def test_every_evaluation_figure_is_in_the_result_file_it_names(folder):
    """Each evaluation names a committed result file; its command, rules and figures are
    that file's, and the command evaluated this folder's policy. A file printed before
    benchmarks named their command and rules has them in what the same run's --out wrote
    beside it (results.md's command, summary.json's sweep settings), whose means are the
    file's figures."""
    meta = json.loads((folder / "metadata.json").read_text())
    assert meta["evaluations"], "no evaluation figures"
    for evaluation in meta["evaluations"]:
        path = REPO / evaluation["results"]
        found = lines(path)
        figures = {k: v for k, v in found.items() if not k.endswith(NOT_FIGURES)}
        assert evaluation["figures"] == figures
        commands = [v for k, v in found.items() if k.endswith(".command")] or [
            line[len("Command: `"):-1] for line in
            (path.parent / "results.md").read_text().splitlines()
            if line.startswith("Command: `")]
        assert commands == [evaluation["command"]]
        rules = [v for k, v in found.items() if k.endswith(".rules")]
        if not rules:
            summary = json.loads((path.parent / "summary.json").read_text())
            rules = [{"eval": summary["eval"]}]
            for row in summary["summary"]:
                figure = f"quality.pct.{row['planner']}.rho{float(row['radio_range']):g}"
                assert figures[figure] == pytest.approx(row["mean"], abs=1e-4)
        assert rules == [evaluation["rules"]]
        command = evaluation["command"].split()
        # the policy whose figures these are: --policy's, --seeds' first, or the preset's
        given = next((command[command.index(o) + 1] for o in ("--policy", "--seeds")
                      if o in command), None)
        policy = given or f"pretrained/{command[command.index('--preset') + 1]}"
        assert policy == f"pretrained/{folder.name}"  # where it was when evaluated


def test_rules_of_a_quality_result_name_its_worlds_and_trials():
    """The rules recorded with the README's figures of pretrained/default_fast: the
    protocol's 25 worlds x 10 trials at both radio ranges."""
    meta = json.loads((REPO / "pretrained/default_fast/metadata.json").read_text())
    rules = meta["evaluations"][0]["rules"]
    assert (rules["worlds"], rules["trials"], rules["config"]) == (
        25, 10, "configs/protocol_table1.yaml")
    assert "eval.radio_ranges=[.inf, 0.1]" in rules["overrides"]


# The worlds (demo seeds) of the quick check; measured at B = 10: policy 63.6, 48.8 and
# 47.6% of the windows, greedy 27.2, 32.8 and 20.0, random 28.0, 19.6 and 17.2.
WORLDS = (1, 2, 3)


def test_the_default_policy_finds_more_than_random_and_greedy_in_each_world(capsys):
    """pretrained/default flown by the onboard runtime (python -m jaxmripp.demo: 3 robots,
    B = 10, a random-layout world per seed) against the runtime's greedy and random modes
    on the same worlds, from the same start: it finds more in every world."""
    found = {planner: [demo.main(["--export", str(REPO / "pretrained/default"), "--planner",
                                  planner, "--seed", str(seed), "--budget", "10", "--quiet"]).percent
                       for seed in WORLDS]
             for planner in ("policy", "greedy", "random")}
    capsys.readouterr()
    for i, seed in enumerate(WORLDS):
        assert found["policy"][i] > max(found["greedy"][i], found["random"][i]), (seed, found)
