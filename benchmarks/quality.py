"""Planning quality: the Table I protocol on a shipped (or given) policy and every
non-learning planner.

N = 3 robots, team budget B = 10, W held-out random-layout worlds x T trials, radio range
rho = inf and 0.1; planners: the policy, nbv_targets, nbv_ahead, nbv_team, nbv,
coordinated, greedy, mcts, rig, random, and three upper references that read the truth
(never "baselines"): the window oracle per unit of cost (oracle), the same looking a
flight ahead with claims heard only in radio range (oracle_ahead), and nbv_targets with
each building's true remaining windows (oracle_rate). Every planner runs the same worlds
and trials, so comparisons are paired by world (`jaxmripp.evaluation.stats`).
Preset `default` is our world (configs/eval_paper.yaml); `paper` the reference's world
(configs/eval_paper_world.yaml, the same protocol). Figures (JSON lines):

    quality.policy_pct               mean % of windows found at rho = inf
    quality.policy_pct_rho01         ... at rho = 0.1
    quality.best_baseline_pct        the best non-learning planner at rho = inf (no reference)
    quality.best_baseline            its name
    quality.policy_vs_best_baseline  policy_pct / best_baseline_pct
    quality.policy_vs_best_p         p of that difference, paired t-test over the per-world
                                     means (with the Wilcoxon p, the difference and its CI)
    quality.oracle_pct               the window oracle at rho = inf
    quality.ceiling_pct              oracle_ahead at rho = inf
    quality.rate_ceiling_pct         oracle_rate at rho = inf
    quality.collisions_per_episode   obstacle + in-range robot collisions, all planners
    quality.train_minutes            the policy's training wall time (its metadata.json)
    quality.pct.<planner>.rho<r>     every planner and range
    quality.recipe_seeds             with several policies of one recipe: how many
    quality.recipe_mean_pct          ... the mean over them of their rho = inf figures
    quality.recipe_std_pct           ... and the standard deviation (ddof 1)

Usage (from the repository root):
    python benchmarks/quality.py [--policy DIR [--policy DIR ...] | --seeds DIR DIR ...]
                                 [--preset default|paper] [--worlds 25] [--trials 10]
                                 [--out DIR] [--set key=value ...]
--policy defaults to pretrained/<preset>; without one there, only the baselines run.
Several policies (the training seeds of one recipe) run in one sweep as policy,
policy_2, ...; the policy figures are the first one's.
--out also writes the evaluation tables and plots (results.md, ...) there.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import emit, emit_p, emit_text  # noqa: E402
from jaxmripp import config as cfgmod  # noqa: E402

PRESETS = {"default": "configs/eval_paper.yaml", "paper": "configs/eval_paper_world.yaml"}
BASELINES = ("nbv_targets", "nbv_ahead", "nbv_team", "nbv", "coordinated", "greedy", "mcts",
             "rig", "random")
REFERENCES = cfgmod.REFERENCES


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, action="append", default=[],
                        help="default: pretrained/<preset>; repeat for several seeds")
    parser.add_argument("--seeds", type=Path, nargs="+", default=[], metavar="DIR",
                        help="policies of one recipe (same as repeating --policy)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="default")
    parser.add_argument("--worlds", type=int, default=25)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--out", type=Path, help="also write tables and plots here")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    given = args.policy + args.seeds
    for folder in given:
        if not (folder / "config.yaml").is_file():
            print(f"error: --policy {folder}: no config.yaml there", file=sys.stderr)
            return 2
    if len(set(given)) < len(given):
        print("error: --policy / --seeds: a folder is given twice; allowed: distinct "
              "policies", file=sys.stderr)
        return 2
    default = Path("pretrained") / args.preset
    folders = given or ([default] if (default / "config.yaml").is_file() else [])
    names = ["policy"] + [f"policy_{i + 1}" for i in range(1, len(folders))]
    has_policy = bool(folders)
    planners = (["policy"] if has_policy else []) + list(BASELINES) + list(REFERENCES)
    overrides = [f"eval.planners=[{','.join(planners)}]", "eval.team_sizes=[3]",
                 "eval.radio_ranges=[.inf, 0.1]", "eval.budgets=[10.0]",
                 "eval.budget_mode=team", f"eval.worlds={args.worlds}",
                 f"eval.trials={args.trials}", "eval.layout=random", "eval.pairs=[]", *args.set]
    try:
        cfg = cfgmod.load(PRESETS[args.preset], overrides)
    except cfgmod.ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    missing = [name for name in planners if name not in cfg.eval.planners]
    missing += [f"rho = {rho:g}" for rho in (math.inf, 0.1) if rho not in cfg.eval.radio_ranges]
    if missing:
        print(f"error: --set: the figures need {', '.join(missing)} in the sweep "
              f"(eval.planners must include {', '.join(planners)}; eval.radio_ranges "
              f"inf and 0.1)", file=sys.stderr)
        return 2

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import outputs, sweep  # noqa: PLC0415
    from jaxmripp.evaluation.stats import paired_by_world  # noqa: PLC0415

    policies = {}
    if has_policy:
        try:
            cfg = pipeline.with_policy_inputs(cfg, folders)
        except cfgmod.ConfigError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        for name, folder in zip(names, folders):
            policies[name] = pipeline.sweep_planner(
                folder, cfg, name=name, log=lambda line: print(line, file=sys.stderr))
    result = sweep.run_sweep(cfg, policies, log=lambda line: print(line, file=sys.stderr),
                             time_planning=False, keep_pictures=False)
    command = "python benchmarks/quality.py " + " ".join(argv or sys.argv[1:])
    emit_text("quality.command", command)  # for jaxmripp.ship
    if args.out:
        outputs.write_outputs(result, args.out, cfg, render=True, gif=False, command=command)
    found = {(r.planner, r.shape.radio_range): r.discovered for r in result.runs}
    worlds = result.runs[0].worlds
    pct = {key: float(value.mean()) for key, value in found.items()}
    for (name, rho), value in pct.items():
        emit(f"quality.pct.{name}.rho{rho:g}", value, "%")
    best = max(BASELINES, key=lambda name: pct[(name, math.inf)])
    emit("quality.best_baseline_pct", pct[(best, math.inf)], "%")
    emit_text("quality.best_baseline", best)
    emit("quality.oracle_pct", pct[("oracle", math.inf)], "%")
    emit("quality.ceiling_pct", pct[("oracle_ahead", math.inf)], "%")
    emit("quality.rate_ceiling_pct", pct[("oracle_rate", math.inf)], "%")
    episodes = sum(len(r.discovered) for r in result.runs)
    collisions = sum(int(r.safety[key].sum()) for r in result.runs
                     for key in ("obstacle_collisions", "robot_collisions_in_range"))
    emit("quality.collisions_per_episode", collisions / episodes, "collisions/episode",
         episodes=episodes)
    if has_policy:
        emit("quality.policy_pct", pct[("policy", math.inf)], "%")
        emit("quality.policy_pct_rho01", pct[("policy", 0.1)], "%")
        emit("quality.policy_vs_best_baseline",
             pct[("policy", math.inf)] / pct[(best, math.inf)], "ratio")
        test = paired_by_world(found[("policy", math.inf)], found[(best, math.inf)], worlds)
        emit_p("quality.policy_vs_best_p", test["p"])
        emit("quality.policy_vs_best_diff", test["diff"], "points", ci95=[
            round(x, 3) for x in test["ci"]], p_wilcoxon=float(f"{test['p_wilcoxon']:.3g}"),
            dz=round(test["dz"], 3), worlds=worlds)
        if len(folders) > 1:
            seeds = np.array([pct[(name, math.inf)] for name in names])
            emit("quality.recipe_seeds", len(seeds), "policies")
            emit("quality.recipe_mean_pct", float(seeds.mean()), "%")
            emit("quality.recipe_std_pct", float(seeds.std(ddof=1)), "%")
        metadata = folders[0] / "metadata.json"
        if metadata.is_file():
            emit("quality.train_minutes", json.loads(metadata.read_text())["train_minutes"],
                 "min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
