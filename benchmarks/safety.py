"""Safe flight: collisions, blocked and held moves, and discovery, for every planner.

N = 3 robots, team budget B = 10, W held-out random-layout worlds (one trial each) at
radio ranges 0.3 and 0.1; planners random, greedy, coordinated and, with --policy, a
trained run. The environment applies the flight rules of `jaxmripp.spec.flight` to every
planner alike; the figures say whether they hold and what they cost:

    safety.obstacle_collisions                     total over all episodes and planners
    safety.robot_collisions_in_range               total (robots that heard each other)
    safety.robot_collisions_out_of_range_per_episode
    safety.blocked_per_episode, safety.held_per_episode
    safety.discovered_pct.<planner>                mean over both radio ranges
    safety.discovered_pct.<planner>.rho<r>         per radio range

Usage (from the repository root):
    python benchmarks/safety.py [--policy RUN_DIR] [--worlds 50] [--print-config]
                                [section.key=value ...]
The dotted overrides apply after the protocol's settings (e.g. safety.flight=optimistic for
the unsafe reference).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from common import ArgumentParser, emit, entry_point  # noqa: E402
from jaxmripp import config as cfgmod, folders  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.config.cli import add_config_arguments, fail, print_config  # noqa: E402

RANGES = (0.3, 0.1)
BASELINES = ("random", "greedy", "coordinated")


@entry_point
def main(argv=None) -> int:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, help="a trained run directory")
    parser.add_argument("--worlds", type=int, default=50)
    add_config_arguments(parser, None, "dotted overrides after the protocol's, e.g. "
                                       "safety.flight=optimistic")
    args = parser.parse_args(argv)
    if args.policy:  # a folder of another kind or a corrupt export fails here, in one line
        folders.policy(args.policy)
    base = args.policy / "config.yaml" if args.policy else presets.DEFAULT
    planners = (["policy"] if args.policy else []) + list(BASELINES)
    overrides = [f"eval.planners=[{','.join(planners)}]", "eval.team_sizes=[3]",
                 "eval.world_sizes=[50]", f"eval.radio_ranges=[{','.join(map(str, RANGES))}]",
                 "eval.budgets=[10.0]", "eval.budget_mode=team", f"eval.worlds={args.worlds}",
                 "eval.trials=1", "eval.layout=random", "eval.pairs=[]",
                 *args.overrides]
    try:
        cfg = cfgmod.load(base, overrides)
    except cfgmod.ConfigError as err:
        return fail(err)
    if args.print_config:
        return print_config(cfg)

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import sweep  # noqa: PLC0415

    policies = {"policy": pipeline.trained_planner(cfg, args.policy)} if args.policy else {}
    result = sweep.run_sweep(cfg, policies, log=lambda line: print(line, file=sys.stderr),
                             time_planning=False, keep_pictures=False)
    runs = result.runs
    total = lambda name: sum(int(r.safety[name].sum()) for r in runs)
    episodes = sum(len(r.discovered) for r in runs)
    per_episode = lambda name: total(name) / episodes
    emit("safety.obstacle_collisions", total("obstacle_collisions"), "collisions",
         episodes=episodes)
    emit("safety.robot_collisions_in_range", total("robot_collisions_in_range"), "pairs")
    emit("safety.robot_collisions_out_of_range_per_episode",
         per_episode("robot_collisions_out_of_range"), "pairs/episode")
    for r in runs:
        if r.shape.radio_range == 0.1:
            emit(f"safety.robot_collisions_out_of_range_per_episode.{r.planner}.rho0.1",
                 r.safety["robot_collisions_out_of_range"].mean(), "pairs/episode")
    emit("safety.blocked_per_episode", per_episode("blocked"), "moves/episode")
    emit("safety.held_per_episode", per_episode("held"), "moves/episode")
    for name in planners:
        mine = [r for r in runs if r.planner == name]
        emit(f"safety.discovered_pct.{name}", np.mean([r.discovered.mean() for r in mine]), "%")
        for r in mine:
            emit(f"safety.discovered_pct.{name}.rho{r.shape.radio_range:g}",
                 r.discovered.mean(), "%", std=round(float(r.discovered.std(ddof=1)), 3))
    return 0


if __name__ == "__main__":
    sys.exit(main())
