"""`jaxmripp.sim.env` as a JaxMARL `MultiAgentEnv`, its transition unchanged.

Agents `robot_0` .. `robot_{N-1}`; L candidates, F features per candidate, S = 9 robot
state values (`jaxmripp.sim.observation`). Per agent:

    observation  (L * F + S,) float32: the candidate features (L, F) row by row, then the
                 robot state (`flat_observation`); no memory. The team's structured
                 `Observation` (features, mask, robot state, global state for a
                 centralised critic) is `MRIPPState.observation`, leading axis N.
    action       Discrete(L): the index of a candidate pose.
    available    `get_avail_actions`: the env's safety mask, the feasible candidates of a
                 robot that is not done (a robot that is done has none).
    reward       `sim.env.step`'s reward, the one the trainer learns from (alpha r_e +
                 beta r_u + gamma r_c; 0 for a robot that did not move).
    done         out of affordable candidates, or the episode out of steps; "__all__":
                 every robot is done, and `step` starts a new episode (JaxMARL's rule).

An action that is not available (a masked candidate, any action of a robot that is done,
an integer outside [0, L)) makes the robot hover: it keeps its pose and heading, is
charged nothing and rewarded nothing, while it still senses from where it is and the
step counter advances. For masked candidates that is `sim.env.step`'s own rule; an index
outside [0, L) is marked unavailable for that step, where JAX's indexing would otherwise
clamp or wrap it onto a real candidate.

Every `info` entry has shape (N,), as JaxMARL's baselines reshape info to one row per
agent: `discovered` (the share of the world's windows found so far, the same for every
robot), `moved` (the robot flew this step), and the episode's counts so far of
`obstacle_collisions`, `blocked` and `held` flights (per robot) and of
`robot_collisions_in_range` / `robot_collisions_out_of_range` (the team's, repeated per
robot; `jaxmripp.spec.flight` defines them all).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
from flax import struct
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.environments.spaces import Box, Discrete

from jaxmripp.config import Config, ConfigError, load, presets
from jaxmripp.sim import env as envmod
from jaxmripp.sim.observation import N_ROBOT_STATE, Observation
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.sim.types import EnvState


def load_config(source: str | Path = presets.DEFAULT,
                overrides: Sequence[str] = ()) -> Config:
    """A preset name (`recipe_quick`: jaxmripp/configs/recipe_quick.yaml, the default) or a
    config file, with dotted overrides (`world.size=64`), read and validated by
    `jaxmripp.config.load`; a bad name, file or value raises `ConfigError` with one line."""
    return load(source, overrides)


def flat_observation(obs: Observation) -> jax.Array:
    """(..., L, F) features and (..., S) robot state -> (..., L * F + S) float32."""
    features = obs.features.reshape(*obs.features.shape[:-2], -1)
    return jnp.concatenate([features, obs.robot_state], axis=-1).astype(jnp.float32)


@struct.dataclass
class MRIPPState:
    env_state: EnvState
    observation: Observation  # (N, ...) the team's observations of env_state


class MRIPPEnv(MultiAgentEnv):
    """The multi-robot informative path planning env for JaxMARL (see the module doc).

    `config`: a preset name, a config file or a `Config`; `overrides` (`section.key=value`)
    apply to a preset or file. `cfg`, `params` (static) and `dyn` (traced values) are the
    `jaxmripp.sim.env` parameters the env runs with.
    """

    def __init__(self, config: str | Path | Config = presets.DEFAULT,
                 overrides: Sequence[str] = ()):
        if isinstance(config, Config):
            if overrides:
                raise ConfigError("overrides: allowed only with a preset name or config "
                                  "file; change a Config with dataclasses.replace")
            cfg = config
        else:
            cfg = load_config(config, overrides)
        self.cfg = cfg
        self.params = EnvParams.from_config(cfg)
        self.dyn = DynamicParams.from_config(cfg)
        super().__init__(num_agents=self.params.n_robots)
        self.agents = [f"robot_{i}" for i in range(self.num_agents)]
        candidates = self.params.n_candidates
        size = candidates * self.params.n_features + N_ROBOT_STATE
        self.observation_spaces = {a: Box(-jnp.inf, jnp.inf, (size,), jnp.float32)
                                   for a in self.agents}
        self.action_spaces = {a: Discrete(candidates) for a in self.agents}

    @property
    def agent_classes(self) -> dict:
        return {"robot": list(self.agents)}

    @partial(jax.jit, static_argnums=(0,))
    def reset(self, key: jax.Array) -> tuple[dict, MRIPPState]:
        obs, env_state = envmod.reset(key, self.params, self.dyn)
        state = MRIPPState(env_state, obs)
        return self.get_obs(state), state

    def step_env(self, key: jax.Array, state: MRIPPState, actions: dict):
        """One `sim.env.step` with `actions` {agent: candidate index} (no restart)."""
        chosen = jnp.stack([jnp.asarray(actions[a]) for a in self.agents]).astype(jnp.int32)
        count = self.params.n_candidates
        inside = (chosen >= 0) & (chosen < count)
        env_state = state.env_state
        cands = env_state.candidates
        env_state = env_state.replace(candidates=cands.replace(valid=cands.valid & inside[:, None]))
        obs, env_state, reward, done, step_info = envmod.step(
            key, env_state, jnp.clip(chosen, 0, count - 1), self.params, self.dyn)
        state = MRIPPState(env_state, obs)
        rewards = {a: reward[i] for i, a in enumerate(self.agents)}
        dones = {a: done[i] for i, a in enumerate(self.agents)}
        dones["__all__"] = envmod.episode_done(env_state)
        return self.get_obs(state), state, rewards, dones, self._info(step_info)

    def _info(self, step_info) -> dict:
        team = lambda x: jnp.broadcast_to(x, (self.num_agents,))  # noqa: E731
        m = step_info.metrics
        return {
            "discovered": team(step_info.discovered_fraction.astype(jnp.float32)),
            "moved": step_info.acted,
            "obstacle_collisions": m.obstacle_collisions,
            "blocked": m.blocked,
            "held": m.held,
            "robot_collisions_in_range": team(m.robot_collisions_in_range),
            "robot_collisions_out_of_range": team(m.robot_collisions_out_of_range),
        }

    def get_obs(self, state: MRIPPState) -> dict:
        flat = flat_observation(state.observation)
        return {a: flat[i] for i, a in enumerate(self.agents)}

    def get_avail_actions(self, state: MRIPPState) -> dict:
        mask = state.observation.mask
        return {a: mask[i] for i, a in enumerate(self.agents)}
