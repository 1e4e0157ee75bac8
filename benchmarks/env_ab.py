"""The environment step of the working tree against the same step at another commit, in one
process: on a shared machine whose speed moves by tens of percent between minutes, only
steps alternated within one process compare two versions fairly.

The other commit's `jaxmripp` package is exported with `git archive` into a temporary
directory and imported under another name (its absolute imports rewritten), so both
versions run side by side. Each round resets both batches, takes 2 warm-up steps each and
then alternates STEPS timed steps between them (the order flipping every step). Prints
the median wall and CPU time per step of each and their ratios (JSON lines):

    env_ab.step_s.base / env_ab.step_s.tree        median wall seconds per step
    env_ab.wall_ratio                              tree over base (< 1: the tree is faster)
    env_ab.cpu_ratio                               the same for CPU seconds per step

Usage (from the repository root):
    python benchmarks/env_ab.py --base COMMIT [--envs 1024] [--rounds 4] [--steps 6]
        [--tree-set section.key=value ...] [section.key=value ...]
The positional overrides apply to both sides; each --tree-set (repeatable) to the working
tree's side only.
"""

from __future__ import annotations

import importlib
import io
import os
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402

from common import ArgumentParser, RandomTeamStepper, emit, entry_point  # noqa: E402

_BASE_PACKAGE = "jaxmripp_base"


def export_package(commit: str, into: str) -> None:
    """Writes the commit's `jaxmripp` package to `into`/jaxmripp_base, imports renamed."""
    try:
        archive = subprocess.run(["git", "archive", commit, "jaxmripp"], check=True,
                                 capture_output=True).stdout
    except subprocess.CalledProcessError as err:
        raise SystemExit(f"env_ab.py: git archive {commit!r} failed: "
                         f"{err.stderr.decode().strip()}; --base takes a commit of this "
                         "repository") from None
    pattern = re.compile(r"\bjaxmripp(?=[.\s])")
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        for member in tar.getmembers():
            if not member.isfile():
                continue
            path = os.path.join(into, _BASE_PACKAGE + member.name[len("jaxmripp"):])
            os.makedirs(os.path.dirname(path), exist_ok=True)
            data = tar.extractfile(member).read()
            if member.name.endswith(".py"):
                data = pattern.sub(_BASE_PACKAGE, data.decode()).encode()
            with open(path, "wb") as out:
                out.write(data)


def build_stepper(package: str, overrides: list[str], envs: int) -> RandomTeamStepper:
    """The random-planner team step of `package` on the benchmarked setting."""
    config = importlib.import_module(f"{package}.config")
    params_mod = importlib.import_module(f"{package}.sim.params")
    cfg = config.load(None, overrides)
    return RandomTeamStepper(params_mod.EnvParams.from_config(cfg),
                             params_mod.DynamicParams.from_config(cfg), envs, package=package)


@entry_point
def main(argv=None) -> None:
    parser = ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="the commit to compare against")
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--tree-set", action="append", default=[],
                        metavar="section.key=value",
                        help="an override for the working tree's side only, repeatable (with "
                             "--base HEAD: a setting against the same code without it); a "
                             "separate list from the positional overrides, which both sides "
                             "get")
    parser.add_argument("overrides", nargs="*", metavar="section.key=value",
                        help="dotted config overrides for both sides")
    args = parser.parse_args(argv)
    overrides = ["world.size=50", "robots.count=3", *args.overrides]
    with tempfile.TemporaryDirectory() as tmp:
        export_package(args.base, tmp)
        sys.path.insert(0, tmp)
        versions = {"base": build_stepper(_BASE_PACKAGE, overrides, args.envs),
                    "tree": build_stepper("jaxmripp", [*overrides, *args.tree_set],
                                          args.envs)}
        wall = {name: [] for name in versions}
        cpu = {name: [] for name in versions}
        for stepper in versions.values():  # compile both first
            stepper.reset()
            jax.block_until_ready(stepper.step())
        order = list(versions)
        for _ in range(args.rounds):
            for stepper in versions.values():
                stepper.reset()
                stepper.step()
                jax.block_until_ready(stepper.step())
            for _ in range(args.steps):
                order.reverse()
                for name in order:
                    start, cpu_start = time.perf_counter(), time.process_time()
                    jax.block_until_ready(versions[name].step())
                    wall[name].append(time.perf_counter() - start)
                    cpu[name].append(time.process_time() - cpu_start)
    robots = versions["tree"].params.n_robots
    common = dict(envs=args.envs, robots=robots, base=args.base, samples=len(wall["tree"]),
                  backend=jax.default_backend())
    median = {name: statistics.median(times) for name, times in wall.items()}
    for name in versions:
        emit(f"env_ab.step_s.{name}", median[name], "s", **common,
             agent_steps_per_s=round(args.envs * robots / median[name]))
    emit("env_ab.wall_ratio", median["tree"] / median["base"], "tree/base", **common)
    emit("env_ab.cpu_ratio", statistics.median(cpu["tree"]) / statistics.median(cpu["base"]),
         "tree/base", **common)


if __name__ == "__main__":
    sys.exit(main())
