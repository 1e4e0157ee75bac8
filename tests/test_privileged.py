"""The privileged critic (ppo.privileged_critic): its inputs against a NumPy count over the
true windows, the actor blind to them, and a run that trains and exports with them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from jaxmripp import config as cfgmod
from jaxmripp.export import check_layout, header
from jaxmripp.learn import policy as policymod, ppo, train as trainmod
from jaxmripp.sim import privileged
from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import EnvParams
from jaxmripp.sim.world import World

CFG = cfgmod.load("tests/smoke.yaml", ["ppo.algo=mappo", "ppo.privileged_critic=true"])


def reference(height, voxels, valid, discovered, positions):
    """The features by loops over robots, radii and windows."""
    grid = height.shape[0]
    total = max(int(valid.sum()), 1)
    remaining = [t for t in range(len(valid)) if valid[t] and not discovered[t]]
    out = []
    for position in positions:
        for radius in privileged.RADII:
            near = [t for t in remaining
                    if np.linalg.norm(position - (voxels[t] + 0.5) / grid) <= radius]
            out.append(len(near) / total)
    out.append(len(remaining) / total)
    return np.array(out, np.float32)


@struct.dataclass
class Truth:
    """What the features read of an `EnvState` (E environments)."""

    world: World
    position: jax.Array  # (E, N, 3)
    discovered: jax.Array  # (E, T)


@pytest.fixture(scope="module")
def states():
    """Random cities' windows, robots anywhere, some windows found; observations of the
    network's shapes with random global states."""
    params = EnvParams.from_config(CFG)
    rng = np.random.default_rng(4)
    envs, n, grid, slots = 6, params.n_robots, params.size, 40
    voxels = rng.integers(0, grid, (envs, slots, 3)).astype(np.int32)
    valid = np.arange(slots)[None] < rng.integers(1, slots, (envs, 1))
    world = World(height=jnp.zeros((envs, grid, grid), jnp.int32), target_voxel=voxels,
                  target_valid=valid, target_open=np.ones((envs, slots, 5), bool))
    truth = Truth(world, rng.uniform(0, 1, (envs, n, 3)).astype(np.float32),
                  rng.random((envs, slots)) < 0.3)
    zeros = Observation.zeros(params)
    obs = jax.tree.map(lambda x: np.broadcast_to(x, (envs, n, *x.shape)), zeros)
    obs = obs.replace(global_state=rng.normal(size=obs.global_state.shape).astype(np.float32),
                      mask=np.ones(obs.mask.shape, bool))
    return obs, truth


def test_features_count_the_undiscovered_windows_near_each_robot(states):
    obs, state = states
    got = np.asarray(jax.jit(jax.vmap(privileged.features))(state))
    n = state.position.shape[1]
    assert got.shape == (6, privileged.size(n))
    w = jax.tree.map(np.asarray, state.world)
    for e in range(6):
        want = reference(w.height[e], w.target_voxel[e], w.target_valid[e],
                         np.asarray(state.discovered[e]), np.asarray(state.position[e]))
        np.testing.assert_allclose(got[e], want, rtol=1e-6)
    assert (got[:, -1] < 1).any() and (got[:, :-1] > 0).any()


def test_the_critic_reads_them_and_the_actor_does_not(states):
    obs, state = states
    seen = ppo.critic_inputs(CFG, obs, state)
    extra = privileged.size(obs.mask.shape[1])
    assert seen.global_state.shape[-1] == obs.global_state.shape[-1] + extra
    np.testing.assert_array_equal(seen.features, obs.features)
    network = ppo.make_network(CFG)
    params = jax.jit(network.init)(jax.random.key(0), policymod.initial_memory(CFG.policy),
                                   privileged.observation_zeros(EnvParams.from_config(CFG), True))
    memory = jnp.zeros((*obs.mask.shape[:2], CFG.policy.width))
    apply = jax.jit(lambda o: ppo.apply_batched(network, params, memory, o))
    other = seen.replace(global_state=seen.global_state.at[..., -extra:].add(0.5))
    (m1, l1, v1), (m2, l2, v2) = apply(seen), apply(other)
    np.testing.assert_array_equal(l1, l2)
    np.testing.assert_array_equal(m1, m2)
    assert not np.allclose(v1, v2)
    # Where nobody has them (evaluation), zeros stand in: the actor is the same.
    filled = privileged.ZeroFilled(network, obs.mask.shape[1])
    m3, l3, _ = jax.jit(lambda o: ppo.apply_batched(filled, params, memory, o))(obs)
    np.testing.assert_array_equal(l3, l1)
    np.testing.assert_array_equal(m3, m1)
    # Off, the observation passes unchanged.
    plain = dataclasses.replace(CFG, ppo=dataclasses.replace(CFG.ppo, privileged_critic=False))
    assert ppo.critic_inputs(plain, obs, state) is obs


@pytest.mark.slow
def test_a_run_with_the_privileged_critic_trains_and_exports(tmp_path):
    cfg = cfgmod.load("tests/smoke.yaml", ["ppo.algo=mappo", "ppo.privileged_critic=true",
                                             "train.updates=2", "train.updates_per_chunk=2"])
    state = trainmod.train(cfg, tmp_path / "run", log=lambda _: None, quiet=True)
    records = trainmod.read_metrics(tmp_path / "run")
    assert len(records) == 2 and all(np.isfinite(r["value_loss"]) for r in records)
    kernel = state.params["params"]["global_embed"]["kernel"]
    n = cfg.robots.count
    assert kernel.shape[0] == privileged.observation_zeros(
        EnvParams.from_config(cfg), False).global_state.shape[0] + privileged.size(n)
    head = header(cfg)
    check_layout(head, policymod.flatten_params(state.params))
    # Evaluated like any run (the critic's extra inputs zero-filled).
    from jaxmripp import pipeline

    sweep_cfg = cfgmod.load("tests/smoke.yaml", ["eval.worlds=2", "eval.trials=1",
                                                   "eval.planners=[policy]"])
    planner = pipeline.sweep_planner(tmp_path / "run", sweep_cfg, "policy")
    from jaxmripp.evaluation import sweep

    result = sweep.run_sweep(sweep_cfg, {"policy": planner}, log=lambda _: None,
                             time_planning=False, keep_pictures=False)
    assert all(np.isfinite(r.discovered).all() and r.discovered.mean() > 0 for r in result.runs)
