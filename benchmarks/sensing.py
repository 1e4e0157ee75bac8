"""Sensing throughput: cast + team-map update (`sim.maps.observe`) for envs x robots casts
per call.

Run from the repository root: `python benchmarks/sensing.py [--envs 1024] [--size 50]`.
Prints JSON lines; `sensing.robot_casts_per_s` is the default ray-cast camera.
"""

from __future__ import annotations

import dataclasses
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from common import (batch_arguments, emit, entry_point, median_cpu_seconds,  # noqa: E402
                    median_seconds)
from jaxmripp.sim import maps, sensing, world  # noqa: E402
from jaxmripp.config import SensorConfig, WorldConfig  # noqa: E402


def sense_step(worlds, position, heading, team_map, sensor, size):
    """(E,) worlds, (E, N, 3) positions, (E, N) headings, (E, W, G, G, G) team maps."""
    def per_env(w, pos, head, team):
        cast = jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None))
        casts = cast(w, pos, head, sensor, size)
        return maps.observe(team, casts.voxels), sensing.utility(casts)

    return jax.vmap(per_env)(worlds, position, heading, team_map)


@entry_point
def main() -> None:
    parser = batch_arguments(__doc__)
    args = parser.parse_args()
    size, envs, robots = args.size, args.envs, args.robots

    cfg = WorldConfig(size=size, layout="random")
    keys = jax.random.split(jax.random.PRNGKey(0), envs + 1)
    worlds = jax.jit(jax.vmap(lambda k: world.generate(k, cfg)))(keys[1:])
    key_p, key_h = jax.random.split(keys[0])
    position = jax.random.uniform(key_p, (envs, robots, 3), maxval=jnp.array([1.0, 1.0, 0.6]))
    heading = jax.random.randint(key_h, (envs, robots), 0, 4)

    for model in ("raycast", "frustum"):
        sensor = dataclasses.replace(SensorConfig(), model=model)
        step = jax.jit(sense_step, static_argnums=(4, 5), donate_argnums=3)
        state = {"team": jax.jit(jax.vmap(lambda w: maps.empty(w.height, robots)))(worlds)}

        def run():
            state["team"], seen = step(worlds, position, heading, state["team"], sensor, size)
            return seen

        seconds = median_seconds(run, repeats=args.repeats)
        cpu = median_cpu_seconds(run, repeats=args.repeats)
        name = "robot_casts_per_s" if model == "raycast" else f"{model}_casts_per_s"
        # cpu_seconds (all threads) is steadier than wall time when the machine is shared.
        emit(f"sensing.{name}", envs * robots / seconds, "casts/s", envs=envs, robots=robots,
             size=size, view_voxels=sensing.view_size(sensor, size),
             seconds=round(seconds, 4), cpu_seconds=round(cpu, 4))


if __name__ == "__main__":
    sys.exit(main())
