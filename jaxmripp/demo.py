"""A team flown by the onboard runtime: every decision comes from `OnboardPlanner`.

    python -m jaxmripp.demo                         # greedy planners, default config
    python -m jaxmripp.demo --export runs/x/export  # the exported policy
    python -m jaxmripp.demo --export pretrained/default --planner random  # its world, random

The world and the ground-truth camera come from the JAX side (`jaxmripp.sim.world`,
`jaxmripp.sim.sensing.cast`); the planners are the NumPy runtime alone. The robots start on
their take-off pads (`jaxmripp.spec.flight`). Each round every robot senses, broadcasts its message to the robots
within radio range (JSON bytes, as on a real radio) and reads theirs; with
`radio.share_maps` it then broadcasts its map deltas (`jaxmripp.spec.sharing`) and merges
those sent to it; it decides, then broadcasts its intent, reads theirs and resolves (a
robot whose flight would come within d_c of a lower-id robot's holds); the demo
then flies each robot along its line of flight, stopping before a building (the
traversal rule, as the env does), and prints the progress with the mean size of the
round's map messages. It ends when every robot hovers or after the episode's step limit.

The team's radio is authenticated (`jaxmripp.runtime.auth`): every robot holds the same
team key and signs every message; the summary gives the mean size of each kind of message
and the messages refused. The key is derived from --seed (`team_key(seed)`), so a run
repeats byte for byte; it is no secret, which a simulation does not need. A real team
draws its key once from the operating system (`jaxmripp.runtime.team_key()`) and loads it
onto every robot. --unsigned flies without a key (messages carry no tag).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np

from jaxmripp import folders
from jaxmripp.config.cli import ArgumentParser, fail
from jaxmripp.flight.team import exchange, pads
from jaxmripp.runtime.auth import team_key
from jaxmripp.runtime.errors import RuntimeInputError
from jaxmripp.runtime.mapping import fly_until
from jaxmripp.runtime.planner import MODES, OnboardPlanner
from jaxmripp.spec.grid import HEADING_NAMES, OCCUPIED

KINDS = ("waypoints", "map", "intents")  # the round's three broadcasts


@dataclasses.dataclass
class TeamRun:
    """What `main` flew: the world, every robot's positions round by round, the windows
    found, the planners as they ended and the bytes of every message sent, by kind."""

    percent: float
    steps: int
    world: object  # the simulator's world (`jaxmripp.sim.world.World`)
    sensor: object  # its camera (`jaxmripp.config.SensorConfig`)
    height: np.ndarray  # (G, G) building heights in voxels
    valid: np.ndarray  # (T,) bool real windows
    found: np.ndarray  # (T,) bool seen by some robot
    path: list[np.ndarray]  # per round, (N, 3) float32 positions where the robots sensed
    headings: list[np.ndarray]  # per round, (N,) their headings
    blocked_moves: int  # flights a building stopped (none for known-free flights)
    planners: list[OnboardPlanner]
    message_bytes: dict[str, list[int]]  # kind -> sizes of the messages sent


def fly(height: np.ndarray, start: np.ndarray, end: np.ndarray, size: int, shell_hi: float):
    """The truth a flight meets (`jaxmripp.sim.geometry.fly_until` in NumPy): start -> end
    until the first traversed voxel inside a building (voxel z below the column's height),
    stopping midway through the last free piece. Returns (stop position, blocked)."""
    g = np.arange(size)
    solid = (g[None, None, :] < height[:, :, None]).reshape(-1)
    stop, hit, _ = fly_until(start, end, solid, size, shell_hi)
    return stop, hit


def main(argv: list[str] | None = None, prog: str = "python -m jaxmripp.demo") -> float:
    parser = ArgumentParser(prog=prog, description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--export", type=Path, default=None,
                        help="export directory (python -m jaxmripp.export RUN_DIR); "
                             "default: greedy planners")
    parser.add_argument("--planner", choices=MODES, default=None,
                        help="the runtime's mode on every robot (default: policy with "
                             "--export, else greedy)")
    parser.add_argument("--config", type=Path, default=None,
                        help="config for the world and, without --export, the planners")
    parser.add_argument("--robots", type=int, default=None, help="team size (default: config)")
    parser.add_argument("--budget", type=float, default=10.0, help="team budget B")
    parser.add_argument("--size", type=int, default=None, help="world size G (default: config)")
    parser.add_argument("--layout", default="random", choices=("grid", "random"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kappa", type=float, default=None,
                        help="greedy: weight of the utility std (default: eval.greedy_kappa)")
    parser.add_argument("--lam", type=float, default=None,
                        help="greedy: weight of the comm mean (default: eval.greedy_lambda)")
    parser.add_argument("--sectors", action="store_true",
                        help="each robot keeps to its sector of the world while it has unknown "
                             "views there (jaxmripp.spec.sectors)")
    parser.add_argument("--escape", action="store_true",
                        help="robots that met out of radio range may fly apart "
                             "(safety.escape; default: the export's setting)")
    parser.add_argument("--unsigned", action="store_true",
                        help="fly without a team key: messages are neither signed nor checked")
    parser.add_argument("--quiet", action="store_true", help="only the final lines")
    args = parser.parse_args(argv)

    import jax  # the simulated world only; planners below are NumPy

    from jaxmripp import config as cfgmod
    from jaxmripp import export as exportmod
    from jaxmripp.sim import sensing, world as worldmod

    try:
        cfg = cfgmod.load(args.config)
        exported = folders.export(args.export) if args.export is not None else None
    except (cfgmod.ConfigError, folders.FolderError, RuntimeInputError) as err:
        raise SystemExit(fail(err)) from None
    if exported is not None:
        spec, policy = exported.spec, exported.policy
        spacing = exported.header["config"]["robots"].get("pad_spacing",
                                                          cfg.robots.pad_spacing)
    else:
        spec, policy = exportmod.runtime_spec(cfg), None
        spacing = cfg.robots.pad_spacing
    size = args.size or spec.size
    spec = dataclasses.replace(spec, size=size, escape=spec.escape or args.escape)
    n = args.robots or spec.team_size
    per_robot = args.budget / n
    steps = max(spec.max_steps, int(math.ceil(per_robot / spec.shell[0])) + 4)
    kappa = cfg.eval.greedy_kappa if args.kappa is None else args.kappa
    lam = cfg.eval.greedy_lambda if args.lam is None else args.lam
    key = None if args.unsigned else team_key(args.seed)
    try:
        planners = [OnboardPlanner(spec, i, per_robot, team_size=n, policy=policy, kappa=kappa,
                                   lam=lam, max_steps=steps, seed=args.seed * 1000 + i,
                                   mode=args.planner,
                                   sectors=args.sectors,
                                   team_key=key)
                    for i in range(n)]
    except ValueError as err:
        raise SystemExit(fail(err)) from None
    world_cfg = dataclasses.replace(cfg.world, size=size, layout=args.layout,
                                    targets=(cfg.world.targets[1],) * 2)
    world = jax.jit(worldmod.generate, static_argnums=1)(jax.random.key(args.seed), world_cfg)
    height = np.asarray(world.height)
    valid = np.asarray(world.target_valid)
    target = np.asarray(world.target_voxel)[valid]
    window_voxels = (target[:, 0] * size + target[:, 1]) * size + target[:, 2]
    cast = jax.jit(jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None)),
                   static_argnums=(3, 4))

    position = pads(spec.start, n, spacing)
    heading = np.full(n, spec.start_heading, np.int32)
    blocked = np.zeros(n, bool)
    found = np.zeros(valid.shape, bool)
    rules = [name for name, on in (("sectors", args.sectors), ("escape", spec.escape)) if on]
    mode = planners[0].mode + (f" ({', '.join(rules)})" if rules else "")
    if not args.quiet:
        print(f"{n} robots, {mode} planners, G = {size}, {int(valid.sum())} windows, "
              f"B = {args.budget:g}, rho = {spec.radio_range:g}, seed {args.seed}")
    decide_seconds, map_bytes, path, headings, blocked_moves = [], [], [], [], 0
    sent = {kind: [] for kind in KINDS}

    def broadcast(kind, outbox, receive):
        sent[kind].extend(len(data) for data in outbox)
        exchange(outbox, position, spec.radio_range, receive)

    for step in range(steps + 1):
        view = cast(world, position, heading, cfg.sensor, size)
        voxels, values = np.asarray(view.voxels), np.asarray(view.values)
        seen = np.asarray(view.seen)
        found |= seen.any(axis=0)
        path.append(position.copy())
        headings.append(heading.copy())
        start = time.perf_counter()
        for i, planner in enumerate(planners):
            # The robot's window classifier: the windows among the voxels it saw OCCUPIED.
            windows = np.intersect1d(window_voxels, voxels[i][values[i] == OCCUPIED])
            planner.sense(position[i], int(heading[i]), voxels[i], values[i],
                          int(seen[i].sum()), blocked=bool(blocked[i]), windows=windows)
        broadcast("waypoints", [planner.message() for planner in planners],
                  lambda i, data: planners[i].receive(data))
        if spec.share_maps:
            outbox = [planner.map_message() for planner in planners]
            broadcast("map", outbox, lambda i, data: planners[i].receive_map(data))
            map_bytes.append([len(data) for data in outbox])
        for planner in planners:
            planner.decide()
        broadcast("intents", [planner.intent_message() for planner in planners],
                  lambda i, data: planners[i].receive_intent(data))
        decisions = [planner.resolve() for planner in planners]
        decide_seconds.append((time.perf_counter() - start) / n)
        percent = 100.0 * found.sum() / max(valid.sum(), 1)
        if not args.quiet:
            moves = "  ".join(
                f"r{i} " + ("hover" if d.hover else
                            f"({d.position[0]:.2f},{d.position[1]:.2f},{d.position[2]:.2f}) "
                            f"{HEADING_NAMES[d.heading]}")
                for i, d in enumerate(decisions))
            sizes = f"map {np.mean(map_bytes[-1]):6.0f} B/msg  " if spec.share_maps else ""
            print(f"step {step:3d}  found {percent:5.1f}%  {sizes}{moves}")
        if all(d.hover for d in decisions):
            if not args.quiet:
                for i, d in enumerate(decisions):
                    print(f"  r{i}: {d.reason}")
            break
        for i, d in enumerate(decisions):
            blocked[i] = False
            if not d.hover:
                position[i], blocked[i] = fly(height, position[i], d.position, size, spec.shell[1])
                heading[i] = d.heading
                blocked_moves += int(blocked[i])
    percent = 100.0 * found.sum() / max(valid.sum(), 1)
    print(f"found {percent:.1f}% of {int(valid.sum())} windows in {step} steps "
          f"(median {1e3 * float(np.median(decide_seconds)):.2f} ms per robot decision, "
          f"budget left {sum(float(p.budget_left) for p in planners):.3f} of {args.budget:g})")
    if spec.share_maps:
        sizes = np.asarray(map_bytes, float)
        later = sizes[1:].mean() if len(sizes) > 1 else 0.0
        print(f"map messages: mean {sizes.mean():.0f} bytes per robot per step (first step "
              f"{sizes[0].mean():.0f}, later steps {later:.0f}, largest {sizes.max():.0f})")
    refused = sum(sum(p.rejected_messages.values()) for p in planners)
    means = ", ".join(f"{kind} {np.mean(sent[kind]):.0f}" for kind in KINDS if sent[kind])
    print(f"radio: {'unsigned' if key is None else 'signed with the team key'}; mean bytes "
          f"per message: {means}; {refused} refused")
    return TeamRun(percent, step, world, cfg.sensor, height, valid, found, path, headings,
                   blocked_moves, planners, sent)


if __name__ == "__main__":
    main()
    sys.exit(0)
