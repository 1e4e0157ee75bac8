"""How the simulation's cost grows with the team: environment steps with the random planner
for N robots in the 16x world (G = 125, rho = 0.12, the paper's scale setting).

For each N, a batch of environments is reset and stepped (one jitted, vmapped team step
with the state donated, as benchmarks/env.py does); the cost is the median step time over
envs x N agent-steps. Figures (JSON lines):

    scale.us_per_agent_step.n<N>   microseconds of simulation per robot decision
    scale.cost_growth_n<max>_vs_n<min>  the first over the last, e.g. n64_vs_n3
    scale.peak_rss_mb              the process's peak resident memory (all N)

Usage (from the repository root):
    python benchmarks/scale.py [--teams 3,16,32,64] [--size 125] [--envs 2] [--repeats 3]
        [--set key=value ...]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common import RandomTeamStepper, emit, median_seconds  # noqa: E402
from jaxmripp import config  # noqa: E402
from jaxmripp.sim.params import DynamicParams, EnvParams  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--teams", default="3,16,32,64")
    parser.add_argument("--size", type=int, default=125)
    parser.add_argument("--radio-range", type=float, default=0.12)
    parser.add_argument("--envs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--set", nargs="*", default=[], help="extra config overrides")
    args = parser.parse_args(argv)
    teams = sorted(int(n) for n in args.teams.split(","))
    micros = {}
    for n in teams:
        try:
            cfg = config.load(None, [f"world.size={args.size}", f"robots.count={n}",
                                     f"radio.range={args.radio_range}",
                                     f"robots.budget=[{10 / 3 * n}, {10 / 3 * n}]", *args.set])
        except config.ConfigError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        stepper = RandomTeamStepper(EnvParams.from_config(cfg), DynamicParams.from_config(cfg),
                                    args.envs)
        stepper.reset()
        seconds = median_seconds(stepper.step, repeats=args.repeats, warmup=2)
        micros[n] = 1e6 * seconds / (args.envs * n)
        emit(f"scale.us_per_agent_step.n{n}", micros[n], "us/agent-step", envs=args.envs,
             size=args.size, step_s=round(seconds, 4))
        del stepper
    first, last = teams[0], teams[-1]
    emit(f"scale.cost_growth_n{last}_vs_n{first}", micros[last] / micros[first], "ratio")
    # ru_maxrss is in kilobytes on Linux
    emit("scale.peak_rss_mb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
