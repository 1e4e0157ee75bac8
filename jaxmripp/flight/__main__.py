"""Flies one mission of simulated quadrotors, each planning with the onboard runtime.

    python -m jaxmripp.flight                                  # pretrained/default
    python -m jaxmripp.flight --export runs/x/export --seed 3 --planner random

Writes to --out: result.json (figures), paths.png (3D plot of the paths and the windows
found) and flight.gif (top-down, as it happened). The city is the voxel world of
`--seed` (random layout, building sides of 2 to 5 voxels) in a 60 m x 60 m x 30 m box; the
team budget is the paper's 7.0.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jaxmripp.config import presets
from jaxmripp.config.cli import ArgumentParser, fail
from jaxmripp.flight.mission import PLANNERS
from jaxmripp.flight.team import DEFAULT_FOOTPRINTS


def main(argv: list[str] | None = None, prog: str = "python -m jaxmripp.flight") -> int:
    parser = ArgumentParser(prog=prog, description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--export", type=Path, default=presets.in_checkout("pretrained/default"),
                        help="exported policy (directory with policy.json)")
    parser.add_argument("--planner", default="policy", choices=PLANNERS)
    parser.add_argument("--seed", type=int, default=0, help="city and planner seed")
    parser.add_argument("--budget", type=float, default=7.0, help="team budget")
    parser.add_argument("--footprints", default="%d,%d" % DEFAULT_FOOTPRINTS,
                        help="building sides drawn from LO..HI voxels (default %(default)s; "
                             "the shipped policy trained on 3,3)")
    parser.add_argument("--sectors", action="store_true",
                        help="each drone keeps to its sector of the world while it has unknown "
                             "views there (jaxmripp.spec.sectors)")
    parser.add_argument("--out", type=Path, default=Path("runs/flight"))
    parser.add_argument("--no-pictures", action="store_true")
    args = parser.parse_args(argv)

    from jaxmripp.flight import city as citymod
    from jaxmripp.flight.mission import MissionSettings, fly_mission
    from jaxmripp.flight.team import load_team, parse_footprints

    try:
        team = load_team(args.export, parse_footprints(args.footprints))
    except ValueError as error:  # a bad export or config (RuntimeInputError, ConfigError)
        return fail(error)
    settings = MissionSettings(budget=args.budget, sectors=args.sectors)
    city = citymod.generate(args.seed, team.world, settings.frame)
    rule = " (sectors)" if args.sectors else ""
    print(f"{team.spec.team_size} drones, {args.planner} planners{rule}, "
          f"{city.n_windows} windows, {len(city.box_centre)} buildings, "
          f"budget {args.budget:g}, seed {args.seed}")
    result = fly_mission(city, team.spec, team.exported, args.planner, settings,
                         seed=args.seed, pad_spacing=team.pad_spacing,
                         progress=lambda k, pct: print(f"round {k:3d}  found {pct:5.1f}%",
                                                       flush=True))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "result.json").write_text(json.dumps(result.figures(), indent=2) + "\n")
    written = ["result.json"]
    if not args.no_pictures:
        from jaxmripp.flight import pictures

        pictures.paths_3d(city, result, args.out / "paths.png")
        pictures.flight_gif(city, result, args.out / "flight.gif")
        written += ["paths.png", "flight.gif"]
    print(f"found {result.pct:.1f}% of {result.windows} windows, {len(result.crashes)} "
          f"crashes, {result.sim_seconds:.0f} s flown in {result.wall_seconds:.0f} s "
          f"(median decision {np.median(result.decision_ms):.1f} ms)")
    print(f"wrote {', '.join(str(args.out / name) for name in written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
