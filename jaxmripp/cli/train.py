"""Train a policy: `jaxmripp train --config PRESET [section.key=value ...]` (or
`python train.py ...` from the repository root).

A new run goes to RUNS/<train.name> (--runs, default runs; -2, -3, ... where that exists),
or with --run-dir to exactly the folder named, so that training stages chain by folder,
each starting from the one before (`make scale` runs the whole chain):
  jaxmripp train --config recipe_scale_n8 --run-dir runs/scale_n8 train.init_from=runs/scale_n3
  jaxmripp train --config recipe_scale --run-dir runs/scale train.init_from=runs/scale_n8"""

import argparse
import sys
from pathlib import Path

from jaxmripp import allocator
from jaxmripp import config as cfgmod
from jaxmripp import folders, pipeline
from jaxmripp.config import presets
from jaxmripp.config.cli import (ArgumentParser, add_config_arguments, fail, presets_epilog,
                                 print_config)
from jaxmripp.learn import train as trainmod
from jaxmripp.learn.checkpoint import CheckpointError
from jaxmripp.parallel import launch, progress
from jaxmripp.parallel.mesh import ShardingError, is_main_process


def parser(prog: str | None = None) -> ArgumentParser:
    out = ArgumentParser(prog=prog, description=__doc__, epilog=presets_epilog(),
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    out.add_argument("--resume", metavar="RUN_DIR",
                     help="continue this run from its last checkpoint; overrides may change "
                          "only train.updates, train.updates_per_chunk, train.keep_checkpoints, "
                          "train.log, train.eval_* and eval.* (recorded in its config.yaml "
                          "and resumes.jsonl)")
    out.add_argument("--stop-after-chunks", type=int, default=None,
                     help="stop after this many chunks (resume later with --resume)")
    out.add_argument("--runs", help="where new run folders are created (default: runs)")
    out.add_argument("--run-dir", metavar="RUN_DIR",
                     help="create the run in exactly this folder, which must be new or empty "
                          "(not with --resume or --runs)")
    out.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    out.add_argument("--quiet", action="store_true",
                     help="no compilation lines, progress bars or line per chunk")
    add_config_arguments(out, presets.DEFAULT)
    launch.add_arguments(out)
    return out


def main(argv=None, prog: str | None = None) -> int:
    cli = parser(prog)
    args = cli.parse_args(argv)
    for other in ("resume", "runs"):
        if args.run_dir and getattr(args, other):
            cli.error(f"argument --run-dir: not allowed with argument --{other}")
    allocator.keep_freed_memory()
    progress.set_quiet(args.quiet)  # the final evaluation's bars as well
    try:
        if args.resume:
            run_dir = Path(args.resume)
            folders.training_run(run_dir)  # a checkpoint to continue, before any write
            cfg = cfgmod.load(run_dir / "config.yaml", args.overrides)
        else:
            cfg = cfgmod.load(args.config, args.overrides)
        if args.print_config:
            return print_config(cfg)
        if args.run_dir:
            folders.new_run(args.run_dir)  # every process, before any creates it
        if not args.resume:
            pipeline.check_initial_params(cfg)  # its files, before JAX starts
        launch.initialize(launch.from_arguments(args))
        initial_params = None if args.resume else pipeline.initial_params(cfg)
        if not args.resume:  # every process picks the folder before any creates it
            run_dir = (Path(args.run_dir) if args.run_dir else
                       trainmod.fresh_run_dir(Path(args.runs or "runs"), cfg.train.name))
            launch.barrier("run folder chosen")
        say = print if is_main_process() else (lambda *_: None)
        say(f"run folder: {run_dir}")
        state = trainmod.train(cfg, run_dir, resume=bool(args.resume),
                               stop_after_chunks=args.stop_after_chunks, log=say,
                               initial_params=initial_params, quiet=args.quiet)
    except (cfgmod.ConfigError, folders.FolderError, CheckpointError, launch.LaunchError,
            ShardingError) as err:
        return fail(err)
    finished = int(state.update) >= cfg.train.updates
    if finished and not args.no_eval:
        pipeline.report(cfg, run_dir, log=say)
    written = [name for name in ("metrics.jsonl", "learning_curve.png", "eval_table.md",
                                 "discovered_vs_budget.png", "episode_policy.png", "checkpoints")
               if (run_dir / name).exists()]
    say(f"results: {run_dir}/ ({', '.join(written)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
