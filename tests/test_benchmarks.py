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
from scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
TINY_BATCH = ["--envs", "4", "--size", "20", "--repeats", "1"]

SCRIPTS = {  # script: (arguments, figures it must print)
    "env.py": (TINY_BATCH, ["env.agent_steps_per_s", "env.slots_at_robot",
                            "env.share_candidates", "env.share_view_gain",
                            "env.share_share_maps", "env.share_gps"]),
    "env_ab.py": (["--base", "HEAD", "--envs", "4", "--rounds", "1", "--steps", "1",
                   "world.size=20", "--tree-set", "gp.catchup_rounds=2"],
                  ["env_ab.wall_ratio", "env_ab.cpu_ratio"]),
    "sensing.py": (TINY_BATCH, ["sensing.robot_casts_per_s", "sensing.frustum_casts_per_s"]),
    "gp.py": ([], ["gp.step_per_s", "gp.speedup_vs_refactor", "gp.block_speedup_vs_adds"]),
    "runtime.py": ([], ["runtime.decision_ms", "runtime.map_message_bytes",
                        "runtime.policy_forward_ms"]),
    "train.py": (["--config", "tests/smoke.yaml", "--envs", "8", "--steps", "2",
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


def test_each_line_names_the_machine_by_vendor_and_family():
    """The machine each figure names, from /proc/cpuinfo model names of the kinds the
    README's figures come from; `benchmarks/figures.py` imports only the standard library,
    so it is loaded here directly."""
    figures = load_script("benchmarks/figures.py")
    assert figures.cpu_family("Intel(R) Xeon(R) Processor") == "Intel Xeon"
    assert figures.cpu_family("AMD EPYC 7R13 Processor") == "AMD EPYC"
    assert figures.cpu_family("Intel(R) Core(TM) i7-8700 CPU @ 3.20GHz") == "Intel Core"
    assert figures.cpu_family("") == ""
    assert figures.host_cpu().startswith(f"{os.cpu_count()}-core")
    record = json.loads(figures.line("x.rate", 1.5, "1/s", device="2-core Intel Xeon", envs=4))
    assert record == {"name": "x.rate", "value": 1.5, "unit": "1/s", "envs": 4,
                      "device": "2-core Intel Xeon"}
    assert "unit" not in json.loads(figures.line("x.best", "nbv", device="d"))


def test_quality_refuses_a_sweep_without_the_planners_of_its_figures():
    """quality.py's overrides may change the protocol's settings but not drop a planner or
    a radio range its figures are defined over: one line naming what is missing, exit 2,
    before anything is compiled."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "quality.py"),
                           "--worlds", "1", "eval.planners=[policy,nbv,oracle]"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr[-3000:]
    error = done.stderr.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("error: overrides:"), error
    assert "nbv_ahead, nbv_team, coordinated, greedy, mcts, rig, random" in error[0]
    assert done.stdout == ""


def test_quality_seed_statistics_name_the_median_seed(monkeypatch, capsys):
    """With --seeds, the recipe's mean, std (ddof 1) and the median seed's folder come from
    each policy's own rho = inf episodes (a sweep faked here: the figures are arithmetic on
    what it returns); the same folders as repeated --policy are distinct policies, given
    no recipe lines, and the two flags together are refused."""
    from types import SimpleNamespace

    import numpy as np

    from jaxmripp import pipeline
    from jaxmripp.evaluation import sweep

    quality = load_script("benchmarks/quality.py")
    seeds = [ROOT / "pretrained" / name for name in ("default", "default_fast", "paper")]
    found = {"policy": [90.0, 94.0], "policy_2": [80.0, 84.0], "policy_3": [95.0, 97.0]}
    runs = [SimpleNamespace(planner=name, shape=SimpleNamespace(radio_range=rho), worlds=2,
                            discovered=np.asarray(pct) - (rho != math.inf),
                            safety={"obstacle_collisions": np.zeros(2),
                                    "robot_collisions_in_range": np.zeros(2)})
            for name, pct in found.items() for rho in (math.inf, 0.1)]
    monkeypatch.setattr(pipeline, "with_policy_inputs", lambda cfg, dirs: cfg)
    monkeypatch.setattr(pipeline, "sweep_planner", lambda folder, cfg, name, log: name)
    monkeypatch.setattr(sweep, "run_sweep", lambda cfg, policies, **_: SimpleNamespace(runs=runs))
    assert quality.main(["--seeds", *map(str, seeds), "--planners", "policy"]) == 0
    lines = {r["name"]: r["value"] for r in map(json.loads, capsys.readouterr().out.splitlines())}
    means = [92.0, 82.0, 96.0]
    assert lines["quality.recipe_seeds"] == 3
    assert lines["quality.recipe_mean_pct"] == pytest.approx(90.0)
    assert lines["quality.recipe_std_pct"] == pytest.approx(np.std(means, ddof=1), abs=1e-4)
    assert lines["quality.recipe_median"] == str(seeds[0])  # 92 between 82 and 96
    assert lines["quality.policy_pct"] == pytest.approx(92.0)
    assert lines["quality.pct.policy_3.rho0.1"] == pytest.approx(95.0)
    policies = [arg for seed in seeds for arg in ("--policy", str(seed))]
    assert quality.main([*policies, "--planners", "policy"]) == 0
    lines = {r["name"]: r["value"] for r in map(json.loads, capsys.readouterr().out.splitlines())}
    assert lines["quality.pct.policy_3.rho0.1"] == pytest.approx(95.0)
    assert not [name for name in lines if name.startswith("quality.recipe_")]
    with pytest.raises(SystemExit) as refused:
        quality.main([*policies[:2], "--seeds", *map(str, seeds[1:]), "--planners", "policy"])
    assert refused.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == ["error: --policy / --seeds: give one of them; allowed: --policy DIR "
                     "(repeated: distinct policies) or --seeds DIR DIR ... (one recipe's seeds)"]


def test_flight_combines_seeds_flown_on_the_same_cities_and_refuses_others(tmp_path, capsys):
    """flight.py --combine: the mean and sample std of the seeds' policy figures, the mean
    over nbv's; files whose nbv or random figures differ flew other cities (or ranges)."""
    flight = load_script("benchmarks/flight.py")

    def flown(name, policy, nbv=56.0, random=18.0, crashes=0):
        lines = [{"name": f"flight.{planner}_pct", "value": value, "unit": "%", "worlds": 10}
                 for planner, value in (("policy", policy), ("random", random), ("nbv", nbv))]
        lines.append({"name": "flight.crashes", "value": crashes, "unit": "count"})
        (tmp_path / name).write_text("".join(json.dumps(line) + "\n" for line in lines))
        return str(tmp_path / name)

    policy = [58.0, 60.5, 65.0]
    files = [flown(f"s{i}.jsonl", pct, crashes=i) for i, pct in enumerate(policy)]
    assert flight.main(["--combine", *files]) == 0
    lines = {r["name"]: r["value"] for r in map(json.loads, capsys.readouterr().out.splitlines())}
    assert lines["flight.recipe_seeds"] == 3
    assert lines["flight.recipe_mean_pct"] == pytest.approx(61.1667, abs=1e-4)
    assert lines["flight.recipe_std_pct"] == pytest.approx(3.5473, abs=1e-4)  # ddof = 1
    assert lines["flight.recipe_policy_vs_nbv"] == pytest.approx(61.1667 / 56.0, abs=1e-4)
    assert lines["flight.recipe_crashes"] == 3
    for other, expected in (([flown("far.jsonl", 59.0, nbv=55.0)], "the files' nbv_pct differ"),
                            ([], "got 1 file"),
                            ([str(tmp_path / "absent.jsonl")], "absent.jsonl: FileNotFoundError")):
        with pytest.raises(SystemExit) as refused:
            flight.main(["--combine", files[0], *other])
        assert refused.value.code == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and error[0].startswith("error: --combine") and expected in error[0]
