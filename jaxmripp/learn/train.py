"""The training run: a Python loop over chunks of jitted PPO updates.

A chunk (train.updates_per_chunk updates) is one compiled call. Environments restart at
every chunk boundary, so a checkpoint needs only the network, the optimiser state, the
seed key and the update counter, and a resumed run repeats an uninterrupted one exactly.
Every random draw is keyed by `fold_in(seed key, update)`.

The environments are split over every device of every process (`parallel.mesh`) and
computed in `train.blocks` blocks (`parallel.blocks`); the state is replicated. Process
0 alone writes config.yaml and metrics.jsonl and logs; every process takes part in the
checkpoints, as orbax expects.
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxmripp import config as cfgmod
from jaxmripp.learn import ppo
from jaxmripp.learn.checkpoint import Checkpoints
from jaxmripp.config import Config
from jaxmripp.sim.observation import Observation
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.learn.policy import VIEW_PRIOR_PARAM, initial_memory
from jaxmripp.parallel.mesh import DataParallel, data_parallel, is_main_process


@struct.dataclass
class TrainState:
    params: Any
    opt_state: Any
    key: jax.Array  # (2,) uint32 seed key; never advanced, folded with `update`
    update: jax.Array  # () int32 updates done


@dataclass
class Trainer:
    """Everything about a run but its state: config, static and dynamic env params,
    network, optimiser, the device layout and the jitted chunk, `chunk(state, env_dynamic)`
    (both arguments replicated over `data`'s devices, e.g. by `place`)."""

    cfg: Config
    env_params: EnvParams
    env_dynamic: DynamicParams
    network: Any
    optimizer: Any
    data: DataParallel
    chunk: Callable[[TrainState, DynamicParams], tuple[TrainState, dict]]

    @classmethod
    @functools.lru_cache(maxsize=8)
    def build(cls, cfg: Config) -> "Trainer":
        """Cached per config, so a resumed run in the same process reuses the compiled chunk."""
        data = data_parallel()
        env_params = EnvParams.from_config(cfg)
        network = ppo.make_network(cfg)
        optimizer = ppo.make_optimizer(cfg.ppo)
        replicated = data.replicated
        chunk = jax.jit(_chunk_fn(cfg, env_params, network, optimizer, data), donate_argnums=0,
                        in_shardings=replicated, out_shardings=replicated)
        return cls(cfg, env_params, data.put_replicated(DynamicParams.from_config(cfg)),
                   network, optimizer, data, chunk)

    def chunk_dynamic(self, index: int) -> DynamicParams:
        """The dynamic parameters chunk `index` trains with (`train.radio_ranges`)."""
        ranges = self.cfg.train.radio_ranges
        if not ranges:
            return self.env_dynamic
        return self.data.put_replicated(
            self.env_dynamic.with_values(radio_range=ranges[index % len(ranges)]))

    def place(self, state: TrainState) -> TrainState:
        """The state replicated over the devices (every process passes the same state)."""
        return self.data.put_replicated(state)

    def init(self) -> TrainState:
        key = jax.random.PRNGKey(self.cfg.train.seed)
        # One compiled program: run eagerly, the initialisers compile op by op (hundreds).
        params = jax.jit(self.network.init)(jax.random.fold_in(key, 1 << 30),
                                            initial_memory(self.cfg.policy),
                                            Observation.zeros(self.env_params))
        return TrainState(params, self.optimizer.init(params), key, jnp.zeros((), jnp.int32))

    def init_from(self, params, source: str | Path) -> TrainState:
        """`init` with the network parameters `params` (of `train.init_from` = `source`)
        and an optimiser state made for them; raises ConfigError if their shapes differ.
        A source without the view prior's weight (trained with `policy.view_prior` = 0)
        starts this config's prior at its configured weight."""
        fresh = self.init()
        params = _with_prior_weight(params, fresh.params)
        want = jax.tree.map(lambda x: tuple(x.shape), fresh.params)
        got = jax.tree.map(lambda x: tuple(x.shape), params)
        if jax.tree.structure(want) != jax.tree.structure(got) or want != got:
            raise cfgmod.ConfigError(
                f"train.init_from: got {str(source)!r}, whose network differs from this "
                f"config's ({_first_difference(want, got)}); allowed: a run or export with "
                "the same policy width, heads, layers, ff_mult and critic")
        params = jax.tree.map(lambda x, like: jnp.asarray(x, like.dtype), params, fresh.params)
        return fresh.replace(params=params, opt_state=self.optimizer.init(params))


def _with_prior_weight(params, fresh):
    """`params` with fresh's view-prior weight added where fresh has one and it lacks it."""
    inner, fresh_inner = params["params"], fresh["params"]
    if VIEW_PRIOR_PARAM in fresh_inner and VIEW_PRIOR_PARAM not in inner:
        return {"params": {**inner, VIEW_PRIOR_PARAM: fresh_inner[VIEW_PRIOR_PARAM]}}
    return params


def _first_difference(want, got) -> str:
    flat_want = dict(jax.tree_util.tree_flatten_with_path(want)[0])
    flat_got = dict(jax.tree_util.tree_flatten_with_path(got)[0])
    for path in sorted(set(flat_want) | set(flat_got), key=str):
        if flat_want.get(path) != flat_got.get(path):
            return (f"{jax.tree_util.keystr(path)}: {flat_want.get(path, 'absent')} here, "
                    f"{flat_got.get(path, 'absent')} there")
    return "tree structure"


def _chunk_fn(cfg: Config, env_params: EnvParams, network, optimizer, data: DataParallel):
    def one_update(dyn, carry, _):
        state, runner = carry
        key_rollout, key_update = jax.random.split(jax.random.fold_in(state.key, state.update))
        teacher = ppo.Teacher.at(cfg.ppo, state.update)
        runner, transitions, stats = ppo.rollout(key_rollout, runner, state.params, network,
                                                 cfg, env_params, dyn, data, teacher)
        last_value = ppo.values(network, state.params, runner.memory, runner.obs,
                                cfg.train.blocks, data)
        params, opt_state, losses = ppo.update(key_update, state.params, state.opt_state,
                                               network, optimizer, transitions, last_value,
                                               cfg.ppo, cfg.train.blocks, data, teacher)
        active = transitions.active.astype(jnp.float32)
        metrics = dict(losses, episodes=stats.episodes, discovered_sum=stats.discovered,
                       return_sum=stats.episode_return, reward_parts=stats.reward_parts,
                       active_samples=active.sum())
        return (TrainState(params, opt_state, state.key, state.update + 1), runner), metrics

    def chunk(state: TrainState, dyn: DynamicParams):
        key_start = jax.random.fold_in(jax.random.fold_in(state.key, state.update), 1 << 29)
        runner = ppo.start_runner(key_start, cfg, env_params, dyn, data)
        (state, _), metrics = jax.lax.scan(functools.partial(one_update, dyn), (state, runner),
                                           None, length=cfg.train.updates_per_chunk)
        return state, metrics

    return chunk


def summarise(metrics: dict, cfg: Config) -> dict:
    """Per-chunk means of the stacked per-update metrics (host side)."""
    m = jax.tree.map(np.asarray, metrics)
    episodes = max(int(m["episodes"].sum()), 1)
    parts = m["reward_parts"].mean(axis=0)
    return {
        "discovered": float(m["discovered_sum"].sum() / episodes),
        "return": float(m["return_sum"].sum() / episodes),
        "episodes": int(m["episodes"].sum()),
        "policy_loss": float(m["policy_loss"].mean()),
        "value_loss": float(m["value_loss"].mean()),
        "entropy": float(m["entropy"].mean()),
        "approx_kl": float(m["approx_kl"].mean()),
        "imitation": float(m["imitation"].mean()),
        "r_exploration": float(parts[0]),
        "r_discovery": float(parts[1]),
        "r_communication": float(parts[2]),
    }


def fresh_run_dir(root: Path, name: str) -> Path:
    """runs/<name>, or runs/<name>-2, -3, ... so an earlier run is never overwritten."""
    candidate, n = root / name, 1
    while candidate.exists():
        n += 1
        candidate = root / f"{name}-{n}"
    return candidate


def short_chunk_warning(cfg: Config) -> str | None:
    """Why a chunk would end every episode before its end, or None.

    Environments restart at every chunk boundary, so with fewer steps per chunk than an
    episode's `episode.max_steps` the policy never learns from an episode's later steps
    and no episode is counted in the metrics."""
    steps = cfg.train.updates_per_chunk * cfg.train.rollout_steps
    if steps >= cfg.episode.max_steps:
        return None
    return (f"warning: a chunk steps each environment {steps} times (train.updates_per_chunk "
            f"x train.rollout_steps), fewer than an episode's episode.max_steps = "
            f"{cfg.episode.max_steps}; environments restart at every chunk, so no episode "
            "reaches its end: raise train.updates_per_chunk")


def train(cfg: Config, run_dir: Path, resume: bool = False, stop_after_chunks: int | None = None,
          log: Callable[[str], None] = print, initial_params: Any = None) -> TrainState:
    """Trains into run_dir (config.yaml, metrics.jsonl, checkpoints/); returns the state.

    A checkpoint restores onto whatever devices this run has (the state is replicated),
    so a run may resume with another device or process count. A new run with
    `train.init_from` starts from `initial_params`, the parameters of that run or export
    (`jaxmripp.pipeline.initial_params` reads them: exports are the runtime's format)."""
    main = is_main_process()
    log = log if main else (lambda _: None)
    run_dir.mkdir(parents=True, exist_ok=True)
    trainer = Trainer.build(cfg)
    trainer.data.check_divides(cfg.train.envs, "train.envs")
    trainer.data.check_divides(cfg.train.envs // cfg.ppo.minibatches,
                               "train.envs / ppo.minibatches (environments per minibatch)")
    if cfg.train.blocks:
        trainer.data.check_divides(cfg.train.blocks, "train.blocks")
    if (warning := short_chunk_warning(cfg)) is not None:
        log(warning)
    checkpoints = Checkpoints(run_dir / "checkpoints", cfg.train.keep_checkpoints)
    resuming = resume and checkpoints.latest_step() is not None
    if resuming:
        state = checkpoints.restore(trainer.place(trainer.init()))
        log(f"resumed {run_dir} at update {int(state.update)}")
    else:
        if cfg.train.init_from and initial_params is None:
            raise cfgmod.ConfigError(
                f"train.init_from: got {cfg.train.init_from!r} but no initial_params; "
                "allowed: its parameters passed as initial_params "
                "(jaxmripp.pipeline.initial_params)")
        state = trainer.place(trainer.init_from(initial_params, cfg.train.init_from)
                              if cfg.train.init_from else trainer.init())
        if cfg.train.init_from:
            log(f"parameters from {cfg.train.init_from}")
        if main:
            (run_dir / "config.yaml").write_text(cfgmod.to_yaml(cfg))
            (run_dir / "metrics.jsonl").write_text("")
    samples_per_update = cfg.train.envs * cfg.train.rollout_steps * cfg.robots.count
    total_chunks = cfg.train.updates // cfg.train.updates_per_chunk
    done_chunks = int(state.update) // cfg.train.updates_per_chunk
    for index in range(done_chunks, total_chunks):
        if stop_after_chunks is not None and index - done_chunks >= stop_after_chunks:
            log(f"stopped after {stop_after_chunks} chunk(s) as asked; --resume continues")
            break
        start = time.perf_counter()
        state, metrics = trainer.chunk(state, trainer.chunk_dynamic(index))
        record = summarise(metrics, cfg)
        seconds = time.perf_counter() - start
        updates = int(state.update)
        record.update(update=updates, env_steps=updates * samples_per_update,
                      seconds=round(seconds, 2),
                      agent_steps_per_s=round(cfg.train.updates_per_chunk * samples_per_update
                                              / seconds, 1))
        if main:
            with open(run_dir / "metrics.jsonl", "a") as fh:
                fh.write(json.dumps(record) + "\n")
        checkpoints.save(updates, state, record["discovered"])
        ended = (f"discovered {100 * record['discovered']:.1f}%  return {record['return']:.2f}"
                 if record["episodes"] else "no episode ended")
        log(f"chunk {index + 1}/{total_chunks}  updates {updates}  "
            f"agent-steps {record['env_steps']:,}  {record['agent_steps_per_s']:,.0f}/s  "
            f"{ended}  entropy {record['entropy']:.2f}  value-loss {record['value_loss']:.3f}")
    checkpoints.close()
    return state


def restore(cfg: Config, run_dir: Path, best: bool = False) -> TrainState:
    """A run's last (or best) checkpoint, on the default device."""
    checkpoints = Checkpoints(Path(run_dir) / "checkpoints", cfg.train.keep_checkpoints)
    try:
        return checkpoints.restore(Trainer.build(cfg).init(), best=best)
    finally:
        checkpoints.close()


def read_metrics(run_dir: Path) -> list[dict]:
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
