"""Physics in the loop: the exported policy against the random planner (and next-best
view) on simulated quadrotors, over W cities (`jaxmripp.flight`).

    python benchmarks/flight.py [--export pretrained/default] [--worlds 5]
        [--planners policy,random,nbv] [--budget 7.0] [--footprints 2,5]
        [--radio-range RHO]
    python benchmarks/flight.py --combine SEED0.jsonl SEED1.jsonl SEED2.jsonl

Every planner flies the same cities (seeds first_seed .. first_seed + W - 1, random
layout, building sides of 2 to 5 voxels, 60 m x 60 m x 30 m, N from the export), every
planner at the export's radio range (`radio.range`) unless --radio-range is given. Prints
JSON lines: flight.<planner>_pct (mean, with std and 95% half-width),
flight.policy_vs_random, flight.policy_vs_nbv (with nbv flown; flight.policy_vs_nbv_p the
paired t-test over the cities), flight.crashes (all planners, all missions),
flight.decision_ms (median per robot decision, policy), flight.sense_ms (median depth
image -> map update), flight.sim_realtime_factor (simulated seconds per wall second, all
missions), flight.max_speed, flight.track_error_m (farthest from a line of flight),
flight.late_arrivals, flight.false_free_voxels (building voxels some map held FREE; 0
by the depth rule), flight.refused_messages (the drones fly a signed radio, a team key
from each city's seed: none refused in an honest team) and flight.map_conflicts (voxels
of merged map deltas one drone held FREE and another OCCUPIED; OCCUPIED is kept).

--combine reads this script's output for each training seed of one recipe (flown on the
same cities, with the same planners and range: their nbv and random figures must agree) and
prints the figures over seeds instead of flying: flight.recipe_seeds,
flight.recipe_mean_pct, flight.recipe_std_pct (over seeds), flight.recipe_policy_vs_nbv
(the mean over seeds / nbv) and flight.recipe_crashes (every seed's missions).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from common import ArgumentParser, add_quiet, emit, emit_p, entry_point  # noqa: E402
from jaxmripp.flight.team import DEFAULT_FOOTPRINTS  # noqa: E402


@entry_point
def main(argv=None) -> None:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--export", type=Path, default=Path("pretrained/default"))
    parser.add_argument("--worlds", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--planners", default="policy,random,nbv")
    parser.add_argument("--budget", type=float, default=7.0)
    parser.add_argument("--footprints", default="%d,%d" % DEFAULT_FOOTPRINTS,
                        help="building sides drawn from LO..HI voxels")
    parser.add_argument("--radio-range", type=float, default=None,
                        help="fly every planner at this range (inf allowed) instead "
                             "of the export's radio.range")
    parser.add_argument("--combine", nargs="+", type=Path, metavar="FILE",
                        help="print the figures over training seeds from each seed's "
                             "output of this script instead of flying")
    add_quiet(parser)
    args = parser.parse_args(argv)
    if args.combine:
        return combine(args.combine, parser)
    planners = args.planners.split(",")
    if args.worlds < 1 or "policy" not in planners or "random" not in planners:
        parser.error("--worlds must be >= 1 and --planners must include policy and random")

    from jaxmripp.flight import city as citymod
    from jaxmripp.parallel import progress
    from jaxmripp.flight.mission import MissionSettings, fly_mission
    from jaxmripp.flight.team import load_team, parse_footprints

    try:
        team = load_team(args.export, parse_footprints(args.footprints), args.radio_range)
    except ValueError as error:
        parser.error(str(error))
    settings = MissionSettings(budget=args.budget)
    results = {name: [] for name in planners}
    bar = progress.bar(args.worlds * len(planners), "missions", unit="mission")
    for seed in range(args.first_seed, args.first_seed + args.worlds):
        city = citymod.generate(seed, team.world, settings.frame)
        for name in planners:
            results[name].append(fly_mission(city, team.spec, team.exported, name, settings,
                                             seed=seed, pad_spacing=team.pad_spacing))
            bar.set_postfix({name: f"{results[name][-1].pct:.1f}%"})
            bar.update()
    bar.close()
    every = [r for runs in results.values() for r in runs]
    for name, runs in results.items():
        pct = np.array([r.pct for r in runs])
        std = float(pct.std(ddof=1)) if len(pct) > 1 else 0.0
        emit(f"flight.{name}_pct", pct.mean(), "%", std=round(std, 3),
             ci95=round(1.96 * std / math.sqrt(len(pct)), 3), worlds=len(pct))
    policy = np.mean([r.pct for r in results["policy"]])
    random = np.mean([r.pct for r in results["random"]])
    emit("flight.policy_vs_random", policy / random, "ratio")
    if "nbv" in results:
        from jaxmripp.evaluation.stats import paired_by_world  # noqa: PLC0415

        # One mission per city and planner: the cities are the pairs.
        test = paired_by_world([r.pct for r in results["policy"]],
                               [r.pct for r in results["nbv"]], args.worlds)
        emit("flight.policy_vs_nbv", policy / np.mean([r.pct for r in results["nbv"]]),
             "ratio", diff=round(test["diff"], 3))
        emit_p("flight.policy_vs_nbv_p", test["p"])
    emit("flight.crashes", sum(len(r.crashes) for r in every), "count",
         missions=len(every))
    emit("flight.decision_ms", np.median([t for r in results["policy"] for t in r.decision_ms]),
         "ms")
    emit("flight.sense_ms", np.median([t for r in every for t in r.sense_ms]), "ms")
    emit("flight.sim_realtime_factor",
         sum(r.sim_seconds for r in every) / sum(r.wall_seconds for r in every), "x")
    emit("flight.max_speed", max(r.max_speed for r in every), "m/s")
    emit("flight.track_error_m", max(r.track_error for r in every), "m")
    emit("flight.late_arrivals", sum(r.late_arrivals for r in every), "count")
    emit("flight.false_free_voxels", sum(r.false_free for r in every), "count")
    emit("flight.refused_messages", sum(r.refused_messages for r in every), "count")
    emit("flight.map_conflicts", sum(r.map_conflicts for r in every), "count")


def combine(files: list[Path], parser: argparse.ArgumentParser) -> int:
    """The recipe's figures over its seeds' flights (see the module docstring)."""
    allowed = "allowed: two or more outputs of benchmarks/flight.py, one per training seed"
    if len(files) < 2:
        parser.error(f"--combine: got {len(files)} file; {allowed}")
    seeds = []
    for file in files:
        try:
            lines = {r["name"]: r for r in map(json.loads, file.read_text().splitlines())}
            seeds.append({name: lines[f"flight.{name}"]["value"] for name in
                          ("policy_pct", "nbv_pct", "random_pct", "crashes")}
                         | {"worlds": lines["flight.policy_pct"]["worlds"]})
        except (OSError, ValueError, KeyError, TypeError) as error:
            parser.error(f"--combine {file}: {type(error).__name__} {error}; {allowed} "
                         "with nbv flown")
    for key in ("worlds", "nbv_pct", "random_pct"):
        if len({seed[key] for seed in seeds}) > 1:
            parser.error(f"--combine: the files' {key} differ "
                         f"({', '.join(str(seed[key]) for seed in seeds)}); {allowed}, "
                         "flown on the same cities at the same radio range")
    pct = np.array([seed["policy_pct"] for seed in seeds])
    emit("flight.recipe_seeds", len(pct), "count")
    emit("flight.recipe_mean_pct", pct.mean(), "%", worlds=seeds[0]["worlds"])
    emit("flight.recipe_std_pct", pct.std(ddof=1), "%")
    emit("flight.recipe_policy_vs_nbv", pct.mean() / seeds[0]["nbv_pct"], "ratio")
    emit("flight.recipe_crashes", sum(seed["crashes"] for seed in seeds), "count")
    return 0


if __name__ == "__main__":
    sys.exit(main())
