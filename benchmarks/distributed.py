"""Training in 1 and in P local processes (one CPU device each) on the same global batch.

Prints JSON lines:
    distributed.max_param_rel_diff   largest relative parameter difference, P processes vs 1
    distributed.samples_per_s.p1     agent-steps per second of training, 1 process
    distributed.samples_per_s.p<P>   the same with P processes
(rates are medians over the chunks after the first, which compiles). Both runs compute
their environments in `--blocks` blocks (train.blocks; default: the process count, so
every run has the same blocks and the parameters agree to the bit); `--blocks 0` gives
each device one block, the fastest layout, whose parameters drift with the device count.

Usage: python benchmarks/distributed.py [--processes 2] [--blocks B] [--config FILE]
           [--keep DIR] [override ...]   (default overrides: a 32-environment, 4-update run)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import ArgumentParser, emit, entry_point  # noqa: E402
from jaxmripp import config as cfgmod  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.config.cli import print_config  # noqa: E402

SMALL = ["train.envs=32", "train.updates=4", "train.updates_per_chunk=1", "ppo.minibatches=4"]


@entry_point
def main(argv=None) -> int:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--blocks", type=int, help="train.blocks (default: --processes)")
    parser.add_argument("--config", default=presets.DEFAULT,
                        help=f"a packaged preset's name or a YAML file (default: "
                             f"{presets.DEFAULT})")
    parser.add_argument("--print-config", action="store_true",
                        help="print the merged config as YAML and exit")
    parser.add_argument("--keep", type=Path, help="keep the run folders here (default: a "
                        "temporary folder)")
    parser.add_argument("overrides", nargs="*", default=SMALL, metavar="section.key=value",
                        help=f"dotted overrides (default: {' '.join(SMALL)})")
    args = parser.parse_args(argv)
    if args.processes < 2:
        parser.error(f"--processes: got {args.processes}; allowed: 2 or more")
    blocks = args.processes if args.blocks is None else args.blocks
    overrides = [*args.overrides, f"train.blocks={blocks}"]
    try:
        cfg = cfgmod.load(args.config, overrides)
    except cfgmod.ConfigError as err:
        parser.error(str(err))
    if args.print_config:
        return print_config(cfg)

    from jaxmripp.learn.train import restore  # noqa: PLC0415
    from jaxmripp.parallel.local import max_relative_difference, run_local  # noqa: PLC0415

    params, rates = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for processes in (1, args.processes):
            runs = (args.keep or Path(tmp)) / f"p{processes}"
            command = ["-m", "jaxmripp", "train", "--config", args.config, *overrides, "--no-eval",
                       "--runs", str(runs)]
            for i, result in enumerate(run_local(command, processes, timeout_s=3600)):
                if result.returncode:
                    print(f"process {i} of {processes} failed:\n{result.stderr[-3000:]}",
                          file=sys.stderr)
                    return 1
            run_dir = runs / cfg.train.name
            records = [json.loads(line) for line in
                       (run_dir / "metrics.jsonl").read_text().splitlines()]
            rates[processes] = statistics.median(
                r["agent_steps_per_s"] for r in (records[1:] or records))
            params[processes] = restore(cfg, run_dir).params
    emit("distributed.max_param_rel_diff",
         max_relative_difference(params[args.processes], params[1]), "ratio")
    emit("distributed.samples_per_s.p1", rates[1], "agent-steps/s")
    emit(f"distributed.samples_per_s.p{args.processes}", rates[args.processes], "agent-steps/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
