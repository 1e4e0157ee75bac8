"""The JaxMARL adapter (jaxmripp.marl): the same episodes as jaxmripp.sim.env, the
interface JaxMARL's tooling relies on (LogWrapper, jit(vmap(step)), IPPO with and without
the action mask), and the hover rule for unavailable actions.

Compilation dominates, so four functions are compiled once for the module on the smoke
config (tests/smoke.yaml: an episode is T_max = 8 steps) and shared by every test: the
adapter's reset and step under JaxMARL's own `LogWrapper` (`jax.jit(jax.vmap(env.step))`,
as JaxMARL's baselines step it; the step restarts finished episodes), and sim.env's reset
and step as the reference. The IPPO steps the environments through that shared step, so
only its small network functions compile anew.
"""

from __future__ import annotations

from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.wrappers.baselines import LogWrapper

from jaxmripp import config
from jaxmripp.config import ConfigError
from jaxmripp.marl import MRIPPEnv
from jaxmripp.sim import env as envmod
from jaxmripp.sim.observation import N_ROBOT_STATE
from jaxmripp.sim.params import DynamicParams, EnvParams

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "tests" / "smoke.yaml"

ENV = MRIPPEnv(SMOKE)
LOGGED = LogWrapper(ENV)
N, L, T_MAX = ENV.num_agents, ENV.params.n_candidates, ENV.params.max_steps
ENVS = 2

TRACES = []  # one entry per trace of the step


def counted_step(key, state, actions):
    TRACES.append(1)
    return LOGGED.step(key, state, actions)


RESET = jax.jit(jax.vmap(LOGGED.reset))
STEP = jax.jit(jax.vmap(counted_step))
# The reference runs with parameters built here from the preset's file.
SIM_PARAMS = EnvParams.from_config(config.load(SMOKE))
SIM_DYN = DynamicParams.from_config(config.load(SMOKE))
SIM_RESET = jax.jit(jax.vmap(lambda key: envmod.reset(key, SIM_PARAMS, SIM_DYN)))
SIM_STEP = jax.jit(jax.vmap(lambda key, state, actions: envmod.step(
    key, state, actions, SIM_PARAMS, SIM_DYN)))


def sim_step(key, state, actions):
    """sim.env.step with the key JaxMARL's `MultiAgentEnv.step` hands to `step_env` (the
    first of split(key); the second draws the restart)."""
    return SIM_STEP(jax.vmap(lambda k: jax.random.split(k)[0])(key), state, actions)


def agents_axis(values: dict) -> jax.Array:
    """{agent: (E, ...)} -> (E, N, ...) ("__all__" left out)."""
    return jnp.stack([values[a] for a in ENV.agents], axis=1)


def as_dict(actions: jax.Array) -> dict:
    """(E, N) -> {agent: (E,)}."""
    return {a: actions[:, i] for i, a in enumerate(ENV.agents)}


def available(logged) -> jax.Array:
    """(E, N, L) `get_avail_actions` of the states under LogWrapper."""
    return agents_axis(jax.vmap(ENV.get_avail_actions)(logged.env_state))


def assert_trees_equal(a, b):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), strict=True)


def assert_same_as_sim(obs: dict, logged, ref_obs, ref_state):
    """The adapter's state, flat observations and available actions against sim.env's
    (E, ...): the flat observation is each robot's features row by row, then its robot
    state; the available actions are the mask."""
    assert_trees_equal(logged.env_state.env_state, ref_state)
    assert_trees_equal(logged.env_state.observation, ref_obs)
    features = np.asarray(ref_obs.features)
    expected = np.concatenate([features.reshape(*features.shape[:-2], -1),
                               np.asarray(ref_obs.robot_state)], -1)
    np.testing.assert_array_equal(agents_axis(obs), expected, strict=True)
    np.testing.assert_array_equal(available(logged), ref_obs.mask, strict=True)


# ---------------------------------------------------------------------------------------
# The environment


def test_episodes_equal_sim_env_bit_for_bit():
    key_reset, key_steps, key_act = jax.random.split(jax.random.key(0), 3)
    reset_keys = jax.random.split(key_reset, ENVS)
    obs, logged = RESET(reset_keys)
    ref_obs, ref_state = SIM_RESET(reset_keys)
    assert_same_as_sim(obs, logged, ref_obs, ref_state)
    feasible = []
    for t, (key, key_a) in enumerate(zip(jax.random.split(key_steps, (T_MAX, ENVS)),
                                          jax.random.split(key_act, T_MAX))):
        # Uniform over all L candidates: masked ones (hovers) as well as feasible ones.
        actions = jax.random.randint(key_a, (ENVS, N), 0, L)
        feasible.append(np.take_along_axis(np.asarray(ref_obs.mask), actions[..., None], -1))
        obs, logged, reward, done, info = STEP(key, logged, as_dict(actions))
        ref_obs, ref_state, ref_reward, ref_done, ref_info = sim_step(key, ref_state, actions)
        np.testing.assert_array_equal(agents_axis(reward), ref_reward, strict=True)
        np.testing.assert_array_equal(agents_axis(done), ref_done, strict=True)
        np.testing.assert_array_equal(done["__all__"], np.all(ref_done, axis=-1), strict=True)
        # Info: per-agent entries from the step's info and metrics.
        np.testing.assert_array_equal(info["moved"], ref_info.acted, strict=True)
        np.testing.assert_array_equal(info["discovered"][:, 0], ref_info.discovered_fraction)
        np.testing.assert_array_equal(info["obstacle_collisions"],
                                      ref_info.metrics.obstacle_collisions, strict=True)
        np.testing.assert_array_equal(info["robot_collisions_in_range"][:, 1],
                                      ref_info.metrics.robot_collisions_in_range, strict=True)
        assert all(v.shape == (ENVS, N) for v in info.values())
        if t < T_MAX - 1:
            assert not done["__all__"].any()
            assert_same_as_sim(obs, logged, ref_obs, ref_state)
    assert done["__all__"].all()  # the episodes ran to T_max (and were restarted)
    # The random actions took both feasible and masked candidates.
    feasible = np.concatenate(feasible)
    assert feasible.any() and not feasible.all()


def test_unavailable_actions_hover():
    """Indices outside [0, L) leave the robot where it is, charged and rewarded nothing,
    where sim.env itself would fly an index that wraps onto a feasible candidate."""
    key_reset, key_steps, key_act = jax.random.split(jax.random.key(1), 3)
    _, logged = RESET(jax.random.split(key_reset, ENVS))
    sim_flew = []
    for t, (key, key_a) in enumerate(zip(jax.random.split(key_steps, (T_MAX - 1, ENVS)),
                                          jax.random.split(key_act, T_MAX - 1))):
        mask = np.asarray(available(logged))
        # Robot 0: k - L for its first feasible candidate k (JAX's indexing wraps it onto
        # k), or L (clamped onto the last candidate); robot 1 picks uniformly.
        outside = np.argmax(mask[:, 0], -1) - L if t % 2 == 0 else np.full(ENVS, L)
        actions = jax.random.randint(key_a, (ENVS, N), 0, L).at[:, 0].set(outside)
        _, after, reward, _, info = STEP(key, logged, as_dict(actions))
        before, now = logged.env_state.env_state, after.env_state.env_state
        for field in ("position", "heading", "budget_left"):
            np.testing.assert_array_equal(getattr(now, field)[:, 0], getattr(before, field)[:, 0])
        assert (np.asarray(reward["robot_0"]) == 0).all()
        assert not np.asarray(info["moved"][:, 0]).any()
        sim_flew.append(np.asarray(sim_step(key, before, actions)[4].acted[:, 0]))
        logged = after
    assert np.any(sim_flew)


def test_preset_file_config_and_overrides():
    cfg = config.load(SMOKE, ["robots.count=3", "world.size=24"])
    for env in (MRIPPEnv(str(SMOKE), ["robots.count=3", "world.size=24"]),
                MRIPPEnv(SMOKE, ["robots.count=3", "world.size=24"]), MRIPPEnv(cfg)):
        assert env.cfg == cfg and env.params == EnvParams.from_config(cfg)
        assert env.agents == ["robot_0", "robot_1", "robot_2"]
    # A preset by name; without one, make train's.
    named = MRIPPEnv("recipe_paper", ["robots.count=4"])
    assert named.cfg == config.load(REPO / "configs" / "recipe_paper.yaml", ["robots.count=4"])
    assert named.num_agents == 4 and named.cfg.sensor.model == "frustum"
    assert MRIPPEnv().cfg == config.load(REPO / "configs" / "recipe_quick.yaml")
    with pytest.raises(ConfigError, match=r"^nosuch: no such preset; allowed: .*recipe_quick"):
        MRIPPEnv("nosuch")
    with pytest.raises(ConfigError, match=r"world.size"):
        MRIPPEnv(SMOKE, ["world.size=-3"])
    with pytest.raises(ConfigError, match=r"^overrides: allowed only with a preset"):
        MRIPPEnv(cfg, ["world.size=30"])


def test_interface():
    assert isinstance(ENV, MultiAgentEnv)
    assert ENV.agents == [f"robot_{i}" for i in range(N)] and N == 2
    size = L * ENV.params.n_features + N_ROBOT_STATE
    for agent in ENV.agents:
        assert ENV.observation_space(agent).shape == (size,)
        assert ENV.action_space(agent).n == L


# ---------------------------------------------------------------------------------------
# JaxMARL tooling


def test_jit_vmap_step_traces_once_and_restarts_finished_episodes():
    _, logged = RESET(jax.random.split(jax.random.key(2), ENVS))
    keys = jax.random.split(jax.random.key(3), (T_MAX + 1, ENVS))
    for t in range(T_MAX + 1):
        actions = {a: jnp.full((ENVS,), t % L, jnp.int32) for a in ENV.agents}
        _, logged, _, done, info = STEP(keys[t], logged, actions)
        assert (np.asarray(done["__all__"]) == (t == T_MAX - 1)).all()
        assert (np.asarray(info["returned_episode"]) == (t == T_MAX - 1)).all()
        # A finished episode restarts at step 0 within the same call.
        np.testing.assert_array_equal(logged.env_state.env_state.step,
                                      np.full(ENVS, (t + 1) % T_MAX))
    assert len(TRACES) == 1  # also over the other tests' calls


class ActorCritic(nn.Module):
    """Feed-forward actor and critic on the flat observation."""

    actions: int

    @nn.compact
    def __call__(self, x):
        hidden = nn.tanh(nn.Dense(32)(nn.tanh(nn.Dense(32)(x))))
        value = nn.Dense(1)(nn.tanh(nn.Dense(32)(x)))[..., 0]
        return nn.Dense(self.actions)(hidden), value


NETWORK, OPTIMIZER = ActorCritic(L), optax.adam(3e-4)
ROWS = ENVS * N  # one sample per robot and environment


def rows(values: dict) -> jax.Array:
    """{agent: (E, ...)} -> (ROWS, ...), environment-major."""
    stacked = agents_axis(values)
    return stacked.reshape(ROWS, *stacked.shape[2:])


def policy(params, x, avail, masked):
    """Logits and values for rows of flat observations; with `masked` (traced),
    unavailable actions get -1e9."""
    logits, value = NETWORK.apply(params, x)
    return jnp.where(masked & ~avail, -1e9, logits), value


@jax.jit
def act(params, x, avail, masked, key):
    logits, value = policy(params, x, avail, masked)
    action = jax.random.categorical(key, logits)
    return action, jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], 1)[:, 0], value


@jax.jit
def update(params, opt_state, batch, last_value, masked):
    """One epoch, one full batch (T, ROWS): GAE cut at each robot's done, clipped loss."""

    def gae(carry, t):
        advantage, next_value = carry
        keep = 1.0 - t["done"]
        delta = t["reward"] + 0.99 * next_value * keep - t["value"]
        advantage = delta + 0.99 * 0.95 * keep * advantage
        return (advantage, t["value"]), advantage

    _, advantage = jax.lax.scan(gae, (jnp.zeros_like(last_value), last_value), batch,
                                reverse=True)
    target = advantage + batch["value"]
    advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)

    def loss(params):
        logits, value = policy(params, batch["x"], batch["avail"], masked)
        log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), batch["action"][..., None],
                                       -1)[..., 0]
        ratio = jnp.exp(log_prob - batch["log_prob"])
        actor = -jnp.minimum(ratio * advantage, jnp.clip(ratio, 0.8, 1.2) * advantage).mean()
        return actor + 0.5 * ((value - target) ** 2).mean()

    value, grads = jax.value_and_grad(loss)(params)
    change, opt_state = OPTIMIZER.update(grads, opt_state)
    return optax.apply_updates(params, change), opt_state, value


def ippo(key, masked: bool, updates: int = 2):
    """IPPO with one shared network: `updates` x (T_max steps of ENVS environments, then one
    update); returns the parameters, the losses and the samples (updates, T, ROWS)."""
    key_init, key_reset, key_run = jax.random.split(key, 3)
    params = NETWORK.init(key_init, jnp.zeros(ENV.observation_space("robot_0").shape))
    opt_state = OPTIMIZER.init(params)
    obs, logged = RESET(jax.random.split(key_reset, ENVS))
    losses, batches = [], []
    for key_update in jax.random.split(key_run, updates):
        samples = []
        for key_act, key_env in jax.random.split(key_update, (T_MAX, 2)):
            x, avail = rows(obs), available(logged).reshape(ROWS, L)
            action, log_prob, value = act(params, x, avail, masked, key_act)
            obs, logged, reward, done, info = STEP(jax.random.split(key_env, ENVS), logged,
                                                   as_dict(action.reshape(ENVS, N)))
            samples.append(dict(x=x, avail=avail, action=action, log_prob=log_prob,
                                value=value, reward=rows(reward), done=rows(done),
                                info={k: v.reshape(ROWS) for k, v in info.items()}))
        batch = jax.tree.map(lambda *xs: jnp.stack(xs), *samples)
        last_value = act(params, rows(obs), available(logged).reshape(ROWS, L), masked,
                         key_update)[2]
        params, opt_state, loss = update(params, opt_state, batch, last_value, masked)
        losses.append(loss)
        batches.append(batch)
    return params, jnp.stack(losses), jax.tree.map(lambda *xs: jnp.stack(xs), *batches)


@pytest.fixture(scope="module")
def ippo_runs():
    return {masked: ippo(jax.random.key(4), masked) for masked in (False, True)}


@pytest.mark.parametrize("masked", [False, True])
def test_ippo_runs_two_updates_and_stays_finite(ippo_runs, masked):
    params, losses, batches = jax.tree.map(np.asarray, ippo_runs[masked])
    assert losses.shape == (2,) and np.isfinite(losses).all()
    assert all(np.isfinite(p).all() for p in jax.tree.leaves(params))
    avail, action = batches["avail"], batches["action"]
    taken = np.take_along_axis(avail, action[..., None], -1)[..., 0]
    can_act = avail.any(-1)
    if masked:  # the mask keeps every robot that can act to available actions
        assert taken[can_act].all()
    else:  # ignoring it, robots take unavailable actions, which hover unrewarded
        assert (~taken[can_act]).any()
        assert (batches["reward"][~taken] == 0).all()
        assert not batches["info"]["moved"][~taken].any()
    assert batches["info"]["moved"][taken].any()


@pytest.mark.parametrize("masked", [False, True])
def test_log_wrapper_returns_are_the_episode_reward_sums(ippo_runs, masked):
    batches = jax.tree.map(np.asarray, ippo_runs[masked][2])
    reward = batches["reward"].reshape(-1, ROWS)  # (updates * T, ROWS), in time order
    ended = batches["info"]["returned_episode"].reshape(reward.shape)
    returns = batches["info"]["returned_episode_returns"].reshape(reward.shape)
    assert ended.sum(0).min() >= 1  # every robot of every environment finished an episode
    running = np.zeros(ROWS)
    for t in range(reward.shape[0]):
        running += reward[t]
        np.testing.assert_allclose(returns[t][ended[t]], running[ended[t]], rtol=1e-5,
                                   atol=1e-6)
        running[ended[t]] = 0.0
