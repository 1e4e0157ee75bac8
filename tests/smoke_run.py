"""The uninterrupted smoke training run that the chunk-size and crash tests compare with,
and its metrics without the fields that differ between identical runs."""

import pytest

from jaxmripp import config as cfgmod
from jaxmripp.learn import train as trainmod

TIMING = ("seconds", "agent_steps_per_s")  # the only record fields that differ between runs


@pytest.fixture(scope="module")
def cfg():
    return cfgmod.load("tests/smoke.yaml")


@pytest.fixture(scope="module")
def full_run(cfg, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "full"
    return run_dir, trainmod.train(cfg, run_dir, log=lambda _: None)


def untimed(run_dir):
    return [{k: v for k, v in r.items() if k not in TIMING} for r in trainmod.read_metrics(run_dir)]
