"""Training throughput: rollout (env + policy) vs policy alone, and PPO update speed.

python benchmarks/train.py [--envs 1024] [--steps 16] [--no-update] [--loop CHUNKS]
    [section.key=value ...]
Prints JSON lines; all figures come from one run, so their ratio is meaningful. Rollout
and policy-only calls alternate for --rounds rounds, so both see the same machine load;
rates are medians over rounds and the ratio is the median of the per-round ratios.

The ratio depends on the network as much as on the environment: the rollout costs the
policy's time plus the environment's, so a cheaper policy lowers it. `--config
benchmarks/train_paper.yaml` measures it with the paper's network (width 128, feed-forward
512), the network the performance model of docs/design.md budgets for (see
docs/performance.md, "Rollout against the policy alone"); the default config's width-64
network is much cheaper. With the update timed it also prints
`train.env_share_of_iteration`: the environment's share (rollout minus policy) of one
rollout plus its PPO update, which is what decides whether the environment slows training.

`--loop CHUNKS` times the training loop itself instead (`jaxmripp.learn.train.train` into a
temporary folder): CHUNKS + 1 chunks of `train.updates_per_chunk` updates, and
`train.loop_agent_steps_per_s` from the median time between the ends of consecutive
chunks after the first (which compiles), metrics and checkpoints included. It uses only
`train(cfg, run_dir, log=...)`, so the script can time another version of the package
(put it first on PYTHONPATH) on the same config.
"""

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from common import ArgumentParser, emit, entry_point, median_seconds  # noqa: E402
from jaxmripp import config as cfgmod  # noqa: E402
from jaxmripp.config import presets  # noqa: E402
from jaxmripp.config.cli import add_config_arguments, print_config  # noqa: E402
from jaxmripp.learn import ppo  # noqa: E402
from jaxmripp.learn import train as trainmod  # noqa: E402


@entry_point
def main(argv=None) -> int | None:
    parser = ArgumentParser(description=__doc__)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=16, help="rollout steps timed per call")
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternating rollout / policy-only timings (and update repeats)")
    parser.add_argument("--no-update", action="store_true",
                        help="skip the PPO update timing (the slowest part at 1024 envs)")
    parser.add_argument("--loop", type=int, default=0, metavar="CHUNKS",
                        help="time CHUNKS chunks of the training loop instead (after one more)")
    add_config_arguments(parser, presets.DEFAULT, "dotted overrides after --envs and --steps")
    args = parser.parse_args(argv)
    cfg = cfgmod.load(args.config, [f"train.envs={args.envs}",
                                    f"train.rollout_steps={args.steps}", *args.overrides])
    if args.print_config:
        return print_config(cfg)
    if args.loop:
        time_loop(args, cfg)
        return
    trainer = trainmod.Trainer.build(cfg)
    state = trainer.init()
    dyn = trainer.env_dynamic
    runner = jax.jit(lambda key, dyn: ppo.start_runner(key, cfg, trainer.env_params, dyn))(
        jax.random.PRNGKey(0), dyn)
    agents = args.envs * cfg.robots.count

    rollout = jax.jit(lambda key, runner, params, dyn: ppo.rollout(
        key, runner, params, trainer.network, cfg, trainer.env_params, dyn))
    run_rollout = lambda: rollout(jax.random.PRNGKey(1), runner, state.params, dyn)  # noqa: E731

    @jax.jit
    def policy_only(key, params, memory, obs):
        def body(memory, step):
            key, t = step
            # A step-dependent input, so XLA cannot hoist the encoder out of the loop.
            stepped = obs.replace(features=obs.features + 1e-6 * t)
            memory, logits, value = ppo.apply_batched(trainer.network, params, memory, stepped)
            action = ppo.distribution(logits, stepped.mask).sample(seed=key)
            return memory, (action, value)
        steps = jnp.arange(args.steps, dtype=jnp.float32)
        return jax.lax.scan(body, memory, (jax.random.split(key, args.steps), steps))

    run_policy = lambda: policy_only(  # noqa: E731
        jax.random.PRNGKey(2), state.params, runner.memory, runner.obs)
    for fn in (run_rollout, run_policy):  # compile and warm up
        jax.block_until_ready(fn())
    rounds = [(median_seconds(run_rollout, 1, warmup=0), median_seconds(run_policy, 1, warmup=0))
              for _ in range(args.rounds)]
    seconds_rollout = statistics.median(r for r, _ in rounds)
    seconds_env = statistics.median(r - p for r, p in rounds)
    rollout_rate = agents * args.steps / seconds_rollout
    policy_rate = agents * args.steps / statistics.median(p for _, p in rounds)
    ratio = statistics.median(p / r for r, p in rounds)

    shape = dict(config=args.config, envs=args.envs, robots=cfg.robots.count,
                 candidates=cfg.candidates.count, width=cfg.policy.width,
                 ff=cfg.policy.width * cfg.policy.ff_mult, world=cfg.world.size)
    emit("train.rollout_agent_steps_per_s", rollout_rate, "agent-steps/s", **shape)
    emit("train.policy_only_agent_steps_per_s", policy_rate, "agent-steps/s", **shape)
    emit("train.rollout_vs_policy_ratio", ratio, "ratio", **shape,
         per_round=[round(p / r, 3) for r, p in rounds])
    if args.no_update:
        return

    _, batch, _ = rollout(jax.random.PRNGKey(3), runner, state.params, dyn)
    last_value = jnp.zeros(batch.reward.shape[1:])
    update = jax.jit(lambda key, params, opt: ppo.update(
        key, params, opt, trainer.network, trainer.optimizer, batch, last_value, cfg.ppo,
        cfg.train.blocks))
    seconds_update = median_seconds(
        lambda: update(jax.random.PRNGKey(4), state.params, state.opt_state),
        repeats=args.rounds)
    samples = agents * args.steps * cfg.ppo.epochs

    emit("train.update_samples_per_s", samples / seconds_update, "samples/s",
         epochs=cfg.ppo.epochs, **shape)
    # What the ratio is for: how much of a training iteration (one rollout of --steps
    # steps and its PPO update) the environment takes, the rollout minus the policy.
    emit("train.env_share_of_iteration", seconds_env / (seconds_rollout + seconds_update),
         "fraction", epochs=cfg.ppo.epochs, env_s=round(seconds_env, 3),
         rollout_s=round(seconds_rollout, 3), update_s=round(seconds_update, 3), **shape)


def time_loop(args, cfg) -> None:
    """`train.loop_agent_steps_per_s`: agent-steps of a chunk over the median time between
    the ends of consecutive chunks (each end is where the loop logs its chunk line)."""
    updates = (args.loop + 1) * cfg.train.updates_per_chunk
    cfg = cfgmod.from_dict({"train": {"updates": updates, "eval_worlds": 1}}, cfg)
    ends = []
    with tempfile.TemporaryDirectory() as tmp:
        trainmod.train(cfg, Path(tmp) / "run",
                       log=lambda line: ends.append(time.perf_counter())
                       if line.startswith("chunk ") else None)
    chunk_s = statistics.median(b - a for a, b in zip(ends, ends[1:]))
    samples = cfg.train.updates_per_chunk * args.envs * args.steps * cfg.robots.count
    emit("train.loop_agent_steps_per_s", samples / chunk_s, "agent-steps/s",
         config=args.config, envs=args.envs, steps=args.steps, robots=cfg.robots.count,
         updates_per_chunk=cfg.train.updates_per_chunk, chunks=args.loop,
         per_chunk_s=[round(b - a, 2) for a, b in zip(ends, ends[1:])])


if __name__ == "__main__":
    sys.exit(main())
