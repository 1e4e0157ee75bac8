"""Planning quality: the Table I protocol on a shipped (or given) policy and every
non-learning planner.

N = 3 robots, team budget B = 10, W held-out random-layout worlds x T trials, radio range
rho = inf and 0.1; planners: the policy, nbv_targets, nbv_ahead, nbv_team, nbv,
coordinated, greedy, mcts, rig, random, and four upper references that read the truth
(never "baselines"): the window oracle per unit of cost (oracle), the same looking a
flight ahead with claims heard only in radio range (oracle_ahead), nbv_targets with
each building's true remaining windows (oracle_rate), and that on the true city
(oracle_city: it knows every building's shape, not where its windows are). Every planner runs the same worlds
and trials, so comparisons are paired by world (`jaxmripp.evaluation.stats`).
Preset `default` is our world (the protocol_table1 preset, configs/protocol_table1.yaml);
`paper` the reference's world (protocol_table1_paper_world, the same protocol). Figures
(JSON lines):

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
    quality.city_ceiling_pct         oracle_city at rho = inf
    quality.collisions_per_episode   obstacle + in-range robot collisions, all planners
    quality.train_minutes            the policy's training time (its metrics.jsonl)
    quality.pct.<planner>.rho<r>     every planner and range
    quality.recipe_seeds             with --seeds (policies of one recipe): how many
    quality.recipe_mean_pct          ... the mean over them of their rho = inf figures
    quality.recipe_std_pct           ... and the standard deviation (ddof 1)
    quality.recipe_median            ... the folder of the median one (the upper middle of
                                     an even count): the seed to ship

and quality.command and quality.rules (the preset, its overrides, the policies, the
worlds, trials and seed), which `python -m jaxmripp.ship` records beside the figures.
With --planners, the figures that need the planners left out (the best baseline, the
references) are not printed.

Usage (from the repository root):
    python benchmarks/quality.py [--policy DIR [--policy DIR ...] | --seeds DIR DIR ...]
                                 [--preset default|paper] [--worlds 25] [--trials 10]
                                 [--planners policy,...] [--out DIR] [--print-config]
                                 [section.key=value ...]
--policy defaults to pretrained/<preset>; without one there, only the baselines run.
Several policies run in one sweep as policy, policy_2, ...; the policy figures are the
first one's. Given with --seeds they are the training seeds of one recipe and the
recipe_* lines summarise them; repeated --policy compares distinct policies.
--out also writes the evaluation tables and plots (results.md, ...) there. The dotted
overrides apply after the protocol's settings.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import ArgumentParser, add_quiet, emit, emit_p, emit_text, entry_point  # noqa: E402
from jaxmripp import config as cfgmod, folders  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.config.cli import add_config_arguments, print_config  # noqa: E402

PRESETS = {"default": "protocol_table1", "paper": "protocol_table1_paper_world"}  # packaged presets
BASELINES = ("nbv_targets", "nbv_ahead", "nbv_team", "nbv", "coordinated", "greedy", "mcts",
             "rig", "random")
REFERENCES = cfgmod.REFERENCES
CEILINGS = {"oracle": "quality.oracle_pct", "oracle_ahead": "quality.ceiling_pct",
            "oracle_rate": "quality.rate_ceiling_pct", "oracle_city": "quality.city_ceiling_pct"}


@entry_point
def main(argv=None) -> int:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, action="append", default=[],
                        help="default: pretrained/<preset>; repeat to compare policies")
    parser.add_argument("--seeds", type=Path, nargs="+", default=[], metavar="DIR",
                        help="the training seeds of one recipe (adds the recipe_* lines)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="default")
    parser.add_argument("--worlds", type=int, default=25)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--planners", help="comma-separated subset (default: all)")
    parser.add_argument("--out", type=Path, help="also write tables and plots here")
    add_config_arguments(parser, None, "dotted overrides after the protocol's, e.g. "
                                       "sensor.gain_occlusion=true")
    add_quiet(parser)
    args = parser.parse_args(argv)
    given = args.policy + args.seeds
    for folder in given:  # a folder of another kind or a corrupt export fails here
        folders.policy(folder)
    if args.policy and args.seeds:
        parser.error("--policy / --seeds: give one of them; allowed: --policy DIR (repeated: "
                     "distinct policies) or --seeds DIR DIR ... (one recipe's seeds)")
    if len(set(given)) < len(given):
        parser.error("--policy / --seeds: a folder is given twice; allowed: distinct policies")
    default = presets.in_checkout(Path("pretrained") / args.preset)
    shipped = folders.is_export(default) or folders.is_training_run(default)
    policy_dirs = given or ([default] if shipped else [])
    names = ["policy"] + [f"policy_{i + 1}" for i in range(1, len(policy_dirs))]
    everything = (["policy"] if policy_dirs else []) + list(BASELINES) + list(REFERENCES)
    planners = args.planners.split(",") if args.planners else everything
    unknown = [name for name in planners if name not in everything]
    if unknown:
        parser.error(f"--planners: {','.join(unknown)} unknown; allowed: "
                     f"{','.join(everything)}")
    overrides = [f"eval.planners=[{','.join(planners)}]", "eval.team_sizes=[3]",
                 "eval.radio_ranges=[.inf, 0.1]", "eval.budgets=[10.0]",
                 "eval.budget_mode=team", f"eval.worlds={args.worlds}",
                 f"eval.trials={args.trials}", "eval.layout=random", "eval.pairs=[]",
                 *args.overrides]
    cfg = cfgmod.load(PRESETS[args.preset], overrides)
    missing = [name for name in planners if name not in cfg.eval.planners]
    missing += [f"rho = {rho:g}" for rho in (math.inf, 0.1) if rho not in cfg.eval.radio_ranges]
    if missing:
        parser.error(f"overrides: the figures need {', '.join(missing)} in the sweep "
                     f"(eval.planners must include {', '.join(planners)}; eval.radio_ranges "
                     "inf and 0.1)")
    if args.print_config:
        return print_config(cfg)

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import outputs, sweep  # noqa: PLC0415
    from jaxmripp.evaluation.stats import paired_by_world  # noqa: PLC0415

    policies = {}
    if "policy" in planners:
        cfg = pipeline.with_policy_inputs(cfg, policy_dirs)
        for name, folder in zip(names, policy_dirs):
            policies[name] = pipeline.sweep_planner(
                folder, cfg, name=name, log=lambda line: print(line, file=sys.stderr))
    result = sweep.run_sweep(cfg, policies, log=lambda line: print(line, file=sys.stderr),
                             time_planning=False, keep_pictures=False)
    command = "python benchmarks/quality.py " + " ".join(argv or sys.argv[1:])
    emit_text("quality.command", command)  # for jaxmripp.ship
    emit_text("quality.rules", {  # what the figures were measured under
        "config": f"configs/{PRESETS[args.preset]}.yaml", "overrides": overrides,
        "policy": [str(d) for d in policy_dirs] if "policy" in planners else None,
        "worlds": cfg.eval.worlds, "trials": cfg.eval.trials, "seed": cfg.eval.seed})
    if args.out:
        outputs.write_outputs(result, args.out, cfg, render=True, gif=False, command=command)
    found = {(r.planner, r.shape.radio_range): r.discovered for r in result.runs}
    worlds = result.runs[0].worlds
    pct = {key: float(value.mean()) for key, value in found.items()}
    for (name, rho), value in pct.items():
        emit(f"quality.pct.{name}.rho{rho:g}", value, "%")
    best = None
    if set(BASELINES) <= set(planners):
        best = max(BASELINES, key=lambda name: pct[(name, math.inf)])
        emit("quality.best_baseline_pct", pct[(best, math.inf)], "%")
        emit_text("quality.best_baseline", best)
    for name, figure in CEILINGS.items():
        if name in planners:
            emit(figure, pct[(name, math.inf)], "%")
    episodes = sum(len(r.discovered) for r in result.runs)
    collisions = sum(int(r.safety[key].sum()) for r in result.runs
                     for key in ("obstacle_collisions", "robot_collisions_in_range"))
    emit("quality.collisions_per_episode", collisions / episodes, "collisions/episode",
         episodes=episodes)
    if "policy" in planners:
        emit("quality.policy_pct", pct[("policy", math.inf)], "%")
        emit("quality.policy_pct_rho01", pct[("policy", 0.1)], "%")
        if best is not None:
            emit("quality.policy_vs_best_baseline",
                 pct[("policy", math.inf)] / pct[(best, math.inf)], "ratio")
            test = paired_by_world(found[("policy", math.inf)], found[(best, math.inf)], worlds)
            emit_p("quality.policy_vs_best_p", test["p"])
            emit("quality.policy_vs_best_diff", test["diff"], "points", ci95=[
                round(x, 3) for x in test["ci"]],
                p_wilcoxon=float(f"{test['p_wilcoxon']:.3g}"), dz=round(test["dz"], 3),
                worlds=worlds)
        if len(args.seeds) > 1:
            seeds = np.array([pct[(name, math.inf)] for name in names])
            emit("quality.recipe_seeds", len(seeds), "policies")
            emit("quality.recipe_mean_pct", float(seeds.mean()), "%")
            emit("quality.recipe_std_pct", float(seeds.std(ddof=1)), "%")
            median = int(np.argsort(seeds, kind="stable")[len(seeds) // 2])
            emit_text("quality.recipe_median", str(policy_dirs[median]))
        minutes = folders.train_minutes(policy_dirs[0])
        if minutes is not None:
            emit("quality.train_minutes", minutes, "min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
