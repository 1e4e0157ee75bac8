"""What computing the environments in `train.blocks` blocks costs on this machine.

Builds the training chunk (one PPO update) of one config twice, with train.blocks = 0
(one block per device) and = B, and times the two alternately, so both see the same
machine load. Blocks make a run's parameters the same on every device count dividing B
(docs/distributed.md); this measures their price.

Prints JSON lines:
    blocks.agent_steps_per_s.b0      training rate, one block per device (median)
    blocks.agent_steps_per_s.b<B>    the same with B blocks
    blocks.speed_ratio               median over rounds of (rate with B blocks / with one)

Usage: python benchmarks/blocks.py [--blocks 2] [--rounds 5] [--config FILE] [override ...]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402

from common import ArgumentParser, emit, entry_point  # noqa: E402
from jaxmripp import config as cfgmod  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.config.cli import add_config_arguments, print_config  # noqa: E402
from jaxmripp.learn import train as trainmod  # noqa: E402


@entry_point
def main(argv=None) -> int:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--blocks", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5)
    add_config_arguments(parser, presets.DEFAULT)
    args = parser.parse_args(argv)
    if args.blocks < 1 or args.rounds < 1:
        parser.error(f"--blocks {args.blocks} --rounds {args.rounds}: both must be >= 1")
    if args.print_config:
        return print_config(cfgmod.load(args.config, args.overrides))
    runs = {}
    for blocks in (0, args.blocks):
        try:
            cfg = cfgmod.load(args.config, [*args.overrides, "train.updates_per_chunk=1",
                                            f"train.blocks={blocks}"])
        except cfgmod.ConfigError as err:
            parser.error(str(err))
        trainer = trainmod.Trainer.build(cfg)
        state = trainer.with_runner(trainer.place(trainer.init()))
        state, _ = jax.block_until_ready(trainer.chunk(state, trainer.env_dynamic))  # compiles
        runs[blocks] = [trainer, state]
    samples = cfg.train.envs * cfg.train.rollout_steps * cfg.robots.count
    rates = {blocks: [] for blocks in runs}
    for _ in range(args.rounds):
        for blocks, run in runs.items():
            trainer, state = run
            start = time.perf_counter()
            run[1], _ = jax.block_until_ready(trainer.chunk(state, trainer.env_dynamic))
            rates[blocks].append(samples / (time.perf_counter() - start))
    for blocks, values in rates.items():
        emit(f"blocks.agent_steps_per_s.b{blocks}", statistics.median(values), "agent-steps/s")
    emit("blocks.speed_ratio", statistics.median(
        b / a for a, b in zip(rates[0], rates[args.blocks])), "ratio")
    return 0


if __name__ == "__main__":
    sys.exit(main())
