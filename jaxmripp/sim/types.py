"""The environment's state and what a step reports: pytrees of arrays, per-robot data
stacked on a leading robot axis of size N."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from jaxmripp.sim import candidates as cands
from jaxmripp.sim import gp, maps, world as worldmod


@struct.dataclass
class Metrics:
    """Counts summed over the episode's steps (the rules of jaxmripp.spec.flight)."""

    obstacle_collisions: jax.Array  # (N,) int32 flights that entered a building (truth)
    blocked: jax.Array  # (N,) int32 flights cut short where the map stops being known free
    held: jax.Array  # (N,) int32 chosen flights given up for a lower-id robot's intent
    robot_collisions_in_range: jax.Array  # () int32 pairs closer than d_c, in radio range
    robot_collisions_out_of_range: jax.Array  # () int32 ... out of radio range
    distance: jax.Array  # (N,) float32 path length flown
    contacts: jax.Array  # () int32 robot pairs in radio contact, summed over steps

    @classmethod
    def zeros(cls, n: int) -> "Metrics":
        count = jnp.zeros((n,), jnp.int32)
        none = jnp.zeros((), jnp.int32)
        return cls(count, count, count, none, none, jnp.zeros((n,), jnp.float32), none)


@struct.dataclass
class EnvState:
    """N robots, T target slots, G voxels per side, H = T_max + 1 history entries, W =
    maps.words(N) bytes per voxel of the team map."""

    world: worldmod.World
    position: jax.Array  # (N, 3) float32
    heading: jax.Array  # (N,) int32 index into geometry.HEADING_ANGLES
    budget_left: jax.Array  # (N,) float32
    budget_initial: jax.Array  # () float32 per-robot share of the team budget
    done: jax.Array  # (N,) bool: out of affordable candidates or out of steps
    team_map: jax.Array  # (W, G, G, G) uint8 the robots' maps as bits (sim.maps)
    building_top: jax.Array  # (N, G, G) int8 per-robot building tops (jaxmripp.spec.view)
    heard: jax.Array  # (N, N) bool robots in radio range at the current positions
    discovered: jax.Array  # (T,) bool: found by anybody
    history_pose: jax.Array  # (N, H, 4) poses each robot visited, in order
    history_utility: jax.Array  # (N, H) normalised number of windows seen from each
    know: jax.Array  # (N, N) int32: robot i knows the first know[i, j] entries of j's history
    fed: jax.Array  # (N, N) int32: entries of j's history already in robot i's GPs
    utility_gp: gp.GPState  # leading axis N (or 1 with a shared utility GP)
    comm_gp: gp.GPState  # leading axis N
    candidates: cands.Candidates  # (N, L) the poses the current observation offers
    step: jax.Array  # () int32
    metrics: Metrics

    @property
    def occupancy(self) -> jax.Array:
        """(..., N, G, G, G) int8 the robots' maps (geometry codes), derived from `team_map`
        (also for states with leading batch axes)."""
        return maps.robot_maps(self.team_map, self.position.shape[-2])


@struct.dataclass
class StepInfo:
    reward_exploration: jax.Array  # (N,) r_e
    reward_discovery: jax.Array  # (N,) r_u, new targets (ties split evenly)
    reward_communication: jax.Array  # (N,) r_c
    discovered_fraction: jax.Array  # ()
    acted: jax.Array  # (N,) bool: the robot was active and its action counted this step
    metrics: Metrics


def discovered_fraction(state: EnvState) -> jax.Array:
    """Share of the world's real windows found so far (divides by the real count)."""
    total = jnp.maximum(state.world.target_valid.sum(), 1)
    return (state.discovered & state.world.target_valid).sum() / total


def episode_done(state: EnvState) -> jax.Array:
    return jnp.all(state.done)
