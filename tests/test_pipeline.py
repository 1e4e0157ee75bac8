"""pipeline.report on a tiny config: the files it promises and the planners' rows."""

import json
from pathlib import Path

import numpy as np

from jaxmripp import config, pipeline
from jaxmripp.learn import train as trainmod
from jaxmripp.learn.checkpoint import Checkpoints

ROOT = Path(__file__).resolve().parents[1]
FAST = {"xla_backend_optimization_level": 0}


def test_report_writes_its_files_and_a_row_per_planner(tmp_path):
    cfg = config.load(ROOT / "tests" / "smoke.yaml",
                      ["train.eval_worlds=3", "eval.planners=[policy, random]"])
    run_dir = tmp_path / "run"
    # An untrained policy is enough: report restores the last checkpoint of the run.
    checkpoints = Checkpoints(run_dir / "checkpoints", cfg.train.keep_checkpoints)
    checkpoints.save(1, trainmod.Trainer.build(cfg).init(), 0.0)
    checkpoints.close()
    records = [{"update": u, "env_steps": 100 * u, "discovered": 0.1 * u, "return": u,
                "entropy": 3.0 - u} for u in (1, 2)]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    lines = []
    means = pipeline.report(cfg, run_dir, log=lines.append, compiler_options=FAST)

    for name in ("learning_curve.png", "eval_table.md", "eval_summary.json",
                 "discovered_vs_budget.png", "episode_policy.png"):
        assert (run_dir / name).is_file() and (run_dir / name).stat().st_size > 0, name
    names = ["policy", "random"]
    assert list(means) == names
    table = (run_dir / "eval_table.md").read_text()
    assert lines == [table.rstrip("\n")]
    assert f"{cfg.train.eval_worlds} held-out random-layout worlds, N = 2" in table
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    assert [row.split(" | ")[0].lstrip("| ") for row in rows[1:]] == names
    summary = json.loads((run_dir / "eval_summary.json").read_text())
    assert list(summary) == names
    for name in names:
        assert 0.0 <= means[name] <= 100.0
        assert np.isclose(summary[name]["mean"], means[name])
        assert f"| {name} | {means[name]:.2f} +- " in table
