"""Evaluation sweeps described by a config's `eval:` section, and the files they write.

A sweep crosses planners x team sizes x world sizes x radio ranges x budgets; every cell
(a `Shape`) runs `worlds x trials` episodes per planner in one jitted, vmapped call (in
memory-sized chunks of the same compiled shape), on worlds drawn from fixed seeds so
every planner sees the same worlds. `run_sweep` returns a `SweepResult`; `write_outputs`
puts a paper-style markdown table, CSV / JSON of every run, Welch t-tests and plots in a
folder. `eval.py` is the command-line front end.

EvalConfig fields read beyond the base ones (defaults in evaluate.EVAL_DEFAULTS while
jaxmripp.config does not define them):
- budget_mode: "team" (eval.budgets are team budgets B, split evenly) or "per_robot"
  (eval.budgets are per-robot budgets; the team gets N times as much);
- zip_with_size: names among radio_ranges, budgets, team_sizes whose i-th entry goes with
  the i-th world size instead of being crossed with all of them (the scale preset pairs
  rho = 0.2 / 0.15 / 0.12 with G = 75 / 100 / 125);
- pairs: "a:b" planner pairs to compare with Welch's t-test in every shape (default: the
  first planner against each other one);
- batch: episodes per vmapped call (0: sized to memory, evaluate.auto_batch);
- time_planning: also time planner.act alone; render: pictures and GIFs;
- coordinated_kappa / _lambda / _mu and mcts_simulations / _depth / _considered / _kappa:
  the baselines' knobs (see baselines.coordinated_planner, tree_search).
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from jaxmripp.evaluation import evaluate
from jaxmripp.evaluation.baselines import Planner
from jaxmripp.config import Config
from jaxmripp.evaluation.evaluate import Shape, ShapeRun, eval_setting

# Table I of the paper (design.md section 1): N = 3, B = 10, G = 50, 25 worlds x 10 trials.
PUBLISHED = [
    ("paper's approach", "inf", "66.00 +- 5.59", "1.58"),
    ("paper's approach", "0.1", "62.16 +- 8.25", "1.58"),
    ("Intent (destination modelling)", "inf", "52.31 +- 9.29", "25.39"),
    ("CAtNIPP greedy", "inf", "45.31 +- 10.59", "3.84"),
    ("MCTS, sequential allocation", "inf", "48.50 +- 7.81", "153.49"),
    ("RIG-tree, sequential allocation", "inf", "47.38 +- 10.43", "60.46"),
    ("random", "inf", "31.83 +- 15.23", "0.06"),
]


def shapes_of(cfg: Config) -> list[Shape]:
    """The sweep's cells in order: world size, team size, radio range, budget."""
    e = cfg.eval
    axes = {"team_sizes": list(e.team_sizes), "radio_ranges": list(e.radio_ranges),
            "budgets": list(e.budgets)}
    zipped = tuple(eval_setting(cfg, "zip_with_size"))
    for name in zipped:
        if name not in axes:
            raise ValueError(f"eval.zip_with_size: got {name!r}; allowed: team_sizes, "
                             "radio_ranges, budgets")
        if len(axes[name]) != len(e.world_sizes):
            raise ValueError(f"eval.{name}: {len(axes[name])} entries cannot pair with "
                             f"{len(e.world_sizes)} world_sizes (eval.zip_with_size)")
    per_robot = eval_setting(cfg, "budget_mode") == "per_robot"
    shapes = []
    for i, size in enumerate(e.world_sizes):
        pick = {k: ([v[i]] if k in zipped else v) for k, v in axes.items()}
        for n, rho, b in itertools.product(pick["team_sizes"], pick["radio_ranges"],
                                           pick["budgets"]):
            shapes.append(Shape(int(n), int(size), float(rho), float(b * n if per_robot else b)))
    return shapes


def planner_names(cfg: Config, policies: dict[str, Planner]) -> list[str]:
    """eval.planners with "policy" replaced by every given policy (or dropped if none);
    given policies are always evaluated, first when "policy" is not listed."""
    names = []
    for name in cfg.eval.planners:
        names.extend(policies if name == "policy" else [name])
    missing = [p for p in policies if p not in names]
    return list(dict.fromkeys(missing + names))


@dataclasses.dataclass
class SweepResult:
    runs: list[ShapeRun]
    pairs: list[tuple[str, str]]

    def shapes(self) -> list[Shape]:
        return list(dict.fromkeys(r.shape for r in self.runs))

    def of(self, shape: Shape) -> dict[str, ShapeRun]:
        return {r.planner: r for r in self.runs if r.shape == shape}

    def records(self) -> list[dict]:
        """One row per episode (every planner, shape, world and trial)."""
        rows = []
        for r in self.runs:
            for e in range(len(r.discovered)):
                rows.append({
                    "planner": r.planner, "n_robots": r.shape.n_robots,
                    "world_size": r.shape.size, "radio_range": _num(r.shape.radio_range),
                    "budget": r.shape.budget, "world": e // r.trials, "trial": e % r.trials,
                    "discovered_pct": round(float(r.discovered[e]), 6),
                    "targets": int(r.targets[e]), "steps": int(r.steps[e]),
                    "obstacle_collisions": int(r.obstacle_collisions[e]),
                    "robot_collisions": int(r.robot_collisions[e]),
                    "distance": round(float(r.distance[e]), 6), "contacts": int(r.contacts[e]),
                })
        return rows

    def summary(self) -> list[dict]:
        rows = []
        for r in self.runs:
            mean, std, half = evaluate.mean_ci(r.discovered)
            rows.append({
                "planner": r.planner, "n_robots": r.shape.n_robots, "world_size": r.shape.size,
                "radio_range": _num(r.shape.radio_range), "budget": r.shape.budget,
                "runs": len(r.discovered), "mean": mean, "std": std,
                "ci95": [mean - half, mean + half],
                "plan_ms_per_robot_step": _num(r.plan_ms_per_robot_step),
                "step_ms_per_robot_step": r.ms_per_robot_step,
                "obstacle_collisions": float(r.obstacle_collisions.mean()),
                "robot_collisions": float(r.robot_collisions.mean()),
                "compile_s": r.compile_s, "run_s": r.run_s,
            })
        return rows

    def ttests(self) -> list[dict]:
        rows = []
        for shape in self.shapes():
            runs = self.of(shape)
            for a, b in self.pairs:
                if a in runs and b in runs:
                    t, df, p = evaluate.welch_ttest(runs[a].discovered, runs[b].discovered)
                    rows.append({"shape": shape.label(), "a": a, "b": b,
                                 "mean_a": float(runs[a].discovered.mean()),
                                 "mean_b": float(runs[b].discovered.mean()),
                                 "t": t, "df": df, "p": p})
        return rows

    def table(self, timing: bool = True) -> str:
        """Markdown: one Table-I-style block per shape, then the t-tests."""
        out = []
        for shape in self.shapes():
            runs = self.of(shape)
            first = next(iter(runs.values()))
            out += [f"### {shape.label()}: {first.worlds} worlds x {first.trials} trials", ""]
            head = "| planner | % targets | 95% CI |"
            rule = "|---|---|---|"
            if timing:
                head += " plan ms / robot-step | sim+plan ms / robot-step |"
                rule += "---|---|"
            out += [head + " obstacle coll. | robot coll. |", rule + "---|---|"]
            for name, r in runs.items():
                mean, std, half = evaluate.mean_ci(r.discovered)
                row = f"| {name} | {mean:.2f} +- {std:.2f} | [{mean - half:.2f}, {mean + half:.2f}] |"
                if timing:
                    row += f" {_ms(r.plan_ms_per_robot_step)} | {_ms(r.ms_per_robot_step)} |"
                row += (f" {r.obstacle_collisions.mean():.2f} |"
                        f" {r.robot_collisions.mean():.2f} |")
                out.append(row)
            out.append("")
        tests = self.ttests()
        if tests:
            out += ["### Welch t-tests (% targets)", "",
                    "| shape | A | B | mean A | mean B | A - B | t | df | p |",
                    "|---|---|---|---|---|---|---|---|---|"]
            for t in tests:
                out.append(f"| {t['shape']} | {t['a']} | {t['b']} | {t['mean_a']:.2f} | "
                           f"{t['mean_b']:.2f} | {t['mean_a'] - t['mean_b']:+.2f} | "
                           f"{t['t']:.3f} | {t['df']:.1f} | {t['p']:.3g} |")
            out.append("")
        return "\n".join(out)


def _num(x: float):
    """JSON-safe float: inf / nan become strings."""
    return x if math.isfinite(x) else str(x)


def _ms(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{x:.3f}"


def default_pairs(names: Sequence[str], configured: Sequence[str]) -> list[tuple[str, str]]:
    pairs = []
    for text in configured:
        a, sep, b = text.partition(":")
        if not sep or not a or not b:
            raise ValueError(f"eval.pairs: got {text!r}; allowed: 'planner_a:planner_b'")
        pairs.append((a.strip(), b.strip()))
    if not pairs and names:
        pairs = [(names[0], other) for other in names[1:]]
    return pairs


def run_sweep(cfg: Config, policies: dict[str, Planner] | None = None,
              log: Callable[[str], None] = print, *, time_planning: bool | None = None,
              batch: int | None = None, keep_pictures: bool = True,
              compiler_options: dict | None = None) -> SweepResult:
    """Runs every planner on every shape of cfg.eval; prints one progress line per cell."""
    policies = dict(policies or {})
    e = cfg.eval
    names = planner_names(cfg, policies)
    if "policy" in e.planners and not policies:
        log("note: eval.planners lists 'policy' but no --policy was given; baselines only")
    time_planning = eval_setting(cfg, "time_planning") if time_planning is None else time_planning
    batch = eval_setting(cfg, "batch") if batch is None else batch
    shapes = shapes_of(cfg)
    runs = []
    cells = len(shapes) * len(names)
    for s_i, shape in enumerate(shapes):
        params = evaluate.eval_params(cfg, shape.budget, layout=e.layout, robots=shape.n_robots,
                                      radio_range=shape.radio_range, size=shape.size)
        for p_i, name in enumerate(names):
            planner = policies.get(name) or evaluate.baseline_planner(name, params, e)
            run = evaluate.run_shape(planner, params, shape, e.seed, e.worlds, e.trials,
                                     batch=batch, keep_pictures=keep_pictures,
                                     compiler_options=compiler_options)
            plan = ""
            if time_planning:
                ms, compile_s = evaluate.time_planning(planner, params, e.seed,
                                                       compiler_options=compiler_options)
                run.plan_ms_per_robot_step = ms
                run.compile_s += compile_s
                plan = f", plan {ms:.3f} ms/robot-step"
            mean, std, _ = evaluate.mean_ci(run.discovered)
            log(f"[{s_i * len(names) + p_i + 1}/{cells}] {name:<12} {shape.label()}: "
                f"compile {run.compile_s:.1f} s, run {run.run_s:.1f} s "
                f"({run.ms_per_robot_step:.3f} ms/robot-step{plan}) -> "
                f"{mean:.2f} +- {std:.2f} % targets")
            runs.append(run)
    pairs = default_pairs(names, eval_setting(cfg, "pairs"))
    for a, b in pairs:
        missing = [x for x in (a, b) if x not in names]
        if missing:
            log(f"note: t-test {a}:{b} skipped: no planner named {', '.join(missing)}")
    return SweepResult(runs, pairs)


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
        first = result.shapes()[0]
        for name, run in result.of(first).items():
            if run.snapshot is None:
                continue
            paths[f"episode_{name}"] = eval_plots.episode_picture(
                out / f"episode_{name}.png", run, 0)
            if gif:
                paths[f"gif_{name}"] = eval_plots.episode_gif(out / f"episode_{name}.gif", run, 0)
    return paths


def _jsonable(v):
    if isinstance(v, float):
        return _num(v)
    if isinstance(v, (tuple, list)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return _jsonable(v.item())
    return v


def policy_mismatches(run_cfg: Config, cfg: Config) -> list[str]:
    """Settings that shape a policy's observations and differ between its training run
    and this evaluation (the evaluation's values are used for every planner)."""
    notes = []
    for section in ("sensor", "candidates", "gp"):
        ours, theirs = getattr(cfg, section), getattr(run_cfg, section)
        for field in dataclasses.fields(ours):
            if field.name == "shared_utility":  # evaluation always uses per-robot GPs
                continue
            a, b = getattr(theirs, field.name), getattr(ours, field.name)
            if a != b:
                notes.append(f"{section}.{field.name}={a} (evaluating with {b})")
    for key in ("reward.utility_norm", "world.target_placement"):
        section, field = key.split(".")
        a, b = getattr(getattr(run_cfg, section), field), getattr(getattr(cfg, section), field)
        if a != b:
            notes.append(f"{key}={a} (evaluating with {b})")
    return notes
