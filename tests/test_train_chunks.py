"""The training loop on the smoke config: chunk size, per-update metrics and their sinks,
what a resumed run may change, and that training improves on the initial policy."""

import json
import shutil
import subprocess
import sys

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from event_files import scalars
from jaxmripp import config as cfgmod
from jaxmripp.evaluation import evaluate
from jaxmripp.evaluation.planners import policy_planner
from jaxmripp.learn import metrics as metricsmod, rundir, train as trainmod
from jaxmripp.sim import episode
from smoke_run import cfg, full_run, untimed  # noqa: F401 (fixtures)


def _leaves_equal(a, b):
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b),
                                                    strict=True))


def _same_run(a_dir, a, b_dir, b):
    """Two runs trained the same: state (runner included) to the bit, records alike."""
    assert int(a.update) == int(b.update)
    for field in ("params", "opt_state", "runner"):
        assert _leaves_equal(getattr(a, field), getattr(b, field)), field
    assert untimed(a_dir) == untimed(b_dir)


# Slow: one chunk of three updates is a program of its own (about 20 s of compiling).
@pytest.mark.slow
def test_a_run_trains_the_same_whatever_its_chunk_size(cfg, full_run, tmp_path):
    """One chunk of all the run's updates against the fixture's one-update chunks."""
    run_dir = tmp_path / "one_chunk"
    state = trainmod.train(cfgmod.load("tests/smoke.yaml", [
        f"train.updates_per_chunk={cfg.train.updates}"]), run_dir, log=lambda _: None)
    assert [r["update"] for r in trainmod.read_metrics(full_run[0])] == \
        list(range(1, cfg.train.updates + 1))
    _same_run(full_run[0], full_run[1], run_dir, state)


def test_every_scalar_of_every_update_reaches_tensorboard(full_run):
    run_dir, _ = full_run
    records = trainmod.read_metrics(run_dir)
    logged = scalars(run_dir / metricsmod.TENSORBOARD_DIR)
    expected = {(key, r["update"]): [np.float32(value)] for r in records
                for key, value in r.items() if key != "update"}
    assert logged == expected
    assert len({tag for tag, _ in logged}) >= 14  # losses, rewards, episodes, timing


def test_wandb_asked_for_but_not_installed_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "wandb", None)  # what find_spec reports when absent
    cfg = cfgmod.load("tests/smoke.yaml", ["train.log=[jsonl, wandb]"])
    with pytest.raises(cfgmod.ConfigError) as err:
        trainmod.train(cfg, tmp_path / "run", log=lambda _: None)
    assert str(err.value) == ("train.log: got ['jsonl', 'wandb'], but wandb is not installed; "
                              "allowed: jsonl and tensorboard, or wandb after `pip install "
                              "wandb`")
    assert not (tmp_path / "run").exists()


def test_a_resumed_run_may_change_only_what_leaves_training_as_it_is(cfg, full_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(full_run[0], run_dir)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    faster = cfgmod.from_dict({"ppo": {"learning_rate": 1e-3}}, cfg)
    with pytest.raises(cfgmod.ConfigError) as err:
        trainmod.train(faster, run_dir, resume=True, log=lambda _: None)
    assert str(err.value).startswith("ppo.learning_rate: got 0.001 to resume ")
    assert "trained with 0.0003; allowed on resume: changes to train.updates, " in str(err.value)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before

    longer = cfgmod.from_dict({"train": {"updates": 4, "updates_per_chunk": 2},
                               "eval": {"worlds": 3}}, cfg)
    lines = []
    state = trainmod.train(longer, run_dir, resume=True, log=lines.append)
    assert int(state.update) == 4 and lines[0] == f"resumed {run_dir} at update 3"
    assert cfgmod.load(run_dir / rundir.CONFIG_FILE) == longer
    assert [json.loads(line) for line in (run_dir / rundir.RESUMES_FILE).read_text().splitlines()] \
        == [{"update": 3, "changes": {"train.updates": {"from": 3, "to": 4},
                                      "train.updates_per_chunk": {"from": 1, "to": 2},
                                      "eval.worlds": {"from": 2, "to": 3}}}]
    assert [r["update"] for r in trainmod.read_metrics(run_dir)] == [1, 2, 3, 4]


def test_train_py_refuses_to_resume_with_another_setting(full_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(full_run[0], run_dir)
    done = subprocess.run([sys.executable, "train.py", "--resume", str(run_dir), "--no-eval",
                           "train.envs=8"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"error: train.envs: got 8 to resume {str(run_dir)!r}, which trained with 4; allowed "
        "on resume: changes to train.updates, train.updates_per_chunk, train.keep_checkpoints, "
        "train.log, train.eval_worlds, train.eval_budget and eval.* (a new run for anything "
        "else)"]


def test_a_checkpoint_without_environments_resumes_with_fresh_ones(cfg, full_run, tmp_path):
    """Checkpoints that hold only the network, optimiser state, key and update (as the
    versions before the runner was saved wrote them) resume with environments started
    afresh at their update."""
    run_dir = tmp_path / "run"
    shutil.copytree(full_run[0], run_dir)
    saved = trainmod.restore(cfg, run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    for manager in ("last", "best"):
        with ocp.CheckpointManager((run_dir / "checkpoints" / manager).absolute()) as old:
            old.save(3, args=ocp.args.StandardSave(
                {name: getattr(saved, name) for name in trainmod.SAVED_FIELDS}),
                     **({"metrics": {"score": 0.0}} if manager == "best" else {}))
    longer = cfgmod.from_dict({"train": {"updates": 4}}, cfg)
    lines = []
    state = trainmod.train(longer, run_dir, resume=True, log=lines.append)
    assert "note: the checkpoint at update 3 holds no environments; they start afresh there" \
        in lines
    assert int(state.update) == 4 and not _leaves_equal(state.params, saved.params)


def test_the_trained_smoke_policy_finds_more_than_its_initial_policy(cfg, full_run):
    """On the same 16 held-out worlds, the policy after the smoke run's three updates
    finds more windows than the initial network (deployed alike: most probable view)."""
    _, state = full_run
    trainer = trainmod.Trainer.build(cfg)
    params = evaluate.eval_params(cfg, cfg.train.eval_budget, layout="random")
    dyn = evaluate.eval_dynamic(cfg, cfg.train.eval_budget)
    keys = evaluate.episode_keys(cfg.eval.seed, 16)

    @jax.jit  # the network's parameters traced: one compilation for both
    def found(net_params):
        planner = policy_planner(trainer.network, net_params, cfg.policy.width)
        return jax.vmap(lambda k: episode.run(k, params, dyn, planner).discovered_fraction)(keys)

    initial = np.asarray(found(trainer.init().params))
    trained = np.asarray(found(jax.device_get(state.params)))
    assert trained.mean() > 1.5 * initial.mean()
    assert (trained > initial).sum() > 2 * (trained < initial).sum()


def test_a_stage_trains_into_its_run_dir_from_the_folder_before(full_run, tmp_path, capsys):
    """`train.py --run-dir B train.init_from=A`, as `make scale` chains its stages: the
    run is made in exactly B (new, or empty as here), nothing beside it, and starts from
    A's parameters."""
    from jaxmripp.cli import train as train_cli  # noqa: PLC0415

    run_a, _ = full_run
    stage = tmp_path / "stages" / "b"
    stage.mkdir(parents=True)
    status = train_cli.main(["--config", "tests/smoke.yaml", "--run-dir", str(stage),
                             "--no-eval", "--quiet", "train.updates=0",
                             f"train.init_from={run_a}"])
    out = capsys.readouterr().out
    assert status == 0
    assert f"run folder: {stage}\n" in out and f"parameters from {run_a}\n" in out
    assert [p.name for p in stage.parent.iterdir()] == ["b"]
    assert cfgmod.load(stage / "config.yaml") == cfgmod.load(
        "tests/smoke.yaml", ["train.updates=0", f"train.init_from={run_a}"])
