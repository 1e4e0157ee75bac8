"""The files an evaluation sweep writes: markdown table, CSV / JSON of every episode, a
JSON summary with the comparisons paired by world (`stats.paired_by_world`), and plots
(`write_outputs`)."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np

from jaxmripp.config import Config
from jaxmripp.evaluation.sweep import SweepResult, _num

# Table I of the paper (docs/design.md section 1): N = 3, B = 10, G = 50, 25 worlds x 10 trials.
PUBLISHED = [
    ("paper's approach", "inf", "66.00 +- 5.59", "1.58"),
    ("paper's approach", "0.1", "62.16 +- 8.25", "1.58"),
    ("Intent (destination modelling)", "inf", "52.31 +- 9.29", "25.39"),
    ("CAtNIPP greedy", "inf", "45.31 +- 10.59", "3.84"),
    ("MCTS, sequential allocation", "inf", "48.50 +- 7.81", "153.49"),
    ("RIG-tree, sequential allocation", "inf", "47.38 +- 10.43", "60.46"),
    ("random", "inf", "31.83 +- 15.23", "0.06"),
]



def write_outputs(result: SweepResult, out_dir: str | Path, cfg: Config | None = None,
                  render: bool = True, gif: bool = True, command: str = "") -> dict[str, Path]:
    """results.md, runs.csv, runs.json, summary.json and plots in out_dir; returns paths."""
    from jaxmripp.evaluation import plots as eval_plots  # noqa: PLC0415 (matplotlib only when writing)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    text = ["# Evaluation", ""]
    if command:
        text += ["Command: `" + command + "`", ""]
    text += ["Mean +- std of the % of the world's windows discovered; the CI is the 95% "
             "Student-t interval of the mean. Timings are per robot decision: *plan* is "
             "`planner.act` alone (vmapped over a few reset states), *sim+plan* a whole "
             "environment step (sensing, maps, GPs, radio, candidates) amortised over the "
             "vmapped batch. Collisions are per episode.", "", result.table()]
    if any(s.n_robots == 3 and s.size == 50 and s.budget == 10 for s in result.shapes()):
        text += ["### Published (Table I of the paper; its own simulator, seconds per step)", "",
                 "| planner | rho | % targets | s / step |", "|---|---|---|---|"]
        text += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in PUBLISHED]
        text.append("")
    paths["table"] = out / "results.md"
    paths["table"].write_text("\n".join(text) + "\n")

    records = result.records()
    paths["csv"] = out / "runs.csv"
    with paths["csv"].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(records[0]))
        writer.writeheader()
        writer.writerows(records)
    paths["json"] = out / "runs.json"
    paths["json"].write_text(json.dumps(records))
    summary = {"summary": result.summary(), "ttests": result.ttests()}
    if cfg is not None:
        summary["eval"] = {k: _jsonable(v) for k, v in dataclasses.asdict(cfg.eval).items()}
    paths["summary"] = out / "summary.json"
    paths["summary"].write_text(json.dumps(summary, indent=2, default=_jsonable))

    for i, shape in enumerate(result.shapes()):
        name = f"discovered_vs_budget_{i}.png"
        paths[name] = eval_plots.discovery_vs_budget(out / name, result.of(shape),
                                                     title=shape.label())
    if len({s.n_robots for s in result.shapes()}) > 1:
        paths["team_size"] = eval_plots.discovery_vs_team_size(
            out / "discovered_vs_team_size.png", result.runs)
    if render:
        for i, group in enumerate(_by_team_world_budget(result.runs)):
            if all(run.snapshot is not None for run in group):
                shape = group[0].shape
                paths[f"missed_windows_{i}.png"] = eval_plots.missed_map(
                    out / f"missed_windows_{i}.png", group,
                    title=f"windows never found: N = {shape.n_robots}, G = {shape.size}, "
                          f"B = {shape.budget:g}, {len(group[0].discovered)} episodes")
        first = result.shapes()[0]
        for name, run in result.of(first).items():
            if run.snapshot is None:
                continue
            paths[f"episode_{name}"] = eval_plots.episode_picture(
                out / f"episode_{name}.png", run, 0)
            if gif:
                paths[f"gif_{name}"] = eval_plots.episode_gif(out / f"episode_{name}.gif", run, 0)
    return paths


def _by_team_world_budget(runs: list) -> list[list]:
    """Runs grouped by (N, G, B), in sweep order: a group differs in planner and radio range."""
    groups: dict = {}
    for run in runs:
        groups.setdefault((run.shape.n_robots, run.shape.size, run.shape.budget), []).append(run)
    return list(groups.values())


def _jsonable(v):
    if isinstance(v, float):
        return _num(v)
    if isinstance(v, (tuple, list)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return _jsonable(v.item())
    return v
