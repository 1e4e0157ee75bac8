"""The benchmark scripts `make bench` runs (on tiny batches where they take a batch shape):
each exits cleanly and prints the figures it promises as finite JSON lines. They call into
the simulator directly, so a changed signature there breaks them without failing any other
test."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY_BATCH = ["--envs", "4", "--size", "20", "--repeats", "1"]

SCRIPTS = {  # script: (arguments, figures it must print)
    "env.py": (TINY_BATCH, ["env.agent_steps_per_s", "env.slots_at_robot",
                            "env.share_candidates", "env.share_view_gain",
                            "env.share_share_maps", "env.share_gps"]),
    "env_ab.py": (["--base", "HEAD", "--envs", "4", "--rounds", "1", "--steps", "1", "--set",
                   "world.size=20", "--tree-set", "gp.peer_rounds=1"],
                  ["env_ab.wall_ratio", "env_ab.cpu_ratio"]),
    "sensing.py": (TINY_BATCH, ["sensing.robot_casts_per_s", "sensing.frustum_casts_per_s"]),
    "gp.py": ([], ["gp.step_per_s", "gp.speedup_vs_refactor", "gp.block_speedup_vs_adds"]),
    "runtime.py": ([], ["runtime.decision_ms", "runtime.map_message_bytes",
                        "runtime.policy_forward_ms"]),
    "train.py": (["--config", "configs/smoke.yaml", "--envs", "8", "--steps", "2",
                  "--rounds", "1"],
                 ["train.rollout_agent_steps_per_s", "train.update_samples_per_s",
                  "train.env_share_of_iteration"]),
}


@pytest.mark.slow  # each script compiles its own programs in a process of its own
@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_benchmark_prints_its_figures(script):
    arguments, names = SCRIPTS[script]
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *arguments],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    figures = {}
    for line in done.stdout.splitlines():
        if line.startswith("{"):
            record = json.loads(line)
            figures[record["name"]] = record["value"]
            assert record["device"], record  # every figure names its machine
    for name in names:
        assert name in figures, (name, sorted(figures))
        assert math.isfinite(figures[name]), (name, figures[name])


def test_cpu_family_keeps_vendor_and_family_only():
    """The machine named beside each figure, from /proc/cpuinfo model names seen on the
    machines the README's figures come from (run apart: importing the benchmarks' helpers
    changes the process's malloc settings)."""
    code = (
        "import common\n"
        "print(common.cpu_family('Intel(R) Xeon(R) Processor'))\n"
        "print(common.cpu_family('AMD EPYC 7R13 Processor'))\n"
        "print(common.cpu_family('Intel(R) Core(TM) i7-8700 CPU @ 3.20GHz'))\n"
        "print(repr(common.cpu_family('')))\n"
        "print(common.machine())\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT / "benchmarks",
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    assert lines[:4] == ["Intel Xeon", "AMD EPYC", "Intel Core", "''"]
    assert lines[4].startswith(f"{os.cpu_count()}-core"), lines[4]
