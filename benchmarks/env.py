"""Environment throughput: one jitted, vmapped team step with the random planner.

Default setting (issue 4): N = 3 robots, G = 50, L = 80 candidates, 1024 environments,
everything on (ray-cast sensing with occlusion, per-robot utility and communication GPs,
radio exchange at rho = 0.3, rewards). The step (random action choice + `env.step`) is
jitted over the vmapped batch with the state donated; `env.agent_steps_per_s` is
envs x robots / the median step time (wall clock; on a shared machine it moves with the
load, so the CPU time per step and `env.agent_steps_per_cpu_s` are printed too). It is
compiled as evaluation sweeps compile simulation, with the host's `jaxmripp.sim.xla_options`
(printed with every figure as `xla_options`).

The same run times the step's parts separately on the same batch, each jitted and
vmapped alone (they are not donated, so each also pays for copying its outputs):
sensing (ray casts + team-map updates), GP updates (`feeding.feed_gps`: own pose,
peers' poses, the trace bookkeeping for r_e / r_c), GP predictions (`observe`'s posterior mean
and variance at every candidate, both GPs), candidates (`candidates.sample`), view gain
(`view.team_view_gain`, as the step computes it) and the map merge (`comms.share_maps`).
Shares are part time / step time; they need not sum to 1 (the rest is motion, radio, rewards and
copies, and XLA fuses differently when a part is compiled alone).

Usage (from the repository root): python benchmarks/env.py [--envs 1024] [--robots 3]
    [--size 50] [--repeats 5] [--print-config] [section.key=value ...]
"""

from __future__ import annotations

import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from common import (RandomTeamStepper, batch_arguments, emit, entry_point,  # noqa: E402
                    median_seconds)
from jaxmripp import config  # noqa: E402
from jaxmripp.config.cli import add_config_arguments, print_config  # noqa: E402
from jaxmripp.sim import comms, feeding, geometry, gp, maps, sensing, view  # noqa: E402
from jaxmripp.sim import xla_options  # noqa: E402
from jaxmripp.sim.xla_options import simulation_jit  # noqa: E402
from jaxmripp.sim import env as envmod  # noqa: E402
from jaxmripp.sim.params import DynamicParams, EnvParams  # noqa: E402


def setting(args) -> config.Config:
    """The config of the benchmarked setting."""
    return config.load(None, [f"world.size={args.size}", f"robots.count={args.robots}",
                              *args.overrides])


def build(args):
    """Static and dynamic env parameters of the benchmarked setting."""
    cfg = setting(args)
    return EnvParams.from_config(cfg), DynamicParams.from_config(cfg)


@entry_point
def main(argv=None) -> int | None:
    parser = batch_arguments(__doc__)
    parser.add_argument("--no-parts", action="store_true", help="skip the per-part timings")
    add_config_arguments(parser, None, "dotted overrides after --size and --robots")
    args = parser.parse_args(argv)
    if args.print_config:
        return print_config(setting(args))
    params, dyn = build(args)
    envs, n = args.envs, params.n_robots
    common = dict(envs=envs, robots=n, size=params.size, candidates=params.n_candidates,
                  gp_capacity=params.gp.capacity, backend=jax.default_backend(),
                  xla_options=xla_options.simulation())

    stepper = RandomTeamStepper(params, dyn, envs)
    start = time.perf_counter()
    stepper.reset()
    emit("env.reset_compile_and_run_s", time.perf_counter() - start, "s", **common)
    run = stepper.step

    start = time.perf_counter()
    jax.block_until_ready(run())
    emit("env.step_compile_and_run_s", time.perf_counter() - start, "s", **common)
    # Warm-up steps move the robots off the start and fill the GPs a little.
    cpu_start = time.process_time()
    seconds = median_seconds(run, repeats=args.repeats, warmup=2)
    cpu_per_step = (time.process_time() - cpu_start) / (args.repeats + 2)
    # On a shared machine the wall time depends on the load: the CPU time this process
    # used per step and the load average at the end give the context.
    emit("env.agent_steps_per_s", envs * n / seconds, "agent-steps/s", **common,
         step_s=round(seconds, 4), cpu_s_per_step=round(cpu_per_step, 4),
         cores=os.cpu_count(), load_average=round(os.getloadavg()[0], 2))
    emit("env.env_steps_per_s", envs / seconds, "env-steps/s", **common)
    # Less sensitive to other processes than wall time: agent-steps per CPU-second used
    # (XLA runs parts of a step on several threads, so wall throughput on an idle machine
    # can exceed it).
    emit("env.agent_steps_per_cpu_s", envs * n / cpu_per_step, "agent-steps/cpu-s", **common)
    # The view gain is computed only for candidates away from their robot's voxel
    # (`view.team_view_gain`): the share of slots that are not, at the last timed step.
    state = stepper.state
    slot_voxel = geometry.voxel_of(state.candidates.position[:, :, ::geometry.N_HEADINGS],
                                   params.size)
    own_voxel = geometry.voxel_of(state.position, params.size)[:, :, None]
    emit("env.slots_at_robot", float(jnp.mean(jnp.all(slot_voxel == own_voxel, axis=-1))),
         "fraction", **common)
    if args.no_parts:
        return

    # Parts of the step, each on the same batch (the current state). Parts that rewrite
    # large state (the team map, GPs) get it donated and fed back, like the step does.
    p = params

    def sensing_part(s):
        casts = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))(
            s.world, s.position, s.heading, p.sensor, p.size)
        return s.replace(team_map=maps.observe(s.team_map, casts.voxels)), casts.seen

    def gp_update_part(s):
        s, r_e, r_c = feeding.feed_gps(s, p)
        return s, r_e + r_c

    def gp_predict_part(s):
        poses = geometry.pose(s.candidates.position, s.candidates.heading)
        ugp = s.utility_gp if not p.gp.shared_utility else jax.tree.map(
            lambda x: jnp.broadcast_to(x, (n, *x.shape[1:])), s.utility_gp)
        predict = jax.vmap(gp.predict, in_axes=(0, 0, None))
        return predict(ugp, poses, p.gp), predict(s.comm_gp, poses, p.gp)

    def candidates_part(s, key, d):
        return envmod.team_candidates(key, s, comms.contacts(s.position, d.radio_range), p, d)

    def view_gain_part(s):
        return view.team_view_gain(s.team_map, s.building_top,
                                   s.candidates.position[:, ::geometry.N_HEADINGS],
                                   s.position, p.sensor, p.size)

    def share_maps_part(s, d):
        contact = comms.contacts(s.position, d.radio_range)
        return comms.share_maps(s.team_map, s.building_top, contact, p.radio.relay)

    parts = {  # name: (function, donates and returns the state, extra arguments)
        "sensing": (simulation_jit(jax.vmap(sensing_part), donate_argnums=0), True, ()),
        "gp_update": (simulation_jit(jax.vmap(gp_update_part), donate_argnums=0), True, ()),
        "gp_predict": (simulation_jit(jax.vmap(gp_predict_part)), False, ()),
        "candidates": (simulation_jit(jax.vmap(candidates_part, in_axes=(0, 0, None))), False,
                       (jax.random.split(jax.random.PRNGKey(0), envs), dyn)),
        "view_gain": (simulation_jit(jax.vmap(view_gain_part)), False, ()),
        "share_maps": (simulation_jit(jax.vmap(share_maps_part, in_axes=(0, None))), False,
                       (dyn,)),
    }
    part_seconds = {}
    for name, (fn, donated, extra) in parts.items():
        def run_part():
            if not donated:
                return fn(stepper.state, *extra)
            stepper.state, out = fn(stepper.state, *extra)
            return out

        part_seconds[name] = median_seconds(run_part, repeats=args.repeats)
        emit(f"env.part_{name}_s", part_seconds[name], "s", **common)
    # Re-time the whole step after the parts, and use the mean of both step timings, so
    # that load changes on a shared machine during the run bias the shares less.
    seconds = 0.5 * (seconds + median_seconds(run, repeats=args.repeats, warmup=0))
    emit("env.step_s", seconds, "s", **common)
    for name, value in part_seconds.items():
        emit(f"env.share_{name}", value / seconds, "fraction", **common)
    emit("env.share_gps", (part_seconds["gp_update"] + part_seconds["gp_predict"]) / seconds,
         "fraction", **common)


if __name__ == "__main__":
    sys.exit(main())
