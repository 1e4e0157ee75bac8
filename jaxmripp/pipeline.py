"""The main job behind `make train`: train, then evaluate against baselines, then plot."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from jaxmripp.evaluation import baselines, evaluate, viz
from jaxmripp.evaluation.sweep import policy_mismatches
from jaxmripp.evaluation.planners import baseline_planner, deployed, policy_planner
from jaxmripp import config as cfgmod, folders
from jaxmripp.learn import policy as policymod, train as trainmod
from jaxmripp.learn.checkpoint import CheckpointError
from jaxmripp.runtime import weights as weights_format
from jaxmripp.runtime.errors import RuntimeInputError
from jaxmripp.config import Config, presets
from jaxmripp.parallel.mesh import is_main_process
from jaxmripp.sim import privileged


def is_training_run(folder: str | Path) -> bool:
    """A folder train.py wrote, with a checkpoint (`jaxmripp.folders`), as opposed to an
    export."""
    return folders.is_training_run(folder)


def trained_params(source: str | Path, cfg: Config | None = None, best: bool = False):
    """Network parameters of a training run (its last or best checkpoint, restored with
    `cfg`, by default the run's config.yaml) or of an export (a folder with policy.npz,
    e.g. pretrained/default). Raises FolderError for a folder of neither kind,
    RuntimeInputError for a corrupt export, CheckpointError for an unreadable checkpoint."""
    source = Path(source)
    if folders.is_training_run(source):
        run_cfg = cfg if cfg is not None else folders.training_run(source, best)
        return trainmod.restore(run_cfg, source, best=best).params
    folders.policy(source, best, with_config=False)  # neither kind: FolderError
    return policymod.unflatten_params(weights_format.load(source).weights)


def eval_dir(config_path: str | Path, policy_dirs: Sequence[Path]) -> Path:
    """Where eval.py writes without --out: the first policy's training run keeps its
    evaluations (RUN/eval); a shipped export (e.g. pretrained/default) stays as shipped,
    so its evaluations go to runs/NAME/eval; a sweep of baselines alone to
    runs/CONFIG_STEM/eval."""
    if not policy_dirs:
        return Path("runs") / Path(config_path).stem / "eval"
    first = Path(policy_dirs[0])
    if is_training_run(first):
        return first / "eval"
    return Path("runs") / first.name / "eval"


def initial_source(cfg: Config) -> Path:
    """The folder `train.init_from` names: relative to the working directory, else to the
    source checkout (`train.init_from=pretrained/default` works from anywhere)."""
    return presets.in_checkout(cfg.train.init_from)


def check_initial_params(cfg: Config) -> None:
    """Checks, by its files alone (no JAX), that `train.init_from` names a training run
    with a checkpoint or an intact export; ConfigError naming the key otherwise."""
    if cfg.train.init_from:
        try:
            folders.policy(initial_source(cfg), with_config=False)
        except (cfgmod.ConfigError, folders.FolderError, RuntimeInputError) as err:
            raise cfgmod.ConfigError(f"train.init_from: {err}") from None


def initial_params(cfg: Config):
    """The parameters `train.init_from` names (None when it is empty), for
    `jaxmripp.learn.train.train`."""
    if not cfg.train.init_from:
        return None
    try:
        return trained_params(initial_source(cfg))
    except (cfgmod.ConfigError, folders.FolderError, RuntimeInputError, CheckpointError) as err:
        raise cfgmod.ConfigError(f"train.init_from: {err}") from None


def trained_planner(cfg: Config, run_dir: Path, best: bool = False):
    """A deterministic policy planner from a training run's checkpoint or from a shipped
    export (a folder with policy.npz, e.g. pretrained/default), `cfg` its config."""
    network = trainmod.Trainer.build(cfg).network
    if cfg.ppo.privileged_critic:  # the critic's training-only inputs, unknown here
        network = privileged.ZeroFilled(network, cfg.robots.count)
    return policy_planner(network, trained_params(run_dir, cfg, best), cfg.policy.width)


AHEAD_FIELDS = ("ahead_branches", "ahead_discount", "ahead_facade_weight", "ahead_rated",
                "belief_features", "belief_strength")


def policy_inputs(cfg: Config) -> tuple:
    """The settings of `cfg`'s optional policy inputs (`AHEAD_FIELDS`: the lookahead and
    belief inputs), which decide the observations its environments build."""
    return tuple(getattr(cfg.policy, f) for f in AHEAD_FIELDS)


def with_policy_inputs(sweep: Config, run_dirs: Sequence[Path]) -> Config:
    """`sweep` with the lookahead input (`policy.ahead_*`) of the policies in `run_dirs`,
    so that its environments build the observations those policies read (the other
    planners ignore the extra column). Policies that read different lookahead inputs
    cannot share one sweep."""
    wanted = {policy_inputs(cfgmod.load(Path(d) / "config.yaml")) for d in run_dirs}
    if len(wanted) > 1:
        raise cfgmod.ConfigError(
            f"--policy: the policies read different lookahead inputs ({AHEAD_FIELDS} = "
            f"{sorted(wanted)}); allowed: policies that agree on them, in one sweep")
    if not wanted:
        return sweep
    values = dict(zip(AHEAD_FIELDS, wanted.pop()))
    return dataclasses.replace(sweep, policy=dataclasses.replace(sweep.policy, **values))


def sweep_planner(run_dir: Path, sweep: Config, name: str = "policy", best: bool = False,
                  log: Callable[[str], None] = print) -> baselines.Planner:
    """The policy in `run_dir` (a training run or an export, with its config.yaml) as the
    sweep config `sweep` deploys it, named `name`; where the sweep's settings differ from
    the policy's training, a note goes to `log`."""
    cfg = cfgmod.load(run_dir / "config.yaml")
    if policy_inputs(cfg) != policy_inputs(sweep):
        raise cfgmod.ConfigError(
            f"{name} reads the lookahead input {AHEAD_FIELDS} = {policy_inputs(cfg)}, the "
            f"sweep builds {policy_inputs(sweep)}; allowed: the same "
            "(pipeline.with_policy_inputs)")
    planner = trained_planner(cfg, run_dir, best)._replace(name=name)
    for note in policy_mismatches(cfg, sweep):  # once the policy has loaded
        log(f"note: {name} was trained with {note}")
    return planner


def baseline_planners(cfg: Config, params) -> list[baselines.Planner]:
    """The baselines `make train` compares the policy with: `eval.planners` but the policy."""
    return [baseline_planner(name, params, cfg.eval) for name in cfg.eval.planners
            if name != "policy"]


def report(cfg: Config, run_dir: Path, log: Callable[[str], None] = print,
           compiler_options: dict | None = None) -> dict:
    """Learning curve, held-out comparison table and an episode picture in run_dir;
    returns the mean % of windows found per planner. `compiler_options` go to XLA.
    Every process of a multi-process run evaluates its share; process 0 writes."""
    params = evaluate.eval_params(cfg, cfg.train.eval_budget, layout="random")
    planners = [deployed(p, cfg.eval.sectors)
                for p in [trained_planner(cfg, run_dir), *baseline_planners(cfg, params)]]
    dyn = evaluate.eval_dynamic(cfg, cfg.train.eval_budget)
    keys = evaluate.episode_keys(cfg.eval.seed, cfg.train.eval_worlds)
    results = evaluate.compare(planners, params, dyn, keys, compiler_options)
    shown = results[planners[0].name]["first_episode"]
    title = (f"{cfg.train.eval_worlds} held-out random-layout worlds, N = {params.n_robots}, "
             f"B = {cfg.train.eval_budget}, rho = {cfg.radio.range}")
    table = evaluate.summary_table(results, title)
    if is_main_process():
        records = trainmod.read_metrics(run_dir)
        if records:
            viz.learning_curve(run_dir / "learning_curve.png", records,
                               keys=("discovered", "return", "entropy"))
        (run_dir / "eval_table.md").write_text(table + "\n")
        (run_dir / "eval_summary.json").write_text(json.dumps(
            {name: {"mean": float(r["discovered"].mean()),
                    "std": float(r["discovered"].std(ddof=1)),
                    "ms_per_robot_step": r["ms_per_robot_step"]} for name, r in results.items()},
            indent=2))
        viz.discovery_curves(run_dir / "discovered_vs_budget.png", results)
        found = 100 * float(shown.discovered_fraction)
        viz.render_result(run_dir / "episode_policy.png", shown, cfg.radio.range,
                          title=f"trained policy: {found:.1f}% found")
        log(table)
    return {name: float(np.mean(r["discovered"])) for name, r in results.items()}
