"""How the simulation's cost grows with the team: environment steps with the random planner
for N robots in the 16x world (G = 125, rho = 0.12, the paper's scale setting).

For each N, a batch of environments is reset and stepped (one jitted, vmapped team step
with the state donated, as benchmarks/env.py does); the cost is the median step time over
envs x N agent-steps. Figures (JSON lines):

    scale.us_per_agent_step.n<N>   microseconds of simulation per robot decision
    scale.cost_growth_n<max>_vs_n<min>  the first over the last, e.g. n64_vs_n3
    scale.peak_rss_mb              the process's peak resident memory (all N)

With --eval, the largest team then plays the cell the paper lost (16x world, N = 64,
rho = 0.12, per-robot budget 10 / 3) on W held-out random-layout worlds: the policy with
single-hop exchange and with relay at rho, and the policy, coordinated, nbv and nbv_team
with global communication (rho = inf: everyone hears everyone every step); --no-timing
skips the timing. Every evaluating mode first prints scale.command and scale.rules (the
policy and the overrides each sweep loads its config.yaml with), which `python -m
jaxmripp.ship` records beside the figures. Figures:

    scale.pct.<planner>.<single_hop|relay|global>   mean % of windows found (95% CI)
    scale.relay_vs_best_global_<R>x   relay over the best planner with global
                                      communication (R: world volume over G = 50's)
    scale.relay_vs_best_global_p      Welch p of that comparison

With --tight the same cell runs at the per-robot budget TIGHT_BUDGET, where the strong
planners no longer find nearly every window (the paper's 10 / 3 lets them find 98-99%);
every figure's name then ends in _tight (scale.pct.<planner>.<exchange>_tight,
scale.relay_vs_best_global_16x_tight, scale.relay_vs_best_global_p_tight).

and, with --figure, % found against the fraction of the team budget spent, per planner
and exchange (mean and std band over the worlds).

With --grid (instead of the timing), the paper's scalability grid: every world size of
--world-sizes (3x / 8x / 16x: G = 75 / 100 / 125, with the paper's rho = 0.2 / 0.15 /
0.12) x every team size of --grid-teams, the same planner-exchange pairs as --eval
(--range-planners adds planners with single hop and relay beside the policy), W worlds per
cell. Figures: scale.grid.<planner>.<exchange>.g<G>.n<N> (mean % found, std, 95%
half-width) and, with --figure, % found against N per world size with std bands. Every
cell's worlds follow from eval.seed and the world's index alone, so the grid can be split
over runs (--world-sizes, --grid-teams, --exchanges, --global-planners, --range-planners),
in parallel on one GPU too; --collected FILE [FILE ...] prints the grid's tables from the
lines collected in the files (mean % found, std over the worlds, and per cell the policy
with relay over the best planner with global communication, with their Welch p; last, those
ratios and single hop's for every world size in one table) and draws --figure.

With --ranges R1,R2,... (instead of the timing), how far the radio must reach: the --eval
cell (the largest team of --teams in the --size world) with the --range-planners with single
hop and relay at each radio range listed (one compilation for all of them), and the
--global-planners with global communication, on W worlds. Figures:
scale.range.<planner>.<exchange>.r<rho> (mean % found, std, 95% half-width),
scale.range.relay_vs_best_global.r<rho> (the policy with relay at rho over the best planner
with global communication, with its Welch p) and, with --figure, % found against the radio
range with std bands, the global figures as horizontal bands.

Usage (from the repository root):
    python benchmarks/scale.py [--teams 3,16,32,64] [--size 125] [--envs 2] [--repeats 3]
        [--eval [--tight] --worlds W --policy pretrained/default [--figure FILE]]
        [section.key=value ...]
    python benchmarks/scale.py --grid [--world-sizes 75,100,125] [--grid-teams 16,32,48,64]
        [--worlds W] [--figure docs/scale_grid.png] [--exchanges global,single_hop,relay]
        [--global-planners policy,coordinated,nbv,nbv_team] [--range-planners policy,nbv_team]
    python benchmarks/scale.py --collected grid.jsonl [more.jsonl ...] [--figure docs/scale_grid.png]
    python benchmarks/scale.py --ranges 0.12,0.15,0.18,0.25 [--worlds W] [--policy DIR]
        [--figure docs/scale_radio_range.png] [--global-planners policy,nbv]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from pathlib import Path  # noqa: E402

from common import (ArgumentParser, RandomTeamStepper, add_quiet, emit, emit_p,  # noqa: E402
                    emit_text, entry_point, median_seconds)
from jaxmripp.config.cli import fail  # noqa: E402
from scale_report import (PAIRS, PAPER_RADIO, PLANNERS, grid_tables, plot_grid,  # noqa: E402
                          plot_ranges, read_grid)
from jaxmripp import config, folders  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.parallel import progress  # noqa: E402
from jaxmripp.sim.params import DynamicParams, EnvParams  # noqa: E402


class UsageError(ValueError):
    """Arguments the script cannot run with: main prints the message and exits with 2."""


@entry_point
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        _run(args, argv)
    except UsageError as err:
        return fail(err)
    return 0


def _parser() -> ArgumentParser:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--teams", default="3,16,32,64")
    parser.add_argument("--size", type=int, default=125)
    parser.add_argument("--radio-range", type=float, default=0.12)
    parser.add_argument("--envs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("overrides", nargs="*", metavar="section.key=value",
                        help="dotted config overrides for every cell")
    parser.add_argument("--eval", action="store_true", help="also evaluate the largest team")
    parser.add_argument("--tight", action="store_true",
                        help=f"with --eval: each robot's budget {TIGHT_BUDGET} instead of 10 / 3")
    parser.add_argument("--no-timing", action="store_true",
                        help="with --eval: the evaluation only, without the timing")
    parser.add_argument("--worlds", type=int, default=4, help="worlds of the --eval cell")
    parser.add_argument("--policy", type=Path, default=presets.in_checkout("pretrained/default"),
                        help="trained run or shipped folder for --eval, --grid and --ranges")
    parser.add_argument("--grid", action="store_true", help="the scalability grid only")
    parser.add_argument("--ranges", default=None,
                        help="radio ranges: %% found against the range in the --eval cell only")
    parser.add_argument("--world-sizes", default="75,100,125")
    parser.add_argument("--grid-teams", default="16,32,48,64")
    parser.add_argument("--figure", type=Path, default=None,
                        help="--grid: %% found against N; --eval: against the budget spent; "
                             "--ranges: against the radio range")
    parser.add_argument("--exchanges", default=",".join(EXCHANGES),
                        help="--grid: the exchanges to evaluate (a cell's pairs split over runs)")
    parser.add_argument("--global-planners", default=",".join(PLANNERS),
                        help="--grid: the planners evaluated with global communication")
    parser.add_argument("--range-planners", default=",".join(RANGE_PLANNERS),
                        help="--grid: the planners evaluated with single hop and relay at "
                             "the cell's radio range")
    parser.add_argument("--collected", type=Path, nargs="+", default=None,
                        help="print the tables (and draw --figure) from the scale.grid.* "
                             "JSON lines of these files, collected from --grid runs (a "
                             "cell in several keeps the last file's figure)")
    add_quiet(parser)
    return parser


def _run(args, argv=None) -> None:
    if args.collected is not None:
        missing = [str(path) for path in args.collected if not path.is_file()]
        if missing:
            raise UsageError(f"--collected {' '.join(missing)}: no such file")
        grid = {}
        for path in args.collected:
            grid.update(read_grid(path))
        if not grid:
            raise UsageError(f"--collected {' '.join(map(str, args.collected))}: no "
                             "scale.grid.<planner>.<exchange>.g<G>.n<N> lines")
        sizes = sorted({size for _, _, size, _ in grid})
        print(grid_tables(grid, sizes))
        if args.figure is not None:
            plot_grid(grid, sizes, args.figure)
        return
    if args.tight and not args.eval:
        raise UsageError("--tight: allowed only with --eval (it sets the --eval cell's budget)")
    evaluates = args.eval or args.grid or args.ranges is not None
    if evaluates:  # a folder of another kind or a corrupt export fails here, in one line
        folders.policy(args.policy)
    exchanges, global_planners, range_planners = _planner_lists(args)
    if args.ranges is not None:
        evaluate_ranges(args.policy, max(int(n) for n in args.teams.split(",")), args.size,
                        _radio_ranges(args.ranges, range_planners), args.worlds, args.overrides,
                        args.figure, exchanges, global_planners, range_planners, argv)
    elif args.grid:
        sizes = [int(g) for g in args.world_sizes.split(",")]
        unknown = sorted(set(sizes) - set(PAPER_RADIO))
        if unknown:
            raise UsageError(f"--world-sizes {unknown}: allowed {sorted(PAPER_RADIO)} (the "
                             "paper's worlds, each with its radio range)")
        evaluate_grid(args.policy, sizes, [int(n) for n in args.grid_teams.split(",")],
                      args.worlds, args.overrides, args.figure, exchanges, global_planners,
                      range_planners, argv)
    else:
        teams = sorted(int(n) for n in args.teams.split(","))
        largest = max(teams) if args.eval and args.no_timing else time_teams(teams, args)
        if args.eval:
            budget = TIGHT_BUDGET if args.tight else PER_ROBOT_BUDGET
            evaluate_cell(args.policy, largest, args.size, args.radio_range, args.worlds,
                          args.overrides, args.figure, argv, budget,
                          "_tight" if args.tight else "")


def _planner_lists(args) -> tuple[list[str], list[str], list[str]]:
    """--exchanges, --global-planners (none without the global exchange), --range-planners."""
    exchanges = args.exchanges.split(",")
    global_planners = args.global_planners.split(",") if "global" in exchanges else []
    range_planners = args.range_planners.split(",")
    for flag, given, allowed in (("--exchanges", exchanges, EXCHANGES),
                                 ("--global-planners", global_planners, PLANNERS),
                                 ("--range-planners", range_planners, PLANNERS)):
        if not set(given) <= set(allowed):
            raise UsageError(f"{flag} {sorted(set(given) - set(allowed))}: allowed "
                             f"{', '.join(allowed)}")
    return exchanges, global_planners, range_planners


def _radio_ranges(text: str, range_planners: list[str]) -> list[float]:
    """--ranges as sorted distinct floats."""
    try:
        ranges = sorted({float(r) for r in text.split(",")})
    except ValueError:
        ranges = []
    if not ranges or not all(0 < r < float("inf") for r in ranges):
        raise UsageError(f"--ranges {text}: allowed a comma-separated list of finite positive "
                         "radio ranges (fractions of the world), e.g. 0.12,0.18")
    if "policy" not in range_planners:
        raise UsageError("--range-planners: --ranges compares the policy with relay, so the "
                         "list must name policy")
    return ranges


def time_teams(teams: list[int], args) -> int:
    """Times the random team's step for each N of `teams` (JSON lines) -> the largest N."""
    micros = {}
    bar = progress.bar(len(teams), "timed teams", unit="team")
    for n in teams:
        cfg = config.load(None, [f"world.size={args.size}", f"robots.count={n}",
                                 f"radio.range={args.radio_range}",
                                 f"robots.budget=[{10 / 3 * n}, {10 / 3 * n}]", *args.overrides])
        stepper = RandomTeamStepper(EnvParams.from_config(cfg), DynamicParams.from_config(cfg),
                                    args.envs)
        stepper.reset()
        seconds = median_seconds(stepper.step, repeats=args.repeats, warmup=2)
        micros[n] = 1e6 * seconds / (args.envs * n)
        emit(f"scale.us_per_agent_step.n{n}", micros[n], "us/agent-step", envs=args.envs,
             size=args.size, step_s=round(seconds, 4))
        del stepper
        bar.update()
    bar.close()
    first, last = teams[0], teams[-1]
    emit(f"scale.cost_growth_n{last}_vs_n{first}", micros[last] / micros[first], "ratio")
    # ru_maxrss is in kilobytes on Linux
    emit("scale.peak_rss_mb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "MB")
    return last


EXCHANGES = ("global", "single_hop", "relay")
PER_ROBOT_BUDGET = 10 / 3  # the paper's small-world protocol: team budget 10 for N = 3
# --tight: in the 16x world with 64 robots, nbv_team with global communication finds 27 /
# 46 / 65 / 88% at per-robot budgets 0.5 / 0.8 / 1.2 / 1.8 (docs/results/scale_tight_search/,
# 2 worlds): 1.2 sits in the middle of the range where planners differ.
TIGHT_BUDGET = 1.2
RANGE_PLANNERS = ("policy",)  # those evaluated at the short range unless --range-planners


def exchange_overrides(teams: list[int], size: int, radio_ranges: list[float], worlds: int,
                       overrides: list[str], exchanges=EXCHANGES, global_planners=PLANNERS,
                       range_planners=RANGE_PLANNERS,
                       budget: float = PER_ROBOT_BUDGET) -> dict[str, list[str]]:
    """exchange -> the overrides its sweep loads the policy's config.yaml with: the
    `range_planners` (the policy) with single-hop exchange and with relay at each of
    radio_ranges, the `global_planners` (policy, coordinated, nbv and nbv_team) with global
    communication, on the same held-out worlds for every team size; each robot's budget
    `budget`."""
    cell = [f"eval.team_sizes=[{', '.join(map(str, teams))}]", f"eval.world_sizes=[{size}]",
            f"eval.budgets=[{budget:.8g}]", "eval.budget_mode=per_robot", f"eval.worlds={worlds}",
            "eval.trials=1", "eval.layout=random", "eval.seed=2000", "eval.render=false",
            "eval.pairs=[]", "eval.zip_with_size=[]", *overrides]
    # exchange -> (radio range, relay, planners)
    ranges = ", ".join(map(str, radio_ranges))
    settings_of = {"global": (".inf", "false", global_planners),
                   "single_hop": (ranges, "false", range_planners),
                   "relay": (ranges, "true", range_planners)}
    return {exchange: [*cell, f"eval.radio_ranges=[{settings_of[exchange][0]}]",
                       f"radio.relay={settings_of[exchange][1]}",
                       f"eval.planners=[{', '.join(settings_of[exchange][2])}]"]
            for exchange in exchanges}


def sweep_exchanges(policy: Path, sweeps: dict[str, list[str]]) -> dict:
    """Each exchange's sweep (`exchange_overrides`) -> {(planner, exchange, n, rho): its
    `cells.ShapeRun`} (rho = inf for global)."""
    from jaxmripp import pipeline  # noqa: PLC0415 (after the timing, which needs no policy)
    from jaxmripp.evaluation import sweep  # noqa: PLC0415

    found = {}
    for exchange, overrides in sweeps.items():
        cfg = config.load(policy / "config.yaml", overrides)
        # a given policy is always evaluated (sweep.planner_names): give it only if listed
        policies = ({"policy": pipeline.trained_planner(cfg, policy)}  # with this relay
                    if "policy" in cfg.eval.planners else {})
        result = sweep.run_sweep(cfg, policies, time_planning=False, keep_pictures=False,
                                 log=lambda line: print(line, file=sys.stderr))
        for run in result.runs:
            found[run.planner, exchange, run.shape.n_robots, run.shape.radio_range] = run
    return found


def emit_rules(argv, policy: Path, worlds: int, sweeps: dict[str, list[str]]) -> None:
    """The command and the sweeps' settings, for `python -m jaxmripp.ship`: what every
    figure after them was measured under."""
    emit_text("scale.command", "python benchmarks/scale.py " + " ".join(argv or sys.argv[1:]))
    emit_text("scale.rules", {"policy": str(policy), "config": str(policy / "config.yaml"),
                              "worlds": worlds, "trials": 1, "sweeps": sweeps})


def evaluate_cell(policy: Path, n: int, size: int, radio_range: float, worlds: int,
                  overrides: list[str], figure: Path | None = None, argv=None,
                  budget: float = PER_ROBOT_BUDGET, tag: str = "") -> None:
    """The --eval cell with each robot's budget `budget`; `tag` ends every figure's name."""
    from jaxmripp.evaluation import plots, stats  # noqa: PLC0415

    sweeps = exchange_overrides([n], size, [radio_range], worlds, overrides, budget=budget)
    emit_rules(argv, policy, worlds, sweeps)
    runs = {key[:3]: run for key, run in sweep_exchanges(policy, sweeps).items()}
    found = {key: run.discovered for key, run in runs.items()}
    for (planner, exchange, _), discovered in found.items():
        mean, std, half = stats.mean_ci(discovered)
        emit(f"scale.pct.{planner}.{exchange}{tag}", mean, "%", std=round(std, 2),
             ci95_half=round(half, 2), worlds=worlds, n=n, size=size,
             budget_per_robot=round(budget, 4))
    best = max((k for k in found if k[1] == "global"), key=lambda k: found[k].mean())
    relay = found["policy", "relay", n]
    ratio = round((size / config.REFERENCE_SIZE) ** 3)
    emit(f"scale.relay_vs_best_global_{ratio}x{tag}",
         relay.mean() / max(found[best].mean(), 1e-9), "ratio", best_global=best[0])
    emit_p(f"scale.relay_vs_best_global_p{tag}", stats.welch_ttest(relay, found[best])[2])
    if figure is not None:
        plots.discovery_vs_budget(figure, {
            f"{planner}, {exchange.replace('_', ' ')}": runs[planner, exchange, n]
            for planner, exchange, _ in sorted(runs, key=lambda k: PAIRS.index(k[:2]))},
            title=f"{ratio}x world (G = {size}), N = {n}, rho = {radio_range:g}, "
                  f"budget {budget:.3g} per robot, {worlds} worlds")


def evaluate_grid(policy: Path, sizes: list[int], teams: list[int], worlds: int,
                  overrides: list[str], figure: Path | None, exchanges=EXCHANGES,
                  global_planners=PLANNERS, range_planners=RANGE_PLANNERS, argv=None) -> None:
    from jaxmripp.evaluation import stats  # noqa: PLC0415

    sweeps = {size: exchange_overrides(teams, size, [PAPER_RADIO[size]], worlds, overrides,
                                       exchanges, global_planners, range_planners)
              for size in sizes}
    emit_rules(argv, policy, worlds, {f"g{size}.{exchange}": settings
                                      for size, by_exchange in sweeps.items()
                                      for exchange, settings in by_exchange.items()})
    grid = {}
    for size in sizes:
        runs = sweep_exchanges(policy, sweeps[size])
        for (planner, exchange, n, _), run in sorted(runs.items()):
            mean, std, half = stats.mean_ci(run.discovered)
            grid[planner, exchange, size, n] = (mean, std, worlds)
            emit(f"scale.grid.{planner}.{exchange}.g{size}.n{n}", mean, "%",
                 std=round(std, 2), ci95_half=round(half, 2) if worlds > 1 else None,
                 worlds=worlds)
    if figure is not None:
        plot_grid(grid, sizes, figure)


def evaluate_ranges(policy: Path, n: int, size: int, radio_ranges: list[float], worlds: int,
                    overrides: list[str], figure: Path | None, exchanges=EXCHANGES,
                    global_planners=PLANNERS, range_planners=RANGE_PLANNERS,
                    argv=None) -> None:
    from jaxmripp.evaluation import stats  # noqa: PLC0415

    sweeps = exchange_overrides([n], size, radio_ranges, worlds, overrides, exchanges,
                                global_planners, range_planners)
    emit_rules(argv, policy, worlds, sweeps)
    runs = sweep_exchanges(policy, sweeps)
    for (planner, exchange, _, rho), run in sorted(runs.items()):
        mean, std, half = stats.mean_ci(run.discovered)
        name = f"scale.range.{planner}.{exchange}" + ("" if exchange == "global" else f".r{rho:g}")
        emit(name, mean, "%", std=round(std, 2), ci95_half=round(half, 2) if worlds > 1 else None,
             worlds=worlds, n=n, size=size)
    best = max((run for key, run in runs.items() if key[1] == "global"),
               key=lambda run: run.discovered.mean(), default=None)
    for rho in radio_ranges:
        relay = runs.get(("policy", "relay", n, rho))
        if relay is None or best is None:
            continue
        emit(f"scale.range.relay_vs_best_global.r{rho:g}",
             relay.discovered.mean() / max(best.discovered.mean(), 1e-9), "ratio",
             best_global=best.planner,
             p=float(f"{stats.welch_ttest(relay.discovered, best.discovered)[2]:.3g}"))
    if figure is not None:
        plot_ranges(runs, figure, title=f"{round((size / config.REFERENCE_SIZE) ** 3)}x world "
                                        f"(G = {size}), N = {n}, {worlds} worlds")


if __name__ == "__main__":
    sys.exit(main())
