"""The packaged presets a user chooses from (jaxmripp/configs): one naming scheme, at most
ten, each with a first line that says what it is and how long it runs; and the curriculum
`make scale` runs, whose stages chain by folder and load to the settings the shipped
pretrained/scale and the run it started from were trained with."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from jaxmripp import config as cfgmod
from jaxmripp.cli import train as train_cli
from jaxmripp.config import presets
from test_config import _training_settings as training_settings

REPO = Path(__file__).resolve().parents[1]
NAMES = presets.names()
KINDS = {"recipe": "Recipe", "world": "World", "protocol": "Protocol"}


def test_at_most_ten_presets_each_named_by_what_it_is():
    assert 0 < len(NAMES) <= 10
    assert all(name.split("_")[0] in KINDS for name in NAMES), NAMES
    assert presets.DEFAULT in NAMES
    # The tests' tiny config and the paper's training settings are files, not presets.
    assert (REPO / "tests" / "smoke.yaml").is_file()
    assert (REPO / "benchmarks" / "train_paper.yaml").is_file()


@pytest.mark.parametrize("name", NAMES)
def test_the_first_line_says_what_a_preset_is_and_how_long_it_runs(name):
    first = (presets.PRESETS / f"{name}.yaml").read_text().splitlines()[0]
    assert first.startswith(f"# {KINDS[name.split('_')[0]]}"), first
    assert re.search(r"~\d+ min on 2 cores|hours on 2 cores", first), first
    assert presets.summary(name) == first[2:]


def make_target(name: str) -> list[str]:
    """The commands of the Makefile's target `name`, continuation lines joined and the
    Makefile's `VAR := value` variables substituted."""
    text = (REPO / "Makefile").read_text()
    variables = dict(re.findall(r"^(\w+) := (.*)$", text, re.M))
    recipe = text.split(f"\n{name}:")[1].split("\n\n")[0].split("\n", 1)[1]
    commands = recipe.replace("\\\n", " ").splitlines()
    for _ in range(3):  # variables that name variables
        commands = [re.sub(r"\$\((\w+)\)", lambda m: variables.get(m[1], m[0]), c)
                    for c in commands]
    return [" ".join(c.split()) for c in commands]


def test_make_scale_chains_its_stages_by_folder_into_what_trained_pretrained_scale():
    commands = make_target("scale")
    stages = [train_cli.parser().parse_args(shlex.split(c)[2:]) for c in commands
              if shlex.split(c)[1:2] == ["train"]]
    assert len(stages) == 3
    configs = [cfgmod.load(s.config, s.overrides) for s in stages]
    # Fixed folders, each stage starting from the one before; no preset names a start.
    assert [s.run_dir for s in stages] == ["runs/scale_n3", "runs/scale_n8", "runs/scale"]
    assert [c.train.init_from for c in configs] == ["", "runs/scale_n3", "runs/scale_n8"]
    assert all(not cfgmod.load(s.config).train.init_from for s in stages)
    assert [(c.robots.count, c.world.size) for c in configs] == [(3, 50), (8, 50), (16, 75)]
    # The 3-robot start is the policy trained by PPO alone whose record is kept (it no
    # longer ships), and the last stage trains what pretrained/scale was trained with.
    started = cfgmod.load(REPO / "docs/results/alternatives/default_ppo/config.yaml")
    assert training_settings(configs[0]) == training_settings(started)
    shipped = cfgmod.load(REPO / "pretrained/scale/config.yaml")
    assert training_settings(configs[-1]) == training_settings(shipped)
    assert commands[-1].endswith("python -m jaxmripp.ship runs/scale pretrained/scale\"")
