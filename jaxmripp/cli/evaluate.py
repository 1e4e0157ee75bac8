"""Evaluate planners: `jaxmripp eval --config PRESET [--policy NAME=RUN_DIR ...] [--out DIR]
[section.key=value ...]` (or `python eval.py ...` from the repository root).

Without --policy only the baselines in eval.planners run. Each --policy restores a trained
run (its config.yaml and checkpoints) or a shipped export under the given name; repeat it
to compare several (e.g. the variants benchmarks/ablation.py trains). Results go to DIR
(default: the first policy's RUN_DIR/eval for a training run, runs/<folder name>/eval for
a shipped export such as pretrained/default, which stays as shipped; without --policy
runs/<config name>/eval): results.md, runs.csv, runs.json, summary.json and plots.
"""

import argparse
import shlex
import sys
from pathlib import Path

from jaxmripp import allocator
from jaxmripp import config as cfgmod
from jaxmripp import folders
from jaxmripp.config.cli import (ArgumentParser, add_config_arguments, fail, presets_epilog,
                                 print_config)
from jaxmripp.parallel import launch, progress
from jaxmripp.runtime.errors import RuntimeInputError


def parse_policy(text: str) -> tuple[str, Path]:
    name, sep, run_dir = text.partition("=")
    if not sep:
        name, run_dir = "policy", text
    return name.strip(), Path(run_dir)


def parser(prog: str | None = None) -> ArgumentParser:
    out = ArgumentParser(prog=prog, description=__doc__, epilog=presets_epilog(),
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    out.add_argument("--policy", action="append", default=[], metavar="NAME=RUN_DIR",
                     help="a trained run to evaluate under NAME (repeatable)")
    out.add_argument("--best", action="store_true", help="restore the best checkpoints")
    out.add_argument("--out", help="output folder")
    out.add_argument("--no-render", action="store_true", help="skip pictures and GIFs")
    out.add_argument("--no-gif", action="store_true", help="skip the GIFs only")
    out.add_argument("--no-timing", action="store_true",
                     help="skip the separate planner.act timing (one compile less per cell)")
    out.add_argument("--quiet", action="store_true",
                     help="no compilation lines or progress bar (the results are the same)")
    add_config_arguments(out, "protocol_table1", "dotted overrides, e.g. eval.worlds=5")
    launch.add_arguments(out)
    return out


def main(argv=None, prog: str | None = None) -> int:
    args = parser(prog).parse_args(argv)
    allocator.keep_freed_memory()
    progress.set_quiet(args.quiet)
    try:
        cfg = cfgmod.load(args.config, args.overrides)
        if args.print_config:
            return print_config(cfg)
        policies = [parse_policy(p) for p in args.policy]
        if len({n for n, _ in policies}) != len(policies):
            raise cfgmod.ConfigError("--policy: names must be distinct (NAME=RUN_DIR)")
        for name, run_dir in policies:  # by their files, before anything starts
            try:
                folders.policy(run_dir, best=args.best)
            except (cfgmod.ConfigError, folders.FolderError, RuntimeInputError) as err:
                raise cfgmod.ConfigError(f"--policy {name}: {err}") from None
        launch.initialize(launch.from_arguments(args))
    except (cfgmod.ConfigError, launch.LaunchError) as err:
        return fail(err)

    from jaxmripp import pipeline  # noqa: PLC0415 (after argument errors)
    from jaxmripp.evaluation import outputs, sweep  # noqa: PLC0415 (after argument errors)
    from jaxmripp.learn.checkpoint import CheckpointError  # noqa: PLC0415
    from jaxmripp.parallel.mesh import is_main_process  # noqa: PLC0415

    say = print if is_main_process() else (lambda *_: None)

    planners = {}
    try:
        cfg = pipeline.with_policy_inputs(cfg, [run_dir for _, run_dir in policies])
        for name, run_dir in policies:
            try:
                planners[name] = pipeline.sweep_planner(run_dir, cfg, name, best=args.best,
                                                        log=say)
            except CheckpointError as err:
                raise cfgmod.ConfigError(f"--policy {name}: {err}") from None
            say(f"policy {name}: {run_dir}")
    except cfgmod.ConfigError as err:
        return fail(err)
    out = Path(args.out) if args.out else pipeline.eval_dir(
        args.config, [run_dir for _, run_dir in policies])
    render = not args.no_render and sweep.eval_setting(cfg, "render")
    result = sweep.run_sweep(cfg, planners, time_planning=False if args.no_timing else None,
                             keep_pictures=render, log=say)
    if not is_main_process():
        return 0
    invocation = prog if prog and " " in prog else "python eval.py"
    command = invocation + " " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    paths = outputs.write_outputs(result, out, cfg, render=render, gif=not args.no_gif,
                                  command=command)
    print(result.table())
    print(f"results: {out}/ ({', '.join(sorted(p.name for p in paths.values()))})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
