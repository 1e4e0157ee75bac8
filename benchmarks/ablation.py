"""Ablations (the paper's Tables II and III): the full policy against policies trained with
one part removed, same seed set and number of updates, evaluated on the paper's protocol
under its rules at short range (no sectors, no parting after meeting out of range).

Variants (the dotted overrides that remove the part):

    full      nothing removed
    no_comm   policy.comm_features=false   communication-GP candidate features
    gamma0    reward.gamma=0               communication reward
    no_share  radio.share_maps=false       shared team maps (trained and evaluated without)
    no_view   policy.view_features=false   view-gain candidate features
    no_intent policy.intent_features=false peer-distance candidate feature

Every variant is trained for each seed into RUNS/<preset>/<variant>-s<seed> (a finished run
is reused, an interrupted one resumed, so the script can be stopped and started again),
then all are evaluated on the same worlds: N = 3, B = 10, W worlds x T trials, rho = inf
and 0.1. A variant's episodes of all seeds are pooled and compared with the full policy's
by Welch's t-test. Figures (JSON lines):

    ablation.<preset>.pct.<variant>.rho<r>        mean % of windows found, seeds pooled
    ablation.<preset>.pct.<variant>.s<seed>.rho<r> one seed
    ablation.<preset>.p.<variant>.rho<r>          Welch p-value against full

Usage (from the repository root):
    python benchmarks/ablation.py [--preset default|paper] [--seeds 2] [--updates U]
        [--variants full,no_comm,...] [--worlds 25] [--trials 10] [--runs runs/ablation]
        [--out docs/results/ablation_default.md]
Preset `default` trains the recipe_quick preset (the `make train` job) and evaluates with
protocol_table1; `paper` trains recipe_paper with the default view gain
(sensor.gain_occlusion=true, sensor.gain_facade=nearby) for --updates (default 60) and
evaluates with protocol_table1_paper_world and that gain. Both train without their
kickstarting teacher (ppo.teacher_coef=0), and both evaluate the policy alone under the
paper's rules (PAPER_RULES).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import ArgumentParser, add_quiet, emit, emit_p, entry_point  # noqa: E402
from jaxmripp import config as cfgmod  # noqa: E402
from jaxmripp.parallel import progress  # noqa: E402

VARIANTS = {
    "full": (),
    "no_comm": ("policy.comm_features=false",),
    "gamma0": ("reward.gamma=0",),
    "no_share": ("radio.share_maps=false",),
    "no_view": ("policy.view_features=false",),
    "no_intent": ("policy.intent_features=false",),
}
# Sections that only shape training; an override elsewhere changes the environment, so the
# variant is evaluated with it too.
TRAINING_SECTIONS = ("policy", "reward", "ppo", "train")
# The variants compare what PPO learns from each input, so no kickstarting teacher pulls
# them toward the next-best-view rule, whatever the preset.
NO_TEACHER = ("ppo.teacher_coef=0",)
# preset: (training preset, evaluation preset, default number of updates, overrides; those
# outside the training sections apply to the evaluation too). Both keep the view gain
# (sensor.gain_*) of recipe_quick that their tables were made with.
PRESETS = {
    "default": ("recipe_quick", "protocol_table1", None, ("sensor.gain_facade=nearby",)),
    "paper": ("recipe_paper", "protocol_table1_paper_world", 60,
              ("sensor.gain_occlusion=true", "sensor.gain_facade=nearby")),
}
# Every variant is evaluated under the paper's rules at short range (no sectors, no parting
# after meeting out of range), which the Table I configurations turn on.
PAPER_RULES = ("eval.sectors=false", "safety.escape=false")


def environment_overrides(overrides) -> tuple[str, ...]:
    return tuple(o for o in overrides if o.split(".")[0] not in TRAINING_SECTIONS)


def train_variant(cfg, run_dir: Path) -> float:
    """Trains (or resumes, or reuses) one run; returns the minutes spent now."""
    from jaxmripp.learn import train as trainmod  # noqa: PLC0415

    done = trainmod.read_metrics(run_dir)
    if done and done[-1]["update"] >= cfg.train.updates:
        print(f"{run_dir}: trained, reused", file=sys.stderr)
        return 0.0
    start = time.perf_counter()
    trainmod.train(cfg, run_dir, resume=bool(done),
                   log=lambda line: print(f"{run_dir.name}: {line}", file=sys.stderr))
    return (time.perf_counter() - start) / 60


def parse_args(argv):
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="default")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--updates", type=int, help="default: the training config's")
    parser.add_argument("--variants", default="full,no_comm,gamma0,no_share,no_view")
    parser.add_argument("--worlds", type=int, default=25)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--runs", type=Path, default=Path("runs/ablation"))
    parser.add_argument("--out", type=Path, help="write the markdown table here")
    add_quiet(parser)
    args = parser.parse_args(argv)
    args.variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown or "full" not in args.variants:
        parser.error(f"--variants: got {','.join(args.variants)}; allowed: full (required) "
                     f"and any of {', '.join(VARIANTS)}")
    if args.seeds < 1:
        parser.error(f"--seeds: got {args.seeds}; allowed: at least 1")
    return args


@entry_point
def main(argv=None) -> int:
    args = parse_args(argv)
    train_path, eval_path, preset_updates, preset_overrides = PRESETS[args.preset]
    updates = args.updates or preset_updates
    common = [*NO_TEACHER, *preset_overrides,
              *([f"train.updates={updates}"] if updates else [])]
    try:
        runs = {(variant, seed): cfgmod.load(train_path, [
            *common, *VARIANTS[variant], f"train.seed={seed}",
            f"train.name={variant}-s{seed}"]) for variant in args.variants
            for seed in range(args.seeds)}
    except cfgmod.ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import sweep  # noqa: PLC0415
    from jaxmripp.evaluation.stats import welch_ttest  # noqa: PLC0415

    minutes = {}
    with progress.bar(len(runs), "ablation runs", unit="run") as bar:
        for (variant, seed), cfg in runs.items():
            minutes[variant, seed] = train_variant(cfg, args.runs / args.preset / f"{variant}-s{seed}")
            bar.update()

    # One sweep per environment setting; policies of the same setting share it.
    found = {}
    protocol = ["eval.planners=[policy]", f"eval.worlds={args.worlds}",
                f"eval.trials={args.trials}", "eval.pairs=[]"]
    preset_env = environment_overrides(preset_overrides)
    for env in sorted({environment_overrides(VARIANTS[v]) for v in args.variants}):
        cfg = cfgmod.load(eval_path, [*protocol, *PAPER_RULES, *preset_env, *env])
        policies = {f"{variant}-s{seed}": pipeline.trained_planner(
            run_cfg, args.runs / args.preset / f"{variant}-s{seed}")._replace(
                name=f"{variant}-s{seed}")
            for (variant, seed), run_cfg in runs.items()
            if environment_overrides(VARIANTS[variant]) == env}
        result = sweep.run_sweep(cfg, policies, log=lambda line: print(line, file=sys.stderr),
                                 time_planning=False, keep_pictures=False)
        for r in result.runs:
            found[r.planner, r.shape.radio_range] = np.asarray(r.discovered)

    rhos = sorted({rho for _, rho in found}, reverse=True)
    rows = []
    for variant in args.variants:
        for rho in rhos:
            per_seed = [found[f"{variant}-s{seed}", rho] for seed in range(args.seeds)]
            pooled = np.concatenate(per_seed)
            full = np.concatenate([found[f"full-s{seed}", rho] for seed in range(args.seeds)])
            for seed, values in enumerate(per_seed):
                emit(f"ablation.{args.preset}.pct.{variant}.s{seed}.rho{rho:g}", values.mean(), "%")
            emit(f"ablation.{args.preset}.pct.{variant}.rho{rho:g}", pooled.mean(), "%",
                 episodes=len(pooled))
            p = welch_ttest(pooled, full)[2] if variant != "full" else math.nan
            if variant != "full":
                emit_p(f"ablation.{args.preset}.p.{variant}.rho{rho:g}", p)
            rows.append((variant, rho, [v.mean() for v in per_seed], pooled, full, p))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(markdown(args, updates or runs["full", 0].train.updates, rows))
    return 0


def markdown(args, updates: int, rows) -> str:
    command = "python benchmarks/ablation.py " + " ".join(sys.argv[1:])
    lines = [f"# Ablations, {args.preset} world", "", f"Command: `{command}`", "",
             f"Each variant trained for {updates} updates with seeds 0..{args.seeds - 1}; "
             f"evaluated on {args.worlds} held-out worlds x {args.trials} trials (N = 3, "
             "B = 10), seeds pooled. p: Welch's t-test against the full policy.", "",
             "| variant | rho | % found (pooled) | per seed | vs full | p |",
             "|---|---|---|---|---|---|"]
    for variant, rho, seeds, pooled, full, p in rows:
        per_seed = ", ".join(f"{s:.2f}" for s in seeds)
        delta = "" if variant == "full" else f"{pooled.mean() - full.mean():+.2f}"
        p_text = "" if variant == "full" else f"{p:.3g}"
        lines.append(f"| {variant} | {rho:g} | {pooled.mean():.2f} +- {pooled.std(ddof=1):.2f} "
                     f"| {per_seed} | {delta} | {p_text} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
