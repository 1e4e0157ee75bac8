"""The training run: a Python loop over chunks of jitted PPO updates.

A chunk (train.updates_per_chunk updates) is one compiled call: a `lax.scan` over updates
whose carry is the whole `TrainState`, the network, optimiser state, seed key and update
counter and the runner (every environment's state, observations, memories and running
returns). Environments carry on from one chunk to the next and every random draw is keyed
by `fold_in(seed key, update)`, so the chunk size decides only how often metrics reach
the host and checkpoints are saved: a run gives the same parameters to the bit with any
chunk size, and resumed from any of its checkpoints (which hold the runner too).

The environments are split over every device of every process (`parallel.mesh`) and
computed in `train.blocks` blocks (`parallel.blocks`): the runner is split over the
devices, the rest of the state replicated. Process 0 alone writes config.yaml and the
metrics (`learn.metrics`), logs and shows progress; every process takes part in the
checkpoints, as orbax expects. A chunk's metrics are written before its checkpoint, and a
resumed run drops those past the checkpoint it restores (`learn.metrics`), so a run
killed at any point and resumed records every update once.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxmripp import config as cfgmod
from jaxmripp.config import Config
from jaxmripp.learn import metrics as metricsmod, ppo, rundir
from jaxmripp.learn.checkpoint import Checkpoints
from jaxmripp.learn.params import first_difference
from jaxmripp.learn.policy import initial_memory
from jaxmripp.parallel import progress
from jaxmripp.parallel.mesh import DataParallel, data_parallel, is_main_process
from jaxmripp.sim import privileged
from jaxmripp.sim.params import DynamicParams, EnvParams

# Re-exported: the run folder's helpers are used through this module.
fresh_run_dir = rundir.fresh_run_dir
read_metrics = metricsmod.read_metrics

RUNNER_SALT = 1 << 29  # fold_in(fold_in(seed key, update), RUNNER_SALT): fresh environments
PARAMS_SALT = 1 << 30  # fold_in(seed key, PARAMS_SALT): the network's initialisation
SAVED_FIELDS = ("params", "opt_state", "key", "update")  # all but the runner


@struct.dataclass
class TrainState:
    params: Any
    opt_state: Any
    key: jax.Array  # (2,) uint32 seed key; never advanced, folded with `update`
    update: jax.Array  # () int32 updates done
    # The environments between two updates, (E, ...) split over the devices; None before
    # the first chunk starts them (`Trainer.start_runner`) and where only the network was
    # restored (`restore`)
    runner: ppo.Runner | None


@dataclasses.dataclass
class Trainer:
    """Everything about a run but its state: config, static and dynamic env params,
    network, optimiser, the device layout and the jitted chunks, `chunk_fn(length)(state,
    env_dynamic)` (`state` laid out as `place` does, `env_dynamic` replicated)."""

    cfg: Config
    env_params: EnvParams
    env_dynamic: DynamicParams
    network: Any
    optimizer: Any
    data: DataParallel
    # Built once per Trainer: jitted functions ("start", chunk lengths), the state's
    # shapes ("shapes", "runner shapes": tracing the reset takes seconds) and compiled
    # chunks (("compiled", length))
    _cache: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def build(cls, cfg: Config) -> "Trainer":
        """The trainer of `cfg`. Configs that differ only in what a resumed run may change
        (`rundir.training_part`) share their compiled programs within a process, so a
        resumed run or another chunk size reuses what was compiled."""
        return dataclasses.replace(cls._build(rundir.training_part(cfg)), cfg=cfg)

    @classmethod
    @functools.lru_cache(maxsize=8)
    def _build(cls, cfg: Config) -> "Trainer":
        data = data_parallel()
        return cls(cfg, EnvParams.from_config(cfg),
                   data.put_replicated(DynamicParams.from_config(cfg)),
                   ppo.make_network(cfg), ppo.make_optimizer(cfg.ppo), data)

    @property
    def shardings(self) -> TrainState:
        """The state's layout (a prefix of its tree): the runner split, the rest replicated."""
        rep = self.data.replicated
        return TrainState(rep, rep, rep, rep, self.data.split())

    def chunk_fn(self, length: int) -> Callable:
        """The jitted chunk of `length` updates: (state, env_dynamic) -> (state, metrics
        stacked over the updates); the state is donated."""
        if length not in self._cache:
            self._cache[length] = jax.jit(
                _chunk_fn(self.cfg, self.env_params, self.network, self.optimizer, self.data,
                          length), donate_argnums=0,
                in_shardings=(self.shardings, self.data.replicated),
                out_shardings=(self.shardings, self.data.replicated))
        return self._cache[length]

    @property
    def chunk(self) -> Callable:
        """The chunk of train.updates_per_chunk updates."""
        return self.chunk_fn(self.cfg.train.updates_per_chunk)

    def compiled(self, length: int, state: TrainState, quiet: bool = False):
        """The chunk of `length` updates compiled for `state`'s layout (once per length),
        with a progress line while it compiles."""
        if ("compiled", length) not in self._cache:
            updates = f"{length} update{'s' if length > 1 else ''}"
            with progress.compiling(f"the training chunk ({updates})", quiet):
                self._cache["compiled", length] = self.chunk_fn(length).lower(
                    state, self.env_dynamic).compile()
        return self._cache["compiled", length]

    def place(self, state: TrainState) -> TrainState:
        """The state laid out over the devices: the runner split, the rest replicated
        (every process passes the same state)."""
        runner = state.runner
        state = self.data.put_replicated(state.replace(runner=None))
        return state.replace(runner=self.data.put_split(runner))

    def start_runner(self, key: jax.Array, update: int) -> ppo.Runner:
        """Fresh environments for the update after `update` done ones, split over the
        devices, drawn from the seed key `key`."""
        if "start" not in self._cache:
            self._cache["start"] = jax.jit(
                lambda key, dyn: ppo.start_runner(key, self.cfg, self.env_params, dyn, self.data),
                in_shardings=self.data.replicated, out_shardings=self.data.split())
        key = jax.random.fold_in(jax.random.fold_in(np.asarray(key), update), RUNNER_SALT)
        return self._cache["start"](self.data.put_replicated(np.asarray(key)),
                                     self.data.put_replicated(
                                         DynamicParams.from_config(self.cfg)))

    def with_runner(self, state: TrainState) -> TrainState:
        """`state` with environments: its own, or fresh ones at its update."""
        if state.runner is not None:
            return state
        return state.replace(runner=self.start_runner(state.key, int(state.update)))

    def example_observation(self):
        """One robot's all-zero observation as the network reads it (its critic's inputs
        included): the shapes its parameters are initialised for."""
        return privileged.observation_zeros(self.env_params, self.cfg.ppo.privileged_critic)

    def init(self) -> TrainState:
        key = jax.random.PRNGKey(self.cfg.train.seed)
        if "init" not in self._cache:
            # One compiled program, traced once per Trainer: run eagerly, the initialisers
            # and the optimiser's zeros compile op by op (hundreds).
            def initial(key):
                params = self.network.init(jax.random.fold_in(key, PARAMS_SALT),
                                           initial_memory(self.cfg.policy),
                                           self.example_observation())
                return params, self.optimizer.init(params)
            self._cache["init"] = jax.jit(initial)
        params, opt_state = self._cache["init"](key)
        return TrainState(params, opt_state, key, jnp.zeros((), jnp.int32), None)

    def fresh_optimizer_state(self, params):
        """The optimiser's initial state for `params` (one compiled program)."""
        if "optimizer init" not in self._cache:
            self._cache["optimizer init"] = jax.jit(self.optimizer.init)
        return self._cache["optimizer init"](params)

    def abstract_state(self, runner: bool = True, device: jax.Device | None = None) -> TrainState:
        """The state's shapes and layout, for orbax to restore into (nothing is computed):
        placed as `place` does, or on `device`; without the runner (None) on request."""
        key = jax.random.PRNGKey(self.cfg.train.seed)
        if "shapes" not in self._cache:
            params = jax.eval_shape(self.network.init, key, initial_memory(self.cfg.policy),
                                    self.example_observation())
            self._cache["shapes"] = TrainState(
                params, jax.eval_shape(self.optimizer.init, params), jax.eval_shape(lambda: key),
                jax.ShapeDtypeStruct((), jnp.int32), None)
        shapes = self._cache["shapes"]
        if runner:
            if "runner shapes" not in self._cache:
                self._cache["runner shapes"] = jax.eval_shape(
                    lambda k: ppo.start_runner(k, self.cfg, self.env_params,
                                               DynamicParams.from_config(self.cfg)), key)
            shapes = shapes.replace(runner=self._cache["runner shapes"])
        layout = self.shardings if device is None else jax.sharding.SingleDeviceSharding(device)
        return jax.tree.map(
            lambda sharding, part: jax.tree.map(
                lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding), part),
            layout, shapes, is_leaf=lambda x: isinstance(x, jax.sharding.Sharding))

    def init_from(self, params, source: str | Path) -> TrainState:
        """`init` with the network parameters `params` (of `train.init_from` = `source`)
        and an optimiser state made for them; raises ConfigError if their shapes differ."""
        fresh = self.init()
        want = jax.tree.map(lambda x: tuple(x.shape), fresh.params)
        got = jax.tree.map(lambda x: tuple(x.shape), params)
        if jax.tree.structure(want) != jax.tree.structure(got) or want != got:
            raise cfgmod.ConfigError(
                f"train.init_from: got {str(source)!r}, whose network differs from this "
                f"config's ({first_difference(want, got)}); allowed: a run or export with "
                "the same policy width, heads, layers, ff_mult and critic")
        params = jax.tree.map(lambda x, like: jnp.asarray(x, like.dtype), params, fresh.params)
        return fresh.replace(params=params, opt_state=self.fresh_optimizer_state(params))

    def resume(self, checkpoints: Checkpoints, log: Callable[[str], None]) -> TrainState:
        """The last checkpoint, laid out over the devices. A checkpoint without a runner
        (written by jaxmripp before the environments carried on across chunks) gets
        fresh environments at its update, as a chunk of that version started with."""
        template, fields = self.abstract_state(), checkpoints.fields()
        if fields.get("runner"):
            return checkpoints.restore(template)
        saved = checkpoints.restore({name: getattr(template, name) if name in SAVED_FIELDS
                                     else None for name in fields})
        saved = {name: saved[name] for name in SAVED_FIELDS}
        log(f"note: the checkpoint at update {int(saved['update'])} holds no environments; "
            "they start afresh there")
        return TrainState(**saved, runner=None)


def _chunk_fn(cfg: Config, env_params: EnvParams, network, optimizer, data: DataParallel,
              length: int):
    def one_update(dyn, state: TrainState, _):
        # Barriers around the update keep XLA from fusing it with what surrounds the loop,
        # which differs with the chunk's length (a loop of one is inlined): every chunk
        # length then runs the same update program, to the bit.
        state = jax.lax.optimization_barrier(state)
        key_rollout, key_update = jax.random.split(jax.random.fold_in(state.key, state.update))
        teacher = ppo.Teacher.at(cfg.ppo, state.update)
        runner, transitions, stats = ppo.rollout(key_rollout, state.runner, state.params,
                                                 network, cfg, env_params, dyn, data, teacher)
        last_value = ppo.values(network, state.params, runner.memory,
                                ppo.critic_inputs(cfg, runner.obs, runner.env_state),
                                cfg.train.blocks, data)
        params, opt_state, losses = ppo.update(key_update, state.params, state.opt_state,
                                               network, optimizer, transitions, last_value,
                                               cfg.ppo, cfg.train.blocks, data, teacher)
        metrics = dict(losses, episodes=stats.episodes, discovered_sum=stats.discovered,
                       return_sum=stats.episode_return, reward_parts=stats.reward_parts)
        state = TrainState(params, opt_state, state.key, state.update + 1, runner)
        return jax.lax.optimization_barrier((state, metrics))

    def chunk(state: TrainState, dyn: DynamicParams):
        return jax.lax.scan(functools.partial(one_update, dyn), state, None, length=length)

    return chunk


def chunk_ends(done: int, cfg: Config, count: int | None = None) -> list[int]:
    """Where the chunks after `done` updates end (the first `count` of them): at the
    multiples of train.updates_per_chunk (a run resumed with another chunk size
    realigns) and at train.updates."""
    size, ends = cfg.train.updates_per_chunk, []
    while done < cfg.train.updates and (count is None or len(ends) < count):
        done = min((done // size + 1) * size, cfg.train.updates)
        ends.append(done)
    return ends


def train(cfg: Config, run_dir: Path, resume: bool = False, stop_after_chunks: int | None = None,
          log: Callable[[str], None] = print, initial_params: Any = None,
          quiet: bool = False) -> TrainState:
    """Trains into run_dir (config.yaml, metrics.jsonl, tensorboard/, checkpoints/);
    returns the state.

    `resume` continues from the last checkpoint (a run without one starts anew), with the
    changes to config.yaml that `rundir.resume_changes` allows. A checkpoint restores onto
    whatever devices this run has, so a run may resume with another device or process
    count. A new run with `train.init_from` starts from `initial_params`, the parameters
    of that run or export (`jaxmripp.pipeline.initial_params` reads them). `quiet` leaves
    out the progress (`parallel.progress`) and the line per chunk. Bad input raises
    ConfigError (or ShardingError) before anything is written."""
    main = is_main_process()
    log = log if main else (lambda _: None)
    metricsmod.check_sinks(cfg.train.log)
    trainer = Trainer.build(cfg)
    trainer.data.check_divides(cfg.train.envs, "train.envs")
    trainer.data.check_divides(cfg.train.envs // cfg.ppo.minibatches,
                               "train.envs / ppo.minibatches (environments per minibatch)")
    if cfg.train.blocks:
        trainer.data.check_divides(cfg.train.blocks, "train.blocks")
    resuming = resume and _latest_step(run_dir, cfg.train.keep_checkpoints) is not None
    if resuming:
        changes = rundir.resume_changes(run_dir, cfg)
    elif cfg.train.init_from and initial_params is None:
        raise cfgmod.ConfigError(
            f"train.init_from: got {cfg.train.init_from!r} but no initial_params; "
            "allowed: its parameters passed as initial_params "
            "(jaxmripp.pipeline.initial_params)")
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoints = Checkpoints(run_dir / "checkpoints", cfg.train.keep_checkpoints)
    if resuming:
        state = trainer.resume(checkpoints, log)
        done = int(state.update)
        log(f"resumed {run_dir} at update {done}")
        if main:
            rundir.record_resume(run_dir, cfg, done, changes)
            metricsmod.keep_until(run_dir, done, log)
    else:
        state = trainer.place(trainer.init_from(initial_params, cfg.train.init_from)
                              if cfg.train.init_from else trainer.init())
        if cfg.train.init_from:
            log(f"parameters from {cfg.train.init_from}")
        if main:
            (run_dir / rundir.CONFIG_FILE).write_text(cfgmod.to_yaml(cfg))
    done = int(state.update)
    sinks = metricsmod.MetricsLog(cfg, run_dir, done, fresh=not resuming) if main else None
    try:
        state = _chunks(trainer, state, checkpoints, sinks, stop_after_chunks, log, quiet)
    finally:
        checkpoints.close()
        if sinks is not None:
            sinks.close()
    return state


def _latest_step(run_dir: Path, keep: int) -> int | None:
    """The run's last checkpoint step (None without one)."""
    if not (run_dir / "checkpoints" / "last").is_dir():
        return None
    checkpoints = Checkpoints(run_dir / "checkpoints", keep)
    try:
        return checkpoints.latest_step()
    finally:
        checkpoints.close()


def _chunks(trainer: Trainer, state: TrainState, checkpoints: Checkpoints,
            sinks: metricsmod.MetricsLog | None, stop_after_chunks: int | None,
            log: Callable[[str], None], quiet: bool) -> TrainState:
    """The chunks from `state` to train.updates (or `stop_after_chunks` of them), a line
    per chunk to `log` unless `quiet`."""
    cfg = trainer.cfg
    samples_per_update = cfg.train.envs * cfg.train.rollout_steps * cfg.robots.count
    total_chunks = -(-cfg.train.updates // cfg.train.updates_per_chunk)
    done = int(state.update)
    ends = chunk_ends(done, cfg, stop_after_chunks)
    if ends:
        state = trainer.with_runner(state)
    # Every chunk length this run needs, compiled before the bar appears.
    for length in dict.fromkeys(end - start for start, end in zip([done, *ends], ends)):
        trainer.compiled(length, state, quiet)
    log = progress.above(log)
    say = (lambda _: None) if quiet else log
    with progress.bar(cfg.train.updates, "training", quiet, initial=done, unit="update") as bar:
        for end in ends:
            chunk = trainer.compiled(end - done, state, quiet)
            start = time.perf_counter()
            state, stacked = chunk(state, trainer.env_dynamic)
            stacked = jax.device_get(stacked)
            records = metricsmod.records(stacked, done, samples_per_update,
                                         time.perf_counter() - start)
            if sinks is not None:
                sinks.write(records)
            discovered = metricsmod.episode_mean(records, "discovered")
            # best/ without the runner: the environments are for resuming, which reads
            # last/, and they outweigh the network (1.6 GB for 64 environments of 64
            # robots in a 125^3 world)
            checkpoints.save(end, state, discovered, best_state=state.replace(runner=None))
            bar.update(end - done)
            done = end
            episodes = sum(r["episodes"] for r in records)
            ended = (f"discovered {100 * discovered:.1f}%  return "
                     f"{metricsmod.episode_mean(records, 'return'):.2f}"
                     if episodes else "no episode ended")
            last = records[-1]
            say(f"chunk {-(-end // cfg.train.updates_per_chunk)}/{total_chunks}  updates "
                f"{end}  agent-steps {last['env_steps']:,}  {last['agent_steps_per_s']:,.0f}/s"
                f"  {ended}  entropy {np.mean([r['entropy'] for r in records]):.2f}  "
                f"value-loss {np.mean([r['value_loss'] for r in records]):.3f}")
    if done < cfg.train.updates:
        log(f"stopped after {stop_after_chunks} chunk(s) as asked; --resume continues")
    return state


def restore(cfg: Config, run_dir: Path, best: bool = False) -> TrainState:
    """The network, optimiser state, key and update of a run's last (or best) checkpoint
    on this process's first device; the runner is left on disk (None)."""
    trainer = Trainer.build(cfg)
    template = trainer.abstract_state(runner=False, device=jax.local_devices()[0])
    checkpoints = Checkpoints(Path(run_dir) / "checkpoints", cfg.train.keep_checkpoints)
    try:
        saved = checkpoints.restore_part({name: getattr(template, name)
                                          for name in SAVED_FIELDS}, best=best)
    finally:
        checkpoints.close()
    return TrainState(**saved, runner=None)
