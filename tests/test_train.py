"""PPO and the training loop on the smoke config (one chunk compilation, shared)."""

import functools
import json
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config as cfgmod, export, pipeline
from jaxmripp.learn import policy as policymod, ppo
from jaxmripp.learn import train as trainmod
from jaxmripp.learn.checkpoint import Checkpoints, CheckpointError
from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import DynamicParams
from jaxmripp.parallel.local import host_devices_env, run_local
from jaxmripp.parallel.mesh import data_parallel
from jaxmripp.spec import layout

@pytest.fixture(scope="module")
def cfg():
    return cfgmod.load("tests/smoke.yaml")


@pytest.fixture(scope="module")
def trainer(cfg):
    return trainmod.Trainer.build(cfg)


def _leaves_equal(a, b):
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


@pytest.fixture(scope="module")
def full_run(cfg, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "full"
    state = trainmod.train(cfg, run_dir, log=lambda _: None)
    return run_dir, state


def test_smoke_run_trains_three_chunks_with_finite_metrics(cfg, full_run):
    run_dir, state = full_run
    assert int(state.update) == cfg.train.updates == 3
    records = trainmod.read_metrics(run_dir)
    assert [r["update"] for r in records] == [1, 2, 3]
    for record in records:
        for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "imitation",
                    "r_exploration", "seconds", "agent_steps_per_s"):
            assert np.isfinite(record[key]), key
        # the episode figures exactly where an episode ended
        assert ("discovered" in record) == ("return" in record) == (record["episodes"] > 0)
    # Episodes run on across the one-update chunks (4 steps each, 8-step episodes).
    assert sum(r["episodes"] for r in records) > 0
    assert all(np.isfinite(x).all() for x in jax.tree.leaves(state.params))
    assert (run_dir / "config.yaml").exists()
    assert cfgmod.load(run_dir / "config.yaml") == cfg


@pytest.mark.slow  # tests/test_train_crash.py resumes from every crash point in make test
def test_interrupted_run_resumes_to_identical_parameters(cfg, full_run, tmp_path):
    _, uninterrupted = full_run
    run_dir = tmp_path / "interrupted"
    first = trainmod.train(cfg, run_dir, stop_after_chunks=2, log=lambda _: None)
    assert int(first.update) == 2
    resumed = trainmod.train(cfg, run_dir, resume=True, log=lambda _: None)
    assert int(resumed.update) == 3
    assert _leaves_equal(resumed.params, uninterrupted.params)
    assert _leaves_equal(resumed.opt_state, uninterrupted.opt_state)
    assert _leaves_equal(resumed.runner, uninterrupted.runner)
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["update"] for line in lines] == [1, 2, 3]


def test_checkpoint_restore_gives_bit_identical_actions(cfg, trainer, full_run):
    run_dir, state = full_run
    checkpoints = Checkpoints(run_dir / "checkpoints", cfg.train.keep_checkpoints)
    restored = checkpoints.restore(trainer.abstract_state())
    # best/ is for evaluation: the network without the environments, which last/ holds
    assert checkpoints.fields()["runner"] and not checkpoints.fields(best=True)["runner"]
    checkpoints.close()
    assert int(restored.update) == int(state.update)
    assert _leaves_equal(restored.runner, state.runner)
    obs = _random_observations(jax.random.PRNGKey(3), trainer, batch=(8,))
    memory = jnp.zeros((8, cfg.policy.width))
    act = jax.jit(lambda params: ppo.apply_batched(trainer.network, params, memory, obs))
    for a, b in zip(act(state.params), act(restored.params)):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def test_checkpoint_of_another_shape_gives_one_clear_error(full_run):
    run_dir, _ = full_run
    wide = cfgmod.load("tests/smoke.yaml", ["policy.width=32"])
    template = trainmod.Trainer.build(wide).abstract_state()
    checkpoints = Checkpoints(run_dir / "checkpoints", 3)
    with pytest.raises(CheckpointError) as err:
        checkpoints.restore(template)
    checkpoints.close()
    assert "\n" not in str(err.value)


def test_init_from_a_run_or_an_export_starts_from_its_parameters(cfg, full_run, tmp_path):
    run_dir, state = full_run
    # Another team size: the attention policy's parameters do not depend on it.
    three = cfgmod.load("tests/smoke.yaml", ["robots.count=3", "train.updates=0",
                                               f"train.init_from={run_dir}"])
    started = trainmod.train(three, tmp_path / "from_run", log=lambda _: None,
                             initial_params=pipeline.initial_params(three))
    assert int(started.update) == 0
    assert _leaves_equal(started.params, state.params)
    assert not _leaves_equal(started.params, trainmod.Trainer.build(three).init().params)
    export.export(cfg, state.params, tmp_path / "export")
    exported = pipeline.trained_params(tmp_path / "export")
    assert _leaves_equal(trainmod.Trainer.build(three).init_from(exported, "export").params,
                         state.params)
    # Errors name the key: a source that is neither, another network, none passed.
    wide = cfgmod.load("tests/smoke.yaml", ["policy.width=32", "train.updates=0"])
    for problem in (lambda: pipeline.initial_params(cfgmod.from_dict(
                        {"train": {"init_from": str(tmp_path / "nowhere")}}, wide)),
                    lambda: trainmod.Trainer.build(wide).init_from(exported, "export"),
                    lambda: trainmod.train(cfgmod.from_dict({"train": {"init_from": "x"}}, wide),
                                           tmp_path / "none", log=lambda _: None)):
        with pytest.raises(cfgmod.ConfigError) as err:
            problem()
        assert str(err.value).startswith("train.init_from: ") and "\n" not in str(err.value)


def _random_observations(key, trainer, batch):
    """Observations with random features and masks (at least one feasible candidate)."""
    example = Observation.zeros(trainer.env_params)
    keys = iter(jax.random.split(key, 8))
    draw = lambda x: jax.random.normal(next(keys), (*batch, *x.shape))
    mask = jax.random.bernoulli(next(keys), 0.6, (*batch, *example.mask.shape))
    mask = mask.at[..., 0].set(True)
    return example.replace(features=draw(example.features), mask=mask,
                           robot_state=draw(example.robot_state),
                           global_state=draw(example.global_state))


@pytest.mark.parametrize("algo", ["ippo", pytest.param("mappo", marks=pytest.mark.slow)])
def test_ppo_loss_falls_on_a_fixed_batch(algo):
    cfg = cfgmod.load("tests/smoke.yaml", [f"ppo.algo={algo}"])
    trainer = trainmod.Trainer.build(cfg)
    state = trainer.init()
    steps, envs, robots = 4, cfg.train.envs, cfg.robots.count

    @jax.jit  # one compilation for the batch's many small ops (op by op they took seconds)
    def fixed_batch(params, key):
        key_obs, key_act, key_reward = jax.random.split(key, 3)
        obs = _random_observations(key_obs, trainer, (steps, envs, robots))
        memory = jnp.zeros((steps, envs, robots, cfg.policy.width))
        _, logits, value = ppo.apply_batched(trainer.network, params, memory, obs)
        dist = ppo.distribution(logits, obs.mask)
        action = dist.sample(seed=key_act)
        batch = ppo.Transition(obs=obs, memory=memory, action=action,
                               log_prob=dist.log_prob(action), value=value,
                               reward=jax.random.normal(key_reward, value.shape),
                               terminal=jnp.zeros(value.shape, bool).at[-1].set(True),
                               active=jnp.ones(value.shape, bool))
        last_value = jnp.zeros(batch.reward.shape[1:])
        advantages, targets = ppo.gae(batch, last_value, cfg.ppo.discount, cfg.ppo.gae_lambda)
        moments = ppo.advantage_moments(batch.active.astype(jnp.float32), advantages, blocks=0)
        return batch, last_value, advantages, targets, moments

    batch, last_value, advantages, targets, moments = fixed_batch(state.params,
                                                                  jax.random.PRNGKey(0))
    loss = jax.jit(lambda p: ppo.loss_fn(p, trainer.network, batch, advantages, targets,
                                         moments, cfg.ppo)[0])
    update = jax.jit(lambda key, params, opt: ppo.update(
        key, params, opt, trainer.network, trainer.optimizer, batch, last_value, cfg.ppo))
    params, opt_state = state.params, state.opt_state
    losses = [float(loss(params))]
    for i in range(4):
        params, opt_state, _ = update(jax.random.PRNGKey(10 + i), params, opt_state)
        losses.append(float(loss(params)))
    assert losses[-1] < losses[0]


@functools.lru_cache(maxsize=1)  # built once for the two loss tests
def decision_batch():
    """An untrained smoke-config network's one-step batch of random observations, env 0's
    robot 0 with nothing feasible: (trainer, params, batch, logits, advantage moments)."""
    cfg = cfgmod.load("tests/smoke.yaml")
    trainer = trainmod.Trainer.build(cfg)
    params = trainer.init().params
    envs, robots = cfg.train.envs, cfg.robots.count
    obs = _random_observations(jax.random.PRNGKey(3), trainer, (1, envs, robots))
    obs = obs.replace(mask=obs.mask.at[0, 0, 0].set(False))
    memory = jnp.zeros((1, envs, robots, cfg.policy.width))
    _, logits, value = ppo.apply_batched(trainer.network, params, memory, obs)
    active = jnp.any(obs.mask, axis=-1)
    zeros = jnp.zeros(value.shape)
    batch = ppo.Transition(obs=obs, memory=memory, action=jnp.zeros(value.shape, jnp.int32),
                           log_prob=zeros, value=value, reward=zeros,
                           terminal=jnp.ones(value.shape, bool), active=active)
    moments = ppo.advantage_moments(active.astype(jnp.float32), zeros, blocks=0)
    return trainer, params, batch, logits, moments


def test_kickstarting_adds_the_cross_entropy_from_the_next_best_view_choice():
    """`imitation` is -log pi(nbv choice) averaged over active samples, checked against a
    NumPy log-softmax; the loss adds it x ppo.teacher_coef; robots with nothing feasible
    add nothing (and no NaN). The weight falls linearly to 0 over ppo.teacher_updates."""
    facade, coef = 3.0, 0.7  # ppo.teacher_facade: not the default 2
    cfg = cfgmod.load("tests/smoke.yaml", [f"ppo.teacher_coef={coef}",
                                             f"ppo.teacher_facade={facade}"])
    trainer, params, batch, logits, moments = decision_batch()
    obs, value, active = batch.obs, batch.value, batch.active
    zeros = jnp.zeros(value.shape)
    loss = lambda teacher: ppo.loss_fn(params, trainer.network, batch, zeros,  # noqa: E731
                                       value, moments, cfg.ppo, teacher)
    total, parts = loss(ppo.Teacher.at(cfg.ppo, 0))
    plain, _ = loss(ppo.NO_TEACHER)

    f, m, z = (np.asarray(x, np.float64) for x in (obs.features, obs.mask, logits))
    names = list(layout.FEATURES)
    score = f[..., names.index("view_unknown_per_cost")] \
        + facade * f[..., names.index("view_facade_per_cost")]
    choice = np.where(m > 0, score, -np.inf).argmax(axis=-1)
    act = np.asarray(active)
    z = np.where(m[act] > 0, z[act], -np.inf)
    log_softmax = z - z.max(-1, keepdims=True)
    log_softmax -= np.log(np.exp(log_softmax).sum(-1, keepdims=True))
    picked = np.take_along_axis(log_softmax, choice[act][..., None], -1)[..., 0]
    assert not act[0, 0, 0] and act.sum() == act.size - 1
    expected = -picked.mean()
    np.testing.assert_allclose(float(parts["imitation"]), expected, rtol=1e-4)
    np.testing.assert_allclose(float(total), float(plain) + coef * expected, rtol=1e-4)

    # Choices stored by the rollout (ppo.teacher = nbv_ahead) replace the NBV choice: here
    # the feasible candidate the NBV score likes least.
    stored = np.where(m > 0, score, np.inf).argmin(axis=-1)
    _, parts = ppo.loss_fn(params, trainer.network, batch.replace(teacher=jnp.asarray(stored)),
                           zeros, value, moments, cfg.ppo, ppo.Teacher.at(cfg.ppo, 0))
    picked = np.take_along_axis(log_softmax, stored[act][..., None], -1)[..., 0]
    assert np.any(stored[act] != choice[act])
    np.testing.assert_allclose(float(parts["imitation"]), -picked.mean(), rtol=1e-4)
    # Samples the teacher did not decide (NO_CHOICE) add nothing; all of them: 0, not inf.
    undecided = stored.copy()
    undecided[0, 1] = ppo.NO_CHOICE
    kept = act.copy()
    kept[0, 1] = False
    picked = np.take_along_axis(log_softmax, undecided[act][..., None], -1)[..., 0]
    _, parts = ppo.loss_fn(params, trainer.network,
                           batch.replace(teacher=jnp.asarray(undecided)), zeros, value,
                           moments, cfg.ppo, ppo.Teacher.at(cfg.ppo, 0))
    np.testing.assert_allclose(float(parts["imitation"]),
                               -picked[kept[act]].sum() / act.sum(), rtol=1e-4)
    _, parts = ppo.loss_fn(params, trainer.network,
                           batch.replace(teacher=jnp.full(stored.shape, ppo.NO_CHOICE)),
                           zeros, value, moments, cfg.ppo, ppo.Teacher.at(cfg.ppo, 0))
    assert float(parts["imitation"]) == 0.0

    decaying = cfgmod.load("tests/smoke.yaml", [f"ppo.teacher_coef={coef}",
                                                  "ppo.teacher_updates=8"]).ppo
    weights = [float(ppo.Teacher.at(decaying, u).weight) for u in (0, 2, 8, 20)]
    np.testing.assert_allclose(weights, [coef, 0.75 * coef, 0.0, 0.0], rtol=1e-6)
    assert float(ppo.Teacher.at(cfg.ppo, 20).weight) == np.float32(coef)
    # Compiled, as the rollout computes it: exactly 0 from teacher_updates on.
    fifty = cfgmod.load("tests/smoke.yaml", ["ppo.teacher_coef=1", "ppo.teacher_updates=50"]).ppo
    jitted = jax.jit(lambda u: ppo.Teacher.at(fifty, u).weight)
    assert [float(jitted(u)) for u in (49, 50, 51)] == [np.float32(1 / 50), 0.0, 0.0]


def test_the_loss_adds_the_cross_entropy_from_the_stored_search_policy():
    """parts["search"] is -sum(pi' log pi) averaged over robots with a choice, checked
    against a NumPy log-softmax; the loss adds it x ppo.search_coef."""
    coef = 0.6
    cfg = cfgmod.load("tests/smoke.yaml", ["ppo.teacher_coef=0", f"ppo.search_coef={coef}",
                                             "policy.ahead_branches=4"])
    trainer, params, batch, logits, moments = decision_batch()
    obs, value, active = batch.obs, batch.value, batch.active
    zeros = jnp.zeros(value.shape)
    target = jax.random.dirichlet(jax.random.PRNGKey(4), jnp.ones(obs.mask.shape[-1]),
                                  value.shape) * obs.mask
    target = target / jnp.maximum(target.sum(-1, keepdims=True), 1e-9)
    total, parts = ppo.loss_fn(params, trainer.network, batch.replace(search=target), zeros,
                               value, moments, cfg.ppo)
    plain, plain_parts = ppo.loss_fn(params, trainer.network, batch, zeros, value, moments,
                                     cfg.ppo)
    assert "search" not in plain_parts

    m, z, t = (np.asarray(x, np.float64) for x in (obs.mask, logits, target))
    act = np.asarray(active)
    z = np.where(m[act] > 0, z[act], -np.inf)
    log_softmax = z - z.max(-1, keepdims=True)
    log_softmax -= np.log(np.exp(log_softmax).sum(-1, keepdims=True))
    expected = -(t[act] * np.where(t[act] > 0, log_softmax, 0.0)).sum(-1).mean()
    assert not act[0, 0, 0]
    np.testing.assert_allclose(float(parts["search"]), expected, rtol=1e-4)
    np.testing.assert_allclose(float(total), float(plain) + coef * expected, rtol=1e-4)


def test_the_learned_search_values_candidates_by_an_action_value_head():
    """ppo.search_value=learned: the network sows q = q_out(relu(q_hidden([E, d]))), one
    value per candidate (checked in NumPy from the encoder's and decoder's captured
    outputs), and leaves the actor and critic as they are; the loss adds value_coef x
    0.5 (q[action] - target)^2 averaged over robots with a choice."""
    cfg = cfgmod.load("tests/smoke.yaml", ["ppo.search_coef=1", "ppo.search_value=learned"])
    learner = trainmod.Trainer.build(cfg)
    network, params = learner.network, learner.init().params
    plain, _, batch, _, moments = decision_batch()
    assert network.action_values and not plain.network.action_values
    memory, obs = batch.memory, batch.obs
    *outputs, q = ppo.apply_batched(network, params, memory, obs, action_values=True)
    for ours, theirs in zip(outputs, ppo.apply_batched(plain.network, params, memory, obs)):
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))

    flat = lambda x: x.reshape((-1, *x.shape[3:]))  # noqa: E731  (1, E, N, ...) -> rows

    def captured(m, o):
        _, state = network.apply(params, m, o, capture_intermediates=True,
                                 mutable=["intermediates"])
        inner = state["intermediates"]
        return inner["encoder_norm"]["__call__"][0], inner["decoder"]["__call__"][0][0]

    encoded, decoded = (np.asarray(x, np.float64) for x in
                        jax.vmap(captured)(flat(memory), jax.tree.map(flat, obs)))
    w = policymod.flatten_params(params)
    pairs = np.concatenate([encoded, np.broadcast_to(decoded[:, None], encoded.shape)], -1)
    hidden = np.maximum(pairs @ w["q_hidden/kernel"] + w["q_hidden/bias"], 0.0)
    expected_q = (hidden @ w["q_out/kernel"] + w["q_out/bias"])[..., 0]
    np.testing.assert_allclose(flat(np.asarray(q)), expected_q, rtol=1e-4, atol=1e-5)

    action = jax.random.categorical(jax.random.PRNGKey(8),
                                    jnp.where(obs.mask, 0.0, -jnp.inf)).astype(jnp.int32)
    targets = jax.random.normal(jax.random.PRNGKey(9), batch.value.shape)
    taught = batch.replace(action=action)
    zeros = jnp.zeros(batch.value.shape)
    total, parts = ppo.loss_fn(params, network, taught, zeros, targets, moments, cfg.ppo)
    base, base_parts = ppo.loss_fn(params, plain.network, taught, zeros, targets, moments,
                                   cfg.ppo)
    assert "action_value_loss" not in base_parts
    act = np.asarray(batch.active)
    taken = np.take_along_axis(np.asarray(q), np.asarray(action)[..., None], -1)[..., 0]
    expected = 0.5 * ((taken - np.asarray(targets)) ** 2)[act].mean()
    assert not act.all()
    np.testing.assert_allclose(float(parts["action_value_loss"]), expected, rtol=1e-4)
    np.testing.assert_allclose(float(total), float(base) + cfg.ppo.value_coef * expected,
                               rtol=1e-4)


def _start_runner(cfg, trainer, dyn) -> ppo.Runner:
    """The runners at reset, compiled: op by op the reset takes the better part of a minute."""
    return jax.jit(lambda dyn: ppo.start_runner(jax.random.PRNGKey(0), cfg, trainer.env_params,
                                                dyn))(dyn)


# The search compiles into the rollout for one to two minutes: make test keeps the search
# (test_lookahead.py) and the loss on stored choices (test_kickstarting_...).
def _taught_rollout(overrides):
    """run(weight) -> the transitions of one rollout of the smoke config with `overrides`
    from an untrained policy, the teacher's weight `weight`; and the config."""
    cfg = cfgmod.load("tests/smoke.yaml", ["ppo.teacher_coef=1", "eval.nbv_ahead_branches=4",
                                             "eval.nbv_targets_branches=4", *overrides])
    trainer = trainmod.Trainer.build(cfg)
    dyn = DynamicParams.from_config(cfg)
    params = trainer.init().params
    runner = _start_runner(cfg, trainer, dyn)
    return jax.jit(lambda weight: ppo.rollout(
        jax.random.PRNGKey(1), runner, params, trainer.network, cfg, trainer.env_params, dyn,
        teacher=ppo.Teacher(weight, cfg.ppo.teacher_facade))[1]), cfg


@pytest.mark.slow
@pytest.mark.parametrize("teacher", ["nbv_ahead", "oracle_rate", "oracle_city"])
def test_a_planner_teacher_is_stored_by_the_rollout_while_its_weight_lasts(teacher):
    """ppo.teacher = nbv_ahead (or the privileged oracle_rate, oracle_city): the transitions carry that
    planner's choices, feasible on the observations, and some differ from the one-step NBV
    choice; with the weight at 0 the rollout skips the planner and stores NO_CHOICE."""
    run, cfg = _taught_rollout([f"ppo.teacher={teacher}"])
    taught = jax.tree.map(np.asarray, run(jnp.float32(1.0)))
    feasible = np.take_along_axis(taught.obs.mask, taught.teacher[..., None], -1)[..., 0]
    assert taught.teacher.dtype == np.int32 and np.all(feasible | ~taught.active)
    nbv = layout.masked_argmax(layout.nbv_score(taught.obs.features, cfg.ppo.teacher_facade),
                               taught.obs.mask)
    assert np.any((nbv != taught.teacher) & taught.active)
    assert np.all(np.asarray(run(jnp.float32(0.0)).teacher) == ppo.NO_CHOICE)


@pytest.mark.slow
def test_the_belief_teacher_with_an_unshakable_prior_teaches_as_nbv_ahead():
    # A prior no window moves puts every building at the prior rate: nbv_targets's search
    # is nbv_ahead's (tests/test_targets.py), so the rollouts store the same choices.
    ahead = _taught_rollout(["ppo.teacher=nbv_ahead"])[0](jnp.float32(1.0))
    targets = _taught_rollout(["ppo.teacher=nbv_targets", "eval.nbv_targets_strength=1e9"])[0](
        jnp.float32(1.0))
    assert np.any(np.asarray(ahead.active))
    np.testing.assert_array_equal(np.asarray(ahead.teacher), np.asarray(targets.teacher))


def test_gae_matches_a_hand_computed_example():
    t = ppo.Transition(obs=None, memory=None, action=None, log_prob=None,
                       value=jnp.array([[[1.0]], [[2.0]], [[0.5]]]),
                       reward=jnp.array([[[1.0]], [[0.0]], [[2.0]]]),
                       terminal=jnp.array([[[False]], [[True]], [[False]]]),
                       active=jnp.ones((3, 1, 1), bool))
    adv, targets = ppo.gae(t, jnp.array([[4.0]]), discount=0.5, lam=0.5)
    # t=2: 2 + 0.5*4 - 0.5 = 3.5; t=1 (terminal): 0 - 2 = -2; t=0: 1 + 0.5*2 - 1 + 0.25*(-2) = 0.5
    np.testing.assert_allclose(np.asarray(adv)[:, 0, 0], [0.5, -2.0, 3.5])
    np.testing.assert_allclose(np.asarray(targets)[:, 0, 0], [1.5, 0.0, 4.0])


def _smoke_command(runs) -> list[str]:
    return ["train.py", "--config", "tests/smoke.yaml", "--no-eval", "--runs", str(runs)]


def _final_params(cfg, run_dir):
    state = trainmod.restore(cfg, run_dir)
    assert int(state.update) == cfg.train.updates
    return state.params


@pytest.mark.slow  # a training compilation for 2 devices in a process of its own
def test_two_local_devices_continue_a_one_device_run_to_its_parameters(cfg, full_run,
                                                                        tmp_path):
    """Updates 2 and 3 on 2 devices, resumed from the 1-device run's first checkpoint."""
    assert data_parallel().devices == 1  # full_run is the 1-device reference
    run_dir = tmp_path / "run"
    shutil.copytree(full_run[0], run_dir)
    for later in ("2", "3"):
        shutil.rmtree(run_dir / "checkpoints" / "last" / later)
    shutil.rmtree(run_dir / "checkpoints" / "best")
    done = subprocess.run([sys.executable, "train.py", "--resume", str(run_dir), "--no-eval"],
                          env=host_devices_env(2), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"resumed {run_dir} at update 1" in done.stdout
    # train.blocks = 2 in the smoke config: bit-identical, not merely close.
    assert _leaves_equal(_final_params(cfg, run_dir), full_run[1].params)


# Two processes compile the chunk at once, both cores for over a minute (make test keeps the
# launch's check-in: test_parallel.py).
@pytest.mark.slow
def test_two_processes_give_the_one_device_parameters(cfg, full_run, tmp_path):
    results = run_local(_smoke_command(tmp_path), processes=2, timeout_s=300)
    for result in results:
        assert result.returncode == 0, result.stderr[-2000:]
    assert "run folder" in results[0].stdout and "run folder" not in results[1].stdout
    assert [p.name for p in tmp_path.iterdir()] == [cfg.train.name]  # one folder for both
    assert len(trainmod.read_metrics(tmp_path / cfg.train.name)) == cfg.train.updates
    assert _leaves_equal(_final_params(cfg, tmp_path / cfg.train.name), full_run[1].params)
