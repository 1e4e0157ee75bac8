"""Generalisation: a policy against the classical planners in 12 shifted settings.

Every cell changes the default world's Table I setting (N = 3, team budget B = 10,
random layout, rho = inf, configs/protocol_table1.yaml) along one or several axes, and runs
every planner on the same W worlds x T trials (default 10 x 5), drawn from the seeds
5000 + cell, which no training run and no other benchmark uses. Per cell the policy is
compared with the best classical planner of that cell (never a reference such as the
oracle), paired by world: the ratio of the means and a paired t-test over the per-world
means. Figures (JSON lines):

    generalize.cell.<name>          policy / best classical, with both means, the best's
                                    name and the paired p-value
    generalize.cells_won            cells where the policy's mean is above the best's
    generalize.geomean_ratio        geometric mean of the 12 ratios

With --ceilings every cell also runs two upper references (never baselines): oracle_rate,
which knows each building's true remaining windows, and oracle_city, which knows those and
the city's geometry; each cell's line adds their means (rate_ceiling_pct,
city_ceiling_pct), and two more lines give how far above the best classical planner they
reach, as the geometric mean over the cells of reference / best classical:

    generalize.geomean_rate_ceiling_ratio
    generalize.geomean_city_ceiling_ratio

--resume FILE reads a previous run's JSON lines (its stdout, e.g. one stopped part-way):
a cell measured there with the same policy weights (policy_sha256), worlds, trials,
overrides and references is printed again as it stands rather than run, so a long run
goes on in pieces and still ends with the summary lines over every cell (write the new run
to another file: the shell empties a file it redirects into before the script reads it).

Cells: the team budget is the team's; "n6" scales it by N / 3 as the issue of record
asks, the combined cells take it literally.

Usage (from the repository root; about 40 minutes on a 2-core CPU, with --ceilings about
8 minutes a cell):
    python benchmarks/generalize.py [--policy DIR] [--worlds 10] [--trials 5]
                                    [--cells a,b,...] [--ceilings] [--resume FILE]
                                    [section.key=value ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from statistics import geometric_mean
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import ArgumentParser, add_quiet, emit, emit_text, entry_point  # noqa: E402
from jaxmripp import config as cfgmod, folders  # noqa: E402
from jaxmripp.config import presets  # noqa: E402

PRESET = "protocol_table1"  # the packaged preset (configs/protocol_table1.yaml)
CLASSICAL = ("nbv_targets", "nbv_ahead", "nbv_team", "nbv")
# --ceilings: reference -> its field in a cell's line
CEILINGS = {"oracle_rate": "rate_ceiling_pct", "oracle_city": "city_ceiling_pct"}
FOOTPRINTS = ("world.footprint=5", "world.footprint_min=2")
# name -> overrides of the default Table I cell (N = 3, B = 10, random layout, rho = inf)
CELLS = {
    "buildings15": ("world.buildings=15",),
    "buildings40": ("world.buildings=40",),
    "footprints2to5": FOOTPRINTS,
    "budget7": ("eval.budgets=[7.0]",),
    "budget14": ("eval.budgets=[14.0]",),
    "n2": ("eval.team_sizes=[2]",),
    "n6": ("eval.team_sizes=[6]", "eval.budgets=[20.0]"),
    "rho0.1": ("eval.radio_ranges=[0.1]",),
    "grid": ("eval.layout=grid",),
    "dense_short": ("world.buildings=40", *FOOTPRINTS, "eval.budgets=[7.0]",
                    "eval.team_sizes=[6]", "eval.radio_ranges=[0.1]"),
    "sparse_pair": ("world.buildings=15", *FOOTPRINTS, "eval.budgets=[14.0]",
                    "eval.team_sizes=[2]", "eval.layout=grid"),
    "dense_long": ("world.buildings=40", *FOOTPRINTS, "eval.budgets=[14.0]",
                   "eval.radio_ranges=[0.3]"),
}
SEED_BASE = 5000


def cell_config(name: str, planners: list[str], worlds: int, trials: int,
                overrides: list[str]) -> cfgmod.Config:
    """The sweep config of one cell: the Table I cell with the cell's shifts."""
    index = list(CELLS).index(name)
    base = [f"eval.planners=[{','.join(planners)}]", "eval.team_sizes=[3]",
            "eval.radio_ranges=[.inf]", "eval.budgets=[10.0]", "eval.budget_mode=team",
            f"eval.worlds={worlds}", f"eval.trials={trials}", "eval.layout=random",
            f"eval.seed={SEED_BASE + index}", "eval.pairs=[]"]
    return cfgmod.load(PRESET, [*base, *CELLS[name], *overrides])


def cell_figures(found: dict, worlds: int) -> dict:
    """One cell's figures from each planner's % found per run (runs ordered world-major,
    the same runs for every planner): the policy's ratio to the best classical planner and
    the paired p-value, both means, random's, and each ceiling's mean where it ran."""
    from jaxmripp.evaluation.stats import paired_by_world  # noqa: PLC0415 (imports scipy)

    best = max(CLASSICAL, key=lambda p: found[p].mean())
    ours, theirs = float(found["policy"].mean()), float(found[best].mean())
    test = paired_by_world(found["policy"], found[best], worlds)
    figures = dict(value=ours / theirs, policy_pct=ours, best=best, best_pct=theirs,
                   random_pct=float(found["random"].mean()), p=float(f"{test['p']:.3g}"))
    figures.update({field: float(found[ref].mean()) for ref, field in CEILINGS.items()
                    if ref in found})
    return figures


def reusable_cells(path: Path, identity: dict, needs: list[str]) -> dict[str, dict]:
    """The cell lines of a previous run's output at `path` whose fields match `identity`
    (policy_sha256, worlds, trials, overrides) and that hold every field in `needs`, by
    cell name. ConfigError for a file that is missing or not JSON lines."""
    try:
        text = path.read_text()
    except OSError as err:
        raise cfgmod.ConfigError(f"--resume {path}: {err.strerror}; allowed: a file this "
                                 "script wrote (its JSON lines)") from None
    cells = {}
    for number, raw in enumerate(text.splitlines(), 1):
        try:
            line = json.loads(raw)
            name = line["name"]
        except (ValueError, TypeError, KeyError):
            raise cfgmod.ConfigError(f"--resume {path}: line {number} is not a figure this "
                                     "script prints; allowed: a file this script wrote (its "
                                     "JSON lines)") from None
        cell = name.removeprefix("generalize.cell.")
        if (cell != name and all(line.get(k) == v for k, v in identity.items())
                and all(k in line for k in needs)):
            cells[cell] = line
    return cells


@entry_point
def main(argv=None) -> int:
    parser = ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, default=presets.in_checkout("pretrained/default"))
    parser.add_argument("--worlds", type=int, default=10)
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--cells", default=",".join(CELLS),
                        help="comma-separated cell names (default: all 12)")
    parser.add_argument("--ceilings", action="store_true",
                        help="also run oracle_rate and oracle_city in every cell "
                             "(upper references)")
    parser.add_argument("--resume", type=Path, metavar="FILE",
                        help="a previous run's JSON lines: its cells with the same policy, "
                             "worlds, trials, overrides and references are reused")
    parser.add_argument("overrides", nargs="*", help="dotted overrides for every cell")
    add_quiet(parser)
    args = parser.parse_args(argv)
    chosen = [c for c in args.cells.split(",") if c]
    unknown = [c for c in chosen if c not in CELLS]
    if unknown or not chosen:
        parser.error(f"--cells: got {args.cells!r}; allowed: a comma-separated subset of "
                     f"{', '.join(CELLS)}")
    if args.worlds < 2 or args.trials < 1:
        parser.error(f"--worlds {args.worlds} --trials {args.trials}: allowed: worlds >= 2 "
                     "(the paired test needs two) and trials >= 1")
    folders.policy(args.policy)  # a folder of another kind fails here, in one line
    planners = ["policy", *CLASSICAL, "random", *(CEILINGS if args.ceilings else ())]
    configs = {name: cell_config(name, planners, args.worlds, args.trials, args.overrides)
               for name in chosen}

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import sweep  # noqa: PLC0415
    from jaxmripp.learn.policy import flatten_params  # noqa: PLC0415
    from jaxmripp.parallel import progress  # noqa: PLC0415
    from jaxmripp.runtime.weights import weights_sha256  # noqa: PLC0415

    # Which policy the figures are of, whatever folder holds it (a run or an export).
    identity = dict(policy_sha256=weights_sha256(flatten_params(
        pipeline.trained_params(args.policy))), worlds=args.worlds, trials=args.trials,
        overrides=args.overrides)
    needs = ["value", "policy_pct", "best_pct", *(CEILINGS.values() if args.ceilings else ())]
    reused = reusable_cells(args.resume, identity, needs) if args.resume else {}

    emit_text("generalize.command", "python benchmarks/generalize.py "
              + " ".join(argv if argv is not None else sys.argv[1:]))
    lines = []
    cells = progress.bar(len(configs), "cells", unit="cell")
    for name, cfg in configs.items():
        if name in reused:
            line = reused[name]
            print(json.dumps(line), flush=True)  # as measured, on the machine it names
            lines.append(line)
            cells.update()
            continue
        cfg = pipeline.with_policy_inputs(cfg, [args.policy])
        policy = pipeline.sweep_planner(args.policy, cfg,
                                        log=lambda line: print(line, file=sys.stderr))
        result = sweep.run_sweep(cfg, {"policy": policy}, log=lambda line: None,
                                 time_planning=False, keep_pictures=False)
        line = cell_figures({r.planner: r.discovered for r in result.runs}, args.worlds)
        lines.append(line)
        emit(f"generalize.cell.{name}", line["value"], "ratio",
             **{k: v for k, v in line.items() if k != "value"}, **identity)
        cells.update()
    cells.close()
    emit("generalize.cells_won", sum(c["policy_pct"] > c["best_pct"] for c in lines), "cells",
         of=len(lines))
    emit("generalize.geomean_ratio",
         geometric_mean([c["policy_pct"] / c["best_pct"] for c in lines]), "ratio")
    for field in CEILINGS.values() if args.ceilings else ():
        emit(f"generalize.geomean_{field.removesuffix('_pct')}_ratio",
             geometric_mean([c[field] / c["best_pct"] for c in lines]), "ratio")
    return 0


if __name__ == "__main__":
    sys.exit(main())
