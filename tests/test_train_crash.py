"""A training run stopped at any point and resumed is the run that was not stopped: the
same parameters to the bit and every update's metrics once (tests/crash_points.py says
where it stops). Here the run raises at the crash point and resumes in this process; the
slow variants kill a `train.py` process there (SIGKILL) and resume with `train.py
--resume`."""

import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import crash_points
from event_files import scalars
from jaxmripp.learn import metrics as metricsmod, train as trainmod
from jaxmripp.learn.checkpoint import Checkpoints
from smoke_run import cfg, full_run, untimed  # noqa: F401 (fixtures)


def _assert_as_uninterrupted(cfg, run_dir: Path, full_run, state=None):
    full_dir, full = full_run
    state = trainmod.restore(cfg, run_dir) if state is None else state
    for field in ("params", "opt_state"):
        assert all(np.array_equal(a, b) for a, b in zip(
            jax.tree.leaves(getattr(state, field)), jax.tree.leaves(getattr(full, field)),
            strict=True)), field
    assert untimed(run_dir) == untimed(full_dir)  # each update once, the same figures
    assert scalars(run_dir / metricsmod.TENSORBOARD_DIR).keys() == \
        scalars(full_dir / metricsmod.TENSORBOARD_DIR).keys()
    assert all(len(values) == 1 for values in
               scalars(run_dir / metricsmod.TENSORBOARD_DIR).values())


@pytest.mark.parametrize("point", [
    "cut_line", "mid_checkpoint",
    *[pytest.param(p, marks=pytest.mark.slow) for p in crash_points.POINTS
      if p not in ("cut_line", "mid_checkpoint")]])
def test_a_run_crashed_and_resumed_is_the_uninterrupted_run(cfg, full_run, tmp_path, point,
                                                            monkeypatch):
    run_dir = tmp_path / "run"
    with monkeypatch.context() as patches:
        crash_points.install(point, crash_points.raise_crash, patches)
        with pytest.raises(crash_points.Crash):
            trainmod.train(cfg, run_dir, log=lambda _: None)
    lines = []
    state = trainmod.train(cfg, run_dir, resume=True, log=lines.append)
    resumed_at = 2 if point == "after_checkpoint" else 1
    assert lines[0] == f"resumed {run_dir} at update {resumed_at}"
    if point == "cut_line":
        assert any("the last line is cut short" in line for line in lines)
    _assert_as_uninterrupted(cfg, run_dir, full_run, state)
    assert _steps(run_dir) == _steps(full_run[0])


def _steps(run_dir: Path) -> tuple[list[int], list[int]]:
    """The steps in a run's checkpoints/last and checkpoints/best."""
    checkpoints = Checkpoints(run_dir / "checkpoints", 3)
    try:
        return checkpoints.last.all_steps(), checkpoints.best.all_steps()
    finally:
        checkpoints.close()


def test_a_cut_last_line_is_left_out_with_a_note_and_others_are_errors(tmp_path):
    path = tmp_path / metricsmod.METRICS_FILE
    path.write_text('{"update": 1}\n{"update": 2}\n{"upd')
    notes = []
    assert metricsmod.read_metrics(tmp_path, notes.append) == [{"update": 1}, {"update": 2}]
    assert notes == [f"note: {path}: the last line is cut short (the run stopped while "
                     "writing it); left out"]
    path.write_text('{"update": 1}\n{"upd\n{"update": 3}\n')
    with pytest.raises(metricsmod.MetricsError, match="line 2 is not a JSON record"):
        metricsmod.read_metrics(tmp_path)


# Each point costs two train.py processes (the compilations come from JAX's cache).
@pytest.mark.slow
@pytest.mark.parametrize("point", crash_points.POINTS)
def test_a_killed_train_py_resumes_to_the_uninterrupted_run(cfg, full_run, tmp_path, point):
    runs = tmp_path / "runs"
    script = (f"import sys; sys.path.insert(0, 'tests'); import crash_points, train; "
              f"crash_points.install({point!r}, crash_points.kill); "
              f"sys.exit(train.main(['--config', 'tests/smoke.yaml', '--no-eval', "
              f"'--quiet', '--runs', {str(runs)!r}]))")
    killed = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=600)
    assert killed.returncode == -9, killed.stderr[-2000:]
    run_dir = runs / cfg.train.name
    resumed = subprocess.run([sys.executable, "train.py", "--resume", str(run_dir), "--no-eval",
                              "--quiet"], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "chunk " not in resumed.stdout  # --quiet: no line per chunk
    _assert_as_uninterrupted(cfg, run_dir, full_run)
    assert _steps(run_dir) == _steps(full_run[0])
