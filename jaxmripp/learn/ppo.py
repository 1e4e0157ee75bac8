"""PPO with parameter sharing: rollouts, GAE and the clipped update, all jit-able.

Every robot of every environment is a sample of one shared policy (CTDE). Shapes: T
rollout steps, E environments, N robots, W memory width. The recurrent memory is stored
with each transition and fed back unchanged in the update (one-step truncated
backpropagation through time), so minibatches of whole environments stay consistent.

With a `DataParallel` layout every E-axis array is kept split over the devices (the
environments step where they live); without one the functions are plain single-device
code. The network runs, and a minibatch's gradient is summed, over `blocks` equal blocks
of environments (`jaxmripp.parallel.blocks`), so a run gives the same parameters to the
bit on every device count that divides `blocks`.
"""

from __future__ import annotations

import functools
import math

import chex
import jax
import jax.numpy as jnp
import optax
from flax import struct

from jaxmripp.sim import belief, env as envmod, lookahead, oracle, privileged
from jaxmripp.config import Config, PPOConfig
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.sim.observation import Observation
from jaxmripp.learn.policy import ActorCritic, distribution, initial_memory
from jaxmripp.learn.search import search_targets
from jaxmripp.parallel.blocks import map_blocks, sum_blocks
from jaxmripp.parallel.mesh import DataParallel
from jaxmripp.spec import layout


NO_CHOICE = -1  # Transition.teacher where the teacher did not decide


@struct.dataclass
class Transition:
    """Leading axes (T, E, N)."""

    obs: Observation
    memory: jax.Array  # (..., W) memory the policy was given
    action: jax.Array  # (...,) int32
    log_prob: jax.Array  # (...,)
    value: jax.Array  # (...,)
    reward: jax.Array  # (...,)
    terminal: jax.Array  # (...,) bool: the robot's episode ended with this step
    active: jax.Array  # (...,) bool: the robot could act (done robots give no samples)
    # (...,) int32 the teacher's choice (ppo.teacher = nbv_ahead), NO_CHOICE where the
    # teacher did not decide; None: the loss takes the next-best-view choice on `obs`
    teacher: jax.Array | None = None
    # (..., L) float32 the search's improved policy (ppo.search_coef > 0), else None
    search: jax.Array | None = None


@struct.dataclass
class Runner:
    """The environments between two updates: what a rollout starts from and leaves
    for the next one (kept across chunks and in checkpoints, `learn.train.TrainState`)."""

    env_state: envmod.EnvState  # (E, ...)
    obs: Observation  # (E, N, ...)
    memory: jax.Array  # (E, N, W)
    episode_return: jax.Array  # (E, N) reward summed since the episode started


@struct.dataclass
class StepStats:
    """What one rollout step reports; stacked over the T steps by the scan."""

    ended: jax.Array  # () environments whose episode ended
    discovered: jax.Array  # () summed final discovered fraction of those episodes
    episode_return: jax.Array  # () summed per-robot mean return of those episodes
    reward_parts: jax.Array  # (3, E * N) r_e, r_u, r_c per robot
    acted: jax.Array  # (E * N,) bool: the robot moved this step


@struct.dataclass
class RolloutStats:
    episodes: jax.Array  # () episodes finished
    discovered: jax.Array  # () summed final discovered fraction of finished episodes
    episode_return: jax.Array  # () summed per-robot return of finished episodes
    reward_parts: jax.Array  # (3,) mean r_e, r_u, r_c per active sample


def make_network(cfg: Config) -> ActorCritic:
    learned_search = cfg.ppo.search_coef > 0 and cfg.ppo.search_value == "learned"
    return ActorCritic(cfg.policy, central_critic=cfg.ppo.algo == "mappo",
                       action_values=learned_search)


def critic_inputs(cfg: Config, obs: Observation, env_state: envmod.EnvState) -> Observation:
    """obs (E, N, ...) as the critic reads it: with `jaxmripp.sim.privileged`'s features
    under ppo.privileged_critic."""
    return privileged.appended(obs, env_state) if cfg.ppo.privileged_critic else obs


def make_optimizer(cfg: PPOConfig) -> optax.GradientTransformation:
    """Adam with the paper's staircase decay (x lr_decay every lr_decay_every steps)."""
    schedule = optax.exponential_decay(cfg.learning_rate, cfg.lr_decay_every, cfg.lr_decay,
                                       staircase=True)
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                       optax.adam(schedule, eps=1e-5))


@functools.partial(jax.jit, static_argnames="network", inline=True)
def _apply(network: ActorCritic, params, memory, obs: Observation):
    """One robot's step of the network. Jitted and inlined as `jaxmripp.sim.env` does: the
    rollout, the critic's values and the loss trace it once between them."""
    return network.apply(params, memory, obs)


@functools.partial(jax.jit, static_argnames="network", inline=True)
def _apply_with_action_values(network: ActorCritic, params, memory, obs: Observation):
    """`_apply` and the action values (L,) the network sows (`ActorCritic.action_values`)."""
    outputs, sown = network.apply(params, memory, obs, mutable=["intermediates"])
    return (*outputs, sown["intermediates"]["action_values"][0])


def apply_batched(network: ActorCritic, params, memory, obs: Observation,
                  action_values: bool = False):
    """Applies the single-robot network over any leading axes of memory / obs: new
    memory, logits and value, and with `action_values` the (..., L) action values."""
    lead = memory.shape[:-1]
    flat = lambda x: x.reshape((-1, *x.shape[len(lead):]))
    one = _apply_with_action_values if action_values else _apply
    outputs = jax.vmap(lambda m, o: one(network, params, m, o))(flat(memory),
                                                               jax.tree.map(flat, obs))
    return tuple(x.reshape((*lead, *x.shape[1:])) for x in outputs)


def act(network: ActorCritic, params, memory, obs: Observation, keys, blocks: int,
        data: DataParallel | None = None):
    """The policy's step for every robot of E environments, block by block: memory
    (E, N, W), obs (E, N, ...) and one key per environment (E, 2) -> new memory
    (E, N, W), sampled action, its log-probability, the value (E, N), the masked
    logits (E, N, L) and the action values (E, N, L) of a network with them, else None."""

    def block(inputs, params):
        memory, obs, keys = inputs
        memory, logits, value, *q = apply_batched(network, params, memory, obs,
                                                  network.action_values)
        dist = distribution(logits, obs.mask)
        # One key per environment, so a draw does not depend on the block it falls in.
        action = jax.vmap(jax.random.categorical)(keys, dist.logits)
        action_values = q[0] if q else None
        return memory, action, dist.log_prob(action), value, dist.logits, action_values

    return map_blocks(block, (memory, obs, keys), params, blocks, data)


def values(network: ActorCritic, params, memory, obs: Observation, blocks: int,
           data: DataParallel | None = None):
    """The critic's values (E, N), block by block like `act`."""
    return map_blocks(lambda inputs, params: apply_batched(network, params, *inputs)[2],
                      (memory, obs), params, blocks, data)


def _split(tree, data: DataParallel | None, axis: int = 0):
    return tree if data is None else data.constrain(tree, axis)


def start_runner(key, cfg: Config, params: EnvParams, dyn: DynamicParams,
                 data: DataParallel | None = None) -> Runner:
    keys = _split(jax.random.split(key, cfg.train.envs), data)
    obs, state = jax.vmap(envmod.reset, in_axes=(0, None, None))(keys, params, dyn)
    memory = jnp.broadcast_to(initial_memory(cfg.policy),
                              (cfg.train.envs, params.n_robots, cfg.policy.width))
    return _split(Runner(state, obs, memory, jnp.zeros((cfg.train.envs, params.n_robots))), data)


def rollout(key, runner: Runner, net_params, network: ActorCritic, cfg: Config,
            params: EnvParams, dyn: DynamicParams, data: DataParallel | None = None,
            teacher: Teacher | None = None):
    """Steps every environment `rollout_steps` times; returns (runner, transitions, stats).

    `params` is static (jit it as a closure or static argument), `dyn` may be traced. With
    ppo.teacher = nbv_ahead the transitions carry that planner's choices while
    `teacher.weight` > 0 (NO_CHOICE after, which the loss leaves out)."""
    envs = cfg.train.envs
    teach = _teacher(cfg, params) if teacher is not None else None
    key_pool, key_steps = jax.random.split(key)
    reset_obs, reset_state = _split(jax.vmap(envmod.reset, in_axes=(0, None, None))(
        _split(jax.random.split(key_pool, envs), data), params, dyn), data)
    max_resets = max(1, math.ceil(cfg.train.reset_share * envs))

    def body(carry, key):
        runner, pool_used = carry
        key_act, key_env = jax.random.split(key)
        act_keys = _split(jax.random.split(key_act, envs), data)
        offered = critic_inputs(cfg, runner.obs, runner.env_state)
        memory, action, log_prob, value, logits, action_values = act(
            network, net_params, runner.memory, offered, act_keys, cfg.train.blocks, data)
        active = jnp.any(runner.obs.mask, axis=-1)
        choice = None
        if teach is not None:
            team = jax.vmap(lambda k, o, s: teach(k, o, s, dyn))
            choice = jax.lax.cond(teacher.weight > 0, team,
                                  lambda *_: jnp.full_like(action, NO_CHOICE),
                                  act_keys, offered, runner.env_state)
        search = None
        if cfg.ppo.search_coef > 0:  # its own key, so runs without it draw as before
            search = search_targets(jax.random.fold_in(key_act, 1), cfg, runner.obs, logits,
                                    value, action_values)
        obs, state, reward, done, info, ended, pool_used = envmod.step_auto_reset(
            _split(jax.random.split(key_env, envs), data), runner.env_state, action, params,
            dyn, reset_obs, reset_state, max_resets, pool_used)
        terminal = (done & active) | ended[:, None]
        memory = jnp.where(ended[:, None, None], initial_memory(cfg.policy), memory)
        ret = runner.episode_return + reward
        stats = StepStats(
            ended=ended.sum(),
            discovered=(info.discovered_fraction * ended).sum(),
            episode_return=(ret.mean(axis=1) * ended).sum(),
            reward_parts=jnp.stack([info.reward_exploration, info.reward_discovery,
                                    info.reward_communication]).reshape(3, -1),
            acted=info.acted.reshape(-1))
        ret = jnp.where(ended[:, None], 0.0, ret)
        transition = Transition(offered, runner.memory, action, log_prob, value, reward,
                                terminal, active, choice, search)
        return (_split(Runner(state, obs, memory, ret), data), pool_used), (transition, stats)

    (runner, _), (transitions, stats) = jax.lax.scan(
        body, (runner, jnp.zeros((), jnp.int32)),
        jax.random.split(key_steps, cfg.train.rollout_steps))
    weights = stats.acted[:, None, :]
    summary = RolloutStats(
        episodes=stats.ended.sum(),
        discovered=stats.discovered.sum(),
        episode_return=stats.episode_return.sum(),
        reward_parts=(stats.reward_parts * weights).sum(axis=(0, 2))
        / jnp.maximum(weights.sum(), 1),
    )
    return runner, _split(transitions, data, axis=1), summary


def _teacher(cfg: Config, params: EnvParams):
    """choose(key, obs, state, dyn) -> the team's choices (N,) that the rollout stores for
    the loss (ppo.teacher = nbv_ahead, nbv_targets or oracle_rate, with the eval settings of
    those planners and the facade weight ppo.teacher_facade), or None where the loss
    derives the choice from the observation itself (nbv)."""
    if cfg.ppo.teacher_coef == 0 or cfg.ppo.teacher == "nbv":
        return None
    e = cfg.eval
    if cfg.ppo.teacher == "nbv_ahead":
        return lambda key, obs, state, dyn: lookahead.choose_in_turn(
            key, obs, state, dyn, params, cfg.ppo.teacher_facade, e.nbv_ahead_discount,
            e.nbv_ahead_branches, e.nbv_ahead_flights)
    # The target belief's rates (nbv_targets) or the truth's (oracle_rate and oracle_city:
    # privileged teachers that know how many windows each building has left, never where).
    rates = belief.rates_for("belief" if cfg.ppo.teacher == "nbv_targets" else "truth",
                             e.nbv_targets_strength, params.sensor, params.world)
    if cfg.ppo.teacher == "oracle_city":  # one flight, on the true city's geometry
        return lambda key, obs, state, dyn: oracle.choose_city_in_turn(
            obs.mask, state, params, oracle.view_tie(key, obs), rates(state))
    return lambda key, obs, state, dyn: lookahead.choose_in_turn(
        key, obs, state, dyn, params, cfg.ppo.teacher_facade, e.nbv_targets_discount,
        e.nbv_targets_branches, e.nbv_ahead_flights, rates=rates(state))


def gae(transitions: Transition, last_value, discount: float, lam: float):
    """Generalised advantage estimates (T, E, N) and value targets, cut at terminals."""

    def body(carry, t):
        advantage, next_value = carry
        keep = 1.0 - t.terminal.astype(jnp.float32)
        delta = t.reward + discount * next_value * keep - t.value
        advantage = delta + discount * lam * keep * advantage
        return (advantage, t.value), advantage

    _, advantages = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value), transitions,
                                 reverse=True)
    return advantages, advantages + transitions.value


@struct.dataclass
class AdvantageMoments:
    """Over a minibatch's active samples: their count, the advantages' mean and std."""

    count: jax.Array
    mean: jax.Array
    std: jax.Array


def advantage_moments(weight, advantages, blocks: int, data: DataParallel | None = None):
    """Two-pass moments of (E, ...) advantages weighted by `weight`, summed block by block."""
    sums = lambda fn, shared: sum_blocks(fn, (weight, advantages), shared, blocks, data)
    count, total = sums(lambda wa, _: (wa[0].sum(), (wa[0] * wa[1]).sum()), None)
    count = jnp.maximum(count, 1.0)
    mean = total / count
    squares = sums(lambda wa, mean: (wa[0] * (wa[1] - mean) ** 2).sum(), mean)
    return AdvantageMoments(count, mean, jnp.sqrt(squares / count) + 1e-8)


@struct.dataclass
class Teacher:
    """Kickstarting: the loss adds `weight` x the cross-entropy from the teacher's choice:
    the next-best-view choice (`layout.nbv_score` with facade weight `facade`) on each
    decided observation, or the choices the rollout stored (`Transition.teacher`)."""

    weight: jax.Array | float  # () float32, this update's weight
    facade: float = struct.field(pytree_node=False, default=0.0)

    @classmethod
    def at(cls, cfg: PPOConfig, update) -> "Teacher":
        """The weight at `update` (updates done): `cfg.teacher_coef`, falling linearly to 0
        over the first `cfg.teacher_updates` updates when that is > 0."""
        weight = jnp.float32(cfg.teacher_coef)
        if cfg.teacher_updates:
            # Updates left, in integers: a float 1 - update / total compiles to a fused
            # multiply-add that leaves a tiny positive weight at update == total, which
            # would keep the teacher running one update too long.
            total = cfg.teacher_updates
            left = jnp.clip(total - jnp.asarray(update, jnp.int32), 0, total)
            weight = weight * (left.astype(jnp.float32) / total)
        return cls(weight, cfg.teacher_facade)


NO_TEACHER = Teacher(0.0)  # a Python float: importing this module must not start JAX


def loss_fn(net_params, network, batch: Transition, advantages, targets,
            moments: AdvantageMoments, cfg: PPOConfig, teacher: Teacher = NO_TEACHER):
    """The clipped PPO loss of the samples in `batch` as their share of a minibatch's
    loss (sums over `batch` divided by the minibatch's `moments.count`), so the shares of
    a minibatch's blocks add up to its loss; returns (loss, its parts). The part
    `imitation` is `teacher`'s cross-entropy over the samples it decided, in the loss x
    `teacher.weight`."""
    _, logits, value, *q = apply_batched(network, net_params, batch.memory, batch.obs,
                                         network.action_values)
    dist = distribution(logits, batch.obs.mask)
    log_prob = dist.log_prob(batch.action)
    weight = batch.active.astype(jnp.float32)
    share = lambda x: (x * weight).sum() / moments.count
    adv = (advantages - moments.mean) / moments.std
    ratio = jnp.exp(log_prob - batch.log_prob)
    clipped = jnp.clip(ratio, 1.0 - cfg.clip, 1.0 + cfg.clip)
    policy_loss = -share(jnp.minimum(ratio * adv, clipped * adv))
    value_clipped = batch.value + jnp.clip(value - batch.value, -cfg.clip, cfg.clip)
    value_loss = 0.5 * share(jnp.maximum((value - targets) ** 2, (value_clipped - targets) ** 2))
    entropy = share(dist.entropy())
    choice = batch.teacher if batch.teacher is not None else layout.masked_argmax(
        layout.nbv_score(batch.obs.features, teacher.facade), batch.obs.mask, jnp)
    taught = jnp.any(batch.obs.mask, axis=-1) & (choice != NO_CHOICE)
    imitation = -share(jnp.where(taught, dist.log_prob(jnp.maximum(choice, 0)), 0.0))
    total = (policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
             + teacher.weight * imitation)
    parts = dict(policy_loss=policy_loss, value_loss=value_loss, entropy=entropy,
                 imitation=imitation)
    if batch.search is not None:
        # Robots with nothing feasible are inactive: `share` leaves them out.
        parts["search"] = -share((batch.search * jax.nn.log_softmax(dist.logits)).sum(-1))
        total += cfg.search_coef * parts["search"]
    if q:  # the action value of the action taken, toward the return that followed it
        taken = jnp.take_along_axis(q[0], batch.action[..., None], -1)[..., 0]
        parts["action_value_loss"] = 0.5 * share((taken - targets) ** 2)
        total += cfg.value_coef * parts["action_value_loss"]
    approx_kl = share((ratio - 1.0) - jnp.log(ratio))
    return total, dict(parts, approx_kl=approx_kl)


def update(key, net_params, opt_state, network, optimizer, transitions: Transition,
           last_value, cfg: PPOConfig, blocks: int = 0, data: DataParallel | None = None,
           teacher: Teacher = NO_TEACHER):
    """Epochs x minibatches of whole environments; returns params, opt_state, losses
    (`teacher`: see `loss_fn`)."""
    advantages, targets = gae(transitions, last_value, cfg.discount, cfg.gae_lambda)
    envs = transitions.reward.shape[1]
    chex.assert_equal(envs % cfg.minibatches, 0)
    grad_fn = jax.grad(loss_fn, has_aux=True)
    # Environment-major (E, T, N, ...), so minibatches and their blocks are leading slices.
    by_env = _split(jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1),
                                 (transitions, advantages, targets)), data)

    def epoch(carry, key):
        net_params, opt_state = carry
        order = jax.random.permutation(key, envs).reshape(cfg.minibatches, -1)

        def minibatch(carry, index):
            net_params, opt_state = carry
            batch, adv, tgt = _split(jax.tree.map(lambda x: x[index], by_env), data)
            moments = advantage_moments(batch.active.astype(jnp.float32), adv, blocks, data)
            grads, aux = sum_blocks(
                lambda b, shared: grad_fn(shared[0], network, *b, shared[1], cfg, teacher),
                (batch, adv, tgt), (net_params, moments), blocks, data)
            updates, opt_state = optimizer.update(grads, opt_state, net_params)
            return (optax.apply_updates(net_params, updates), opt_state), aux

        return jax.lax.scan(minibatch, (net_params, opt_state), order)

    (net_params, opt_state), aux = jax.lax.scan(
        epoch, (net_params, opt_state), jax.random.split(key, cfg.epochs))
    return net_params, opt_state, jax.tree.map(jnp.mean, aux)
