"""ActorCritic (Flax) and its NumPy runtime mirror."""

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.config import PolicyConfig
from jaxmripp.sim.observation import N_FEATURES, Observation, global_state_size
from jaxmripp.learn.policy import (
    ActorCritic,
    distribution,
    flatten_params,
    initial_memory,
    runtime_config,
)
from jaxmripp.runtime import NumpyPolicy

CONFIG = PolicyConfig(width=16, heads=2, layers=1, ff_mult=2)  # IPPO model under test
CONFIG_DEEP = PolicyConfig(width=24, heads=3, layers=2, ff_mult=3)  # central-critic model
L = 12  # candidates
ROBOTS = 3
BATCH = 16
REPO = Path(__file__).resolve().parents[1]


def random_obs(seed, batch=BATCH, candidates=L, feasible=0.5) -> Observation:
    """A batch of observations with random masks; row 0 all infeasible, row 1 one feasible.

    Inputs are drawn with NumPy: eager jax.random calls would each cost a compilation.
    """
    rng = np.random.default_rng(seed)
    mask = rng.random((batch, candidates)) < feasible
    mask[0] = False
    mask[1] = np.arange(candidates) == 3
    normal = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    return Observation(
        features=normal(batch, candidates, N_FEATURES),
        mask=mask,
        robot_state=normal(batch, 9),
        global_state=normal(batch, global_state_size(ROBOTS)),
    )


def random_memory(seed, config=CONFIG, batch=BATCH):
    return np.random.default_rng(seed).normal(size=(batch, config.width)).astype(np.float32)


def init(config, central_critic=False, scale=0.1):
    """A model and its params; `scale` adds weight noise so no output is degenerate."""
    model = ActorCritic(config, central_critic)
    obs = jax.tree.map(lambda x: x[0], random_obs(0))
    # jit: one compilation instead of hundreds of eager ops.
    params = jax.jit(model.init)(jax.random.key(1), initial_memory(config), obs)
    rng = np.random.default_rng(2)  # host-side noise: no extra compilation
    noisy = lambda x: np.float32(np.asarray(x) + scale * rng.normal(size=x.shape))  # noqa: E731
    params = jax.tree.map(noisy, params)
    return model, params


def batched(model):
    """jit(vmap(apply)) over a leading batch axis of memory and observation."""
    return jax.jit(jax.vmap(model.apply, in_axes=(None, 0, 0)))


@pytest.fixture(scope="module")
def ippo():
    model, params = init(CONFIG)
    return CONFIG, model, params, batched(model)


@pytest.fixture(scope="module")
def mappo():
    model, params = init(CONFIG_DEEP, central_critic=True)
    return CONFIG_DEEP, model, params, batched(model)


def test_shapes_unbatched_and_vmapped(ippo):
    config, model, params, apply = ippo
    obs, memory = random_obs(3), random_memory(4)
    new_memory, logits, value = apply(params, memory, obs)
    chex.assert_shape([new_memory, logits, value], [(BATCH, config.width), (BATCH, L), (BATCH,)])
    chex.assert_type([new_memory, logits, value], jnp.float32)

    one = jax.jit(model.apply)(params, memory[5], jax.tree.map(lambda x: x[5], obs))
    chex.assert_trees_all_close(one, (new_memory[5], logits[5], value[5]), atol=1e-5)
    chex.assert_shape(initial_memory(config), (config.width,))


def test_masked_candidates_have_probability_zero(ippo):
    _, _, params, apply = ippo
    obs = random_obs(5)
    _, logits, _ = apply(params, random_memory(6), obs)

    @jax.jit
    def probs_and_samples(logits, mask):
        dist = distribution(logits, mask)
        return dist.probs, dist.sample(seed=jax.random.key(7), sample_shape=256)

    probs, samples = map(np.asarray, probs_and_samples(logits, obs.mask))
    has_feasible = obs.mask.any(axis=1)
    assert np.all(probs[~obs.mask & has_feasible[:, None]] == 0.0)
    np.testing.assert_allclose(probs.sum(axis=1), 1.0, rtol=1e-5)
    picked = np.take_along_axis(obs.mask[None], samples[..., None], axis=2)[..., 0]
    assert np.all(picked | ~has_feasible[None])
    assert probs[1, 3] == 1.0  # the single feasible candidate takes it all


def test_all_masked_row_is_finite_including_gradients(ippo):
    config, model, params, _ = ippo
    obs = jax.tree.map(lambda x: x[0], random_obs(8))
    assert not obs.mask.any()
    # Infeasible candidates may be padded with anything, even NaN.
    obs = obs.replace(features=np.full_like(obs.features, np.nan))

    def loss(params):
        memory, logits, value = model.apply(params, initial_memory(config), obs)
        dist = distribution(logits, obs.mask)
        log_prob, entropy = dist.log_prob(0), dist.entropy()
        return log_prob + entropy + value + memory.sum(), (logits, log_prob, entropy)

    (total, (logits, log_prob, entropy)), grads = jax.jit(
        jax.value_and_grad(loss, has_aux=True)
    )(params)
    assert all(np.all(np.isfinite(x)) for x in (total, logits, log_prob, entropy))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))
    np.testing.assert_allclose(entropy, np.log(L), rtol=1e-5)  # uniform


def test_infeasible_candidates_do_not_change_outputs(ippo):
    _, _, params, apply = ippo
    obs, memory = random_obs(9), random_memory(10)
    noise = 100.0 * np.random.default_rng(11).normal(size=obs.features.shape)
    other = obs.replace(features=np.where(obs.mask[..., None], obs.features, noise))
    chex.assert_trees_all_close(apply(params, memory, obs), apply(params, memory, other), atol=1e-5)


def test_memory_is_recurrent(ippo):
    _, _, params, apply = ippo
    obs = random_obs(12)
    a = apply(params, random_memory(13), obs)
    b = apply(params, random_memory(14), obs)
    assert not np.allclose(np.asarray(a[1])[obs.mask], np.asarray(b[1])[obs.mask])
    assert not np.allclose(a[0], b[0])


def test_jitted_apply_is_traced_once(ippo):
    _, model, params, _ = ippo
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def apply(params, memory, obs):
        return jax.vmap(model.apply, in_axes=(None, 0, 0))(params, memory, obs)

    for seed in range(3):
        apply(params, random_memory(30 + seed), random_obs(20 + seed))


def test_central_critic_reads_global_state_and_actor_does_not(ippo, mappo):
    assert "global_embed" in mappo[2]["params"] and "global_embed" not in ippo[2]["params"]
    for config, _, params, apply in (ippo, mappo):
        obs, memory = random_obs(15), random_memory(16, config)
        moved = obs.replace(global_state=obs.global_state + 1.0)
        m1, logits1, value1 = apply(params, memory, obs)
        m2, logits2, value2 = apply(params, memory, moved)
        chex.assert_trees_all_close((m1, logits1), (m2, logits2))  # the actor is local
        if config is CONFIG_DEEP:
            assert not np.allclose(value1, value2)
        else:
            chex.assert_trees_all_close(value1, value2)


@pytest.mark.parametrize("fixture", ["ippo", "mappo"])
def test_numpy_runtime_matches_flax(fixture, request):
    config, model, params, apply = request.getfixturevalue(fixture)
    central_critic = model.central_critic
    obs, memory = random_obs(17), random_memory(18, config)
    memories, logits, values = map(np.asarray, apply(params, memory, obs))

    runtime = NumpyPolicy(flatten_params(params), runtime_config(config, central_critic))
    compared = 0
    for b in range(BATCH):
        o = jax.tree.map(lambda x: x[b], obs)
        m, lg, v = runtime(memory[b], o.features, o.mask, o.robot_state, o.global_state)
        assert m.dtype == lg.dtype == np.float32 and lg.shape == (L,) and np.ndim(v) == 0
        np.testing.assert_allclose(m, memories[b], atol=1e-4)
        np.testing.assert_allclose(lg, logits[b], atol=1e-4)
        np.testing.assert_allclose(v, values[b], atol=1e-4)
        if o.mask.any():
            top2 = np.sort(logits[b])[-2:]
            if top2[1] - top2[0] > 1e-3:  # a near tie may flip within float rounding
                assert np.argmax(lg) == np.argmax(logits[b])
                compared += 1
            _, action = runtime.act(memory[b], o.features, o.mask, o.robot_state)
            assert o.mask[action]
    assert compared >= BATCH // 2


def test_numpy_runtime_rejects_incomplete_weights(ippo):
    config, _, params, _ = ippo
    weights = flatten_params(params)
    del weights["decoder/attention/key/kernel"]
    with pytest.raises(KeyError, match="decoder/attention/key/kernel"):
        NumpyPolicy(weights, runtime_config(config))


def test_runtime_never_imports_jax(ippo, tmp_path):
    config, _, params, _ = ippo
    np.savez(tmp_path / "weights.npz", **flatten_params(params))
    script = textwrap.dedent(f"""
        import sys
        import numpy as np
        import jaxmripp.runtime as runtime
        weights = dict(np.load({str(tmp_path / "weights.npz")!r}))
        policy = runtime.NumpyPolicy(weights, {runtime_config(config)!r})
        rng = np.random.default_rng(0)
        memory, logits, value = policy(policy.initial_memory(),
                                       rng.normal(size=({L}, {N_FEATURES})),
                                       rng.random({L}) < 0.5, rng.normal(size=9))
        assert np.isfinite(value) and logits.shape == ({L},)
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("jax", "jaxlib", "flax"))
        assert not leaked, leaked
    """)
    subprocess.run([sys.executable, "-c", script], cwd=REPO, check=True)


@pytest.mark.slow
@pytest.mark.parametrize("width", [64, 128])
def test_forward_throughput(width):
    """Prints jitted forward passes/s for 3072 observations at L = 80 (no assertion)."""
    batch, candidates = 3072, 80
    config = PolicyConfig(width=width, heads=4, layers=1, ff_mult=4)
    model, params = init(config)
    apply = batched(model)
    obs, memory = random_obs(19, batch, candidates), random_memory(20, config, batch)
    jax.block_until_ready(apply(params, memory, obs))  # compile
    calls, start = 0, time.perf_counter()
    while calls < 3 or time.perf_counter() - start < 5.0:
        jax.block_until_ready(apply(params, memory, obs))
        calls += 1
    rate = calls * batch / (time.perf_counter() - start)
    print(f"\npolicy forward, width {width}, L {candidates}, batch {batch}: "
          f"{rate:,.0f} passes/s on {jax.devices()[0].platform}")


def test_the_runtime_refuses_a_policy_with_the_removed_view_prior(ippo):
    """An export from before the next-best-view prior was removed: its logits would not
    be this network's, so the runtime refuses it."""
    _, _, params, _ = ippo
    older = {**runtime_config(CONFIG), "view_prior": True}
    with pytest.raises(ValueError, match="view_prior: a policy with the next-best-view prior"):
        NumpyPolicy(flatten_params(params), older)
    NumpyPolicy(flatten_params(params), {**older, "view_prior": False})
