"""Evaluation sweeps described by a config's `eval:` section, and the files they write.

A sweep crosses planners x team sizes x world sizes x radio ranges x budgets; every cell
(a `Shape`) runs `worlds x trials` episodes per planner, on worlds drawn from fixed seeds
so every planner sees the same worlds. Cells with the same team and world size differ
only in dynamic parameters (radio range, budget), so per planner they are traced and
compiled once and run as one vmapped call over their stacked `DynamicParams` (in
memory-sized chunks of the compiled shape; `cells.run_shapes`). `run_sweep` returns a
`SweepResult`; `outputs.write_outputs` puts a paper-style markdown table, CSV / JSON of
every run, comparisons paired by world and plots in a folder. `eval.py` is the
command-line front end.

EvalConfig fields read beyond the base ones (defaults in planners.EVAL_DEFAULTS while
jaxmripp.config does not define them):
- budget_mode: "team" (eval.budgets are team budgets B, split evenly) or "per_robot"
  (eval.budgets are per-robot budgets; the team gets N times as much);
- zip_with_size: names among radio_ranges, budgets, team_sizes whose i-th entry goes with
  the i-th world size instead of being crossed with all of them (protocol_scale pairs
  rho = 0.2 / 0.15 / 0.12 with G = 75 / 100 / 125);
- pairs: "a:b" planner pairs to compare in every shape, paired by world
  (`stats.paired_by_world`; default: the first planner against each other one);
- batch: episodes per vmapped call (0: sized to memory, cells.auto_batch);
- time_planning: also time planner.act alone; render: pictures and GIFs;
- coordinated_kappa / _lambda / _mu, nbv_facade, nbv_team_facade, mcts_simulations /
  _depth / _considered / _kappa and rig_iterations / _depth / _kappa: the baselines' knobs
  (see baselines.coordinated_planner, nbv_planner, tree_search, rig).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Callable, Sequence

from jaxmripp.config import REFERENCES, Config
from jaxmripp.evaluation import cells, evaluate
from jaxmripp.sim.episode import Planner
from jaxmripp.sim.params import StaticAhead, StaticBelief
from jaxmripp.evaluation.cells import SAFETY_COUNTS, Shape, ShapeRun, safety_columns
from jaxmripp.evaluation.planners import baseline_planner, deployed, eval_setting
from jaxmripp.evaluation.stats import mean_ci, paired_by_world
from jaxmripp.parallel import progress as progressmod

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
                    **{name: int(count[e]) for name, count in r.safety.items()},
                    "distance": round(float(r.distance[e]), 6), "contacts": int(r.contacts[e]),
                })
        return rows

    def summary(self) -> list[dict]:
        rows = []
        for r in self.runs:
            mean, std, half = mean_ci(r.discovered)
            rows.append({
                "planner": r.planner, "n_robots": r.shape.n_robots, "world_size": r.shape.size,
                "radio_range": _num(r.shape.radio_range), "budget": r.shape.budget,
                "runs": len(r.discovered), "mean": mean, "std": std,
                "ci95": [mean - half, mean + half],
                "plan_ms_per_robot_step": _num(r.plan_ms_per_robot_step),
                "step_ms_per_robot_step": r.ms_per_robot_step,
                **{name: float(count.mean()) for name, count in r.safety.items()},
                "compile_s": r.compile_s, "compiled_with_cells": r.cells, "run_s": r.run_s,
            })
        return rows

    def ttests(self) -> list[dict]:
        rows = []
        for shape in self.shapes():
            runs = self.of(shape)
            for a, b in self.pairs:
                if a in runs and b in runs:
                    test = paired_by_world(runs[a].discovered, runs[b].discovered,
                                           runs[a].worlds)
                    rows.append({"shape": shape.label(), "a": a, "b": b,
                                 "mean_a": float(runs[a].discovered.mean()),
                                 "mean_b": float(runs[b].discovered.mean()), **test})
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
            out += [head + " " + safety_columns(), rule + "---|" * len(SAFETY_COUNTS)]
            for name, r in runs.items():
                mean, std, half = mean_ci(r.discovered)
                label = f"{name} (reference)" if name in REFERENCES else name
                row = f"| {label} | {mean:.2f} +- {std:.2f} | [{mean - half:.2f}, {mean + half:.2f}] |"
                if timing:
                    row += f" {_ms(r.plan_ms_per_robot_step)} | {_ms(r.ms_per_robot_step)} |"
                row += " " + safety_columns(r.safety)
                out.append(row)
            out.append("")
        tests = self.ttests()
        if tests:
            out += ["### Paired by world (% targets; t-test and Wilcoxon over the per-world "
                    "means)", "",
                    "| shape | A | B | mean A | mean B | A - B [95% CI] | d_z | t | df | p | "
                    "p (Wilcoxon) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
            for t in tests:
                out.append(f"| {t['shape']} | {t['a']} | {t['b']} | {t['mean_a']:.2f} | "
                           f"{t['mean_b']:.2f} | {t['diff']:+.2f} [{t['ci'][0]:+.2f}, "
                           f"{t['ci'][1]:+.2f}] | {t['dz']:.2f} | {t['t']:.3f} | {t['df']} | "
                           f"{t['p']:.3g} | {t['p_wilcoxon']:.3g} |")
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
    """Runs every planner on every shape of cfg.eval, one compilation per planner and
    (team size, world size); prints one progress line per cell and planner, under a bar
    with the time left on a terminal (`parallel.progress`)."""
    policies = dict(policies or {})
    e = cfg.eval
    names = planner_names(cfg, policies)
    if "policy" in e.planners and not policies:
        log("note: eval.planners lists 'policy' but no --policy was given; baselines only")
    time_planning = eval_setting(cfg, "time_planning") if time_planning is None else time_planning
    batch = eval_setting(cfg, "batch") if batch is None else batch
    shapes = shapes_of(cfg)
    runs = []
    with _Progress(log, len(shapes) * len(names)) as progress:
        for group in static_groups(shapes):
            runs += _run_group(cfg, group, names, policies, progress, time_planning,
                               batch=batch, keep_pictures=keep_pictures,
                               compiler_options=compiler_options)
    # Shape-major, planners in order within a shape, as the tables and files list them.
    order = {shape: i for i, shape in enumerate(shapes)}
    runs.sort(key=lambda r: (order[r.shape], names.index(r.planner)))
    pairs = default_pairs(names, eval_setting(cfg, "pairs"))
    for a, b in pairs:
        missing = [x for x in (a, b) if x not in names]
        if missing:
            log(f"note: t-test {a}:{b} skipped: no planner named {', '.join(missing)}")
    return SweepResult(runs, pairs)


def _run_group(cfg: Config, group: list[Shape], names: list[str],
               policies: dict[str, Planner], progress: "_Progress", time_planning: bool,
               compiler_options: dict | None = None, **options) -> list[ShapeRun]:
    """Every planner on the cells of one team and world size: one compilation each."""
    e = cfg.eval
    n, size = group[0].n_robots, group[0].size
    params = evaluate.eval_params(cfg, [s.budget for s in group], layout=e.layout,
                                  robots=n, size=size)
    dynamics = [evaluate.eval_dynamic(cfg, s.budget, s.radio_range) for s in group]
    # Only the policies read the lookahead and belief inputs (policy.ahead_*, belief_*, set
    # for them by pipeline.with_policy_inputs); the baselines' environments skip them.
    plain = dataclasses.replace(params, ahead=StaticAhead(), belief=StaticBelief())
    runs = []
    for name in names:
        planner_params = params if name in policies else plain
        planner = deployed(policies.get(name) or baseline_planner(name, plain, e), e.sectors)
        group_runs = cells.run_shapes(planner, planner_params, group, dynamics, e.seed,
                                      e.worlds, e.trials, compiler_options=compiler_options,
                                      **options)
        if time_planning:
            ms, compile_s = cells.time_planning(planner, planner_params, dynamics, e.seed,
                                                compiler_options=compiler_options)
            for run, plan_ms in zip(group_runs, ms):
                run.plan_ms_per_robot_step = plan_ms
                run.compile_s += compile_s
        for run in group_runs:
            progress.cell(run)
        runs += group_runs
    return runs


def static_groups(shapes: Sequence[Shape]) -> list[list[Shape]]:
    """Shapes grouped by what is static (team size, world size), in order of appearance."""
    groups: dict[tuple[int, int], list[Shape]] = {}
    for shape in shapes:
        groups.setdefault((shape.n_robots, shape.size), []).append(shape)
    return list(groups.values())


class _Progress:
    """One log line per finished cell and planner, above a bar over them all."""

    def __init__(self, log: Callable[[str], None], total: int):
        self.log, self.total, self.done = progressmod.above(log), total, 0
        self.bar = progressmod.bar(total, "sweep", unit="cell")

    def __enter__(self) -> "_Progress":
        return self

    def __exit__(self, *_) -> None:
        self.bar.close()

    def cell(self, run: ShapeRun) -> None:
        self.done += 1
        self.bar.update(1)
        mean, std, _ = mean_ci(run.discovered)
        shared = f" (shared by {run.cells} cells)" if run.cells > 1 else ""
        plan = ("" if not math.isfinite(run.plan_ms_per_robot_step)
                else f", plan {run.plan_ms_per_robot_step:.3f} ms/robot-step")
        self.log(f"[{self.done}/{self.total}] {run.planner:<12} {run.shape.label()}: "
                 f"compile {run.compile_s:.1f} s{shared}, run {run.run_s:.1f} s "
                 f"({run.ms_per_robot_step:.3f} ms/robot-step{plan}) -> "
                 f"{mean:.2f} +- {std:.2f} % targets")


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
    for key in ("reward.utility_norm", "world.target_placement", "radio.share_maps"):
        section, field = key.split(".")
        a, b = getattr(getattr(run_cfg, section), field), getattr(getattr(cfg, section), field)
        if a != b:
            notes.append(f"{key}={a} (evaluating with {b})")
    return notes
