import dataclasses
import math
import re
from pathlib import Path

import pytest
import yaml

from jaxmripp import config as cfgmod
from jaxmripp.config import Config, ConfigError, presets

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
PRESETS = sorted(path.stem for path in CONFIGS.glob("*.yaml"))
# Config files outside the presets: the tests' tiny one, the paper's training settings.
FILES = [CONFIGS / f"{name}.yaml" for name in PRESETS] + [
    REPO / "tests" / "smoke.yaml", REPO / "benchmarks" / "train_paper.yaml"]


def test_every_preset_is_checked():
    assert {"recipe_quick", "world_paper", "protocol_table1"} <= set(PRESETS)
    assert PRESETS == presets.names()


@pytest.mark.parametrize("path", FILES, ids=lambda path: path.stem)
def test_presets_load_and_round_trip(path):
    # Every preset must load and validate: an unknown key or a bad value fails here.
    cfg = cfgmod.load(path)
    again = cfgmod.from_dict(yaml.safe_load(cfgmod.to_yaml(cfg)))
    assert again == cfg
    hash(cfg)  # usable as a static jit argument


SHIPPED = sorted((REPO / "pretrained").glob("*/metadata.json"))


def _training_settings(cfg: Config) -> dict:
    """Every setting that shapes a trained policy: all but the run's name, the run it
    started from (a path on the machine that trained it) and the evaluation settings other
    than the lookahead searches' (the nbv_ahead and nbv_targets teachers read those; the
    teacher's facade weight is ppo.teacher_facade)."""
    flat = {f"{section}.{key}": value
            for section, fields in cfgmod.to_dict(cfg).items() for key, value in fields.items()}
    return {key: value for key, value in flat.items()
            if key not in ("train.name", "train.init_from")
            and (not key.startswith("eval.") or key.startswith(_TEACHER_SEARCH))}


_TEACHER_SEARCH = ("eval.nbv_ahead_", "eval.nbv_targets_strength", "eval.nbv_targets_discount",
                   "eval.nbv_targets_branches")


@pytest.mark.parametrize("metadata", SHIPPED, ids=lambda path: path.parent.name)
def test_shipped_policies_are_what_their_commands_train(metadata):
    # A preset that a shipped policy's command names must still train that policy: a
    # change to a base preset (recipe_quick.yaml) must not change what an older command means.
    command = yaml.safe_load(metadata.read_text())["command"].split("&&")[-1].split()
    assert command[:3] == ["jaxmripp", "train", "--config"], command
    source, overrides = command[3], command[4:]  # a preset's name or a path
    trained = cfgmod.load(metadata.parent / "config.yaml")
    loaded = cfgmod.load(source if presets.is_name(source) else REPO / source, overrides)
    assert _training_settings(loaded) == _training_settings(trained)


def test_infinite_radio_range_round_trips():
    cfg = cfgmod.load(None, ["radio.range=.inf", "eval.radio_ranges=[.inf, 0.1]"])
    assert cfg.radio.range == math.inf
    assert cfgmod.from_dict(yaml.safe_load(cfgmod.to_yaml(cfg))) == cfg


def test_exponents_without_a_dot_are_numbers():
    """YAML 1.1 reads 5e-5 as a string; a number setting takes it as the number."""
    cfg = cfgmod.load(None, ["ppo.learning_rate=5e-5", "gp.noise=1E-3"])
    assert cfg.ppo.learning_rate == 5e-5 and cfg.gp.noise == 1e-3
    with pytest.raises(ConfigError, match="ppo.learning_rate: got 'fast'; allowed: a number"):
        cfgmod.load(None, ["ppo.learning_rate=fast"])
    with pytest.raises(ConfigError, match="allowed: a number"):
        cfgmod.load(None, ["ppo.learning_rate=nan"])


def test_overrides_apply_on_top_of_a_preset():
    cfg = cfgmod.load("configs/recipe_quick.yaml", ["world.size=64", "robots.count=4"])
    assert cfg.world.size == 64 and cfg.robots.count == 4
    assert cfg.robots.budget == (7.0, 9.0)  # from the preset, untouched


def test_paper_preset_inherits_and_changes_the_reference_bits():
    paper = cfgmod.load("configs/world_paper.yaml")
    assert paper.world.target_placement == "footprint"
    assert paper.sensor.model == "frustum"
    assert paper.robots.budget == (7.0, 9.0)


@pytest.mark.parametrize(
    "override, needle",
    [
        ("robots.budget=[-1, 2]", "robots.budget: got [-1.0, 2.0]; allowed: [min, max]"),
        ("robots.budget=[9, 7]", "min <= max"),
        ("radio.collision_distance=0.4", "radio.collision_distance: got 0.4; allowed: less than radio.range"),
        ("world.size=6", "world.size: got 6"),
        ("candidates.positions=0", "candidates.positions: got 0"),
        ("world.layout=spiral", "allowed: one of grid, random"),
        ("sensor.gain_facade=roof", "sensor.gain_facade: got roof; allowed: one of nearby, around, column"),
        ("radio.map_reach=team", "radio.map_reach: got team, a removed setting; allowed: "
                                 "radio (the one built in) or leaving it out"),
        ("world.size=12.5", "allowed: an integer"),
        ("radio.relay=yes please", "allowed: true or false"),
        ("world.buildings=400", "buildings fit"),
        ("ppo.algo=sac", "one of ippo, mappo"),
        ("gp.noise=0", "gp.noise: got 0.0"),
        ("gp.peer_rounds=7", "gp.peer_rounds: got 7, a removed setting; allowed: 255"),
        ("train.radio_ranges=[0.3, .inf]", "train.radio_ranges: got [0.3, inf], a removed "
                                            "setting; allowed: [] (the one built in)"),
        ("world.footprint_min=4", "world.footprint_min: got 4; allowed: 0 (every side"),
        ("train.blocks=3", "train.blocks: got 3; allowed: 0 or a divisor of the environments "
                           "per minibatch (train.envs / ppo.minibatches = 16)"),
    ],
)
def test_bad_values_give_one_clear_line(override, needle):
    with pytest.raises(ConfigError) as err:
        cfgmod.load("configs/recipe_quick.yaml",
                    override if isinstance(override, list) else [override])
    message = str(err.value)
    assert needle in message
    assert "\n" not in message


def test_kickstarting_needs_the_view_features():
    with pytest.raises(ConfigError, match="ppo.teacher_coef: got 1.0; allowed: 0 while"):
        cfgmod.load(None, ["ppo.teacher_coef=1", "policy.view_features=false"])
    with pytest.raises(ConfigError, match="ppo.teacher_updates: got -1"):
        cfgmod.load(None, ["ppo.teacher_updates=-1"])
    with pytest.raises(ConfigError, match="ppo.teacher: got oracle; allowed: one of nbv, nbv_ahead"):
        cfgmod.load(None, ["ppo.teacher=oracle"])
    with pytest.raises(ConfigError, match="ppo.teacher_facade: got -1.0"):
        cfgmod.load(None, ["ppo.teacher_facade=-1"])


@pytest.mark.parametrize("override, teacher_key", [
    ("policy.ahead_facade_weight=4", "ppo.teacher_facade = 2.0"),
    ("policy.ahead_discount=1", "eval.nbv_targets_discount = 3.0"),
    ("eval.nbv_targets_branches=16", "eval.nbv_targets_branches = 16"),
    ("policy.belief_strength=1", "eval.nbv_targets_strength = 3.0"),
])
def test_the_rated_input_ranks_as_its_teacher(override, teacher_key):
    """recipe_default's rated input is its nbv_targets teacher's value: a setting of either
    side alone is refused, naming the other side's value."""
    cfgmod.load("configs/recipe_default.yaml")
    with pytest.raises(ConfigError, match=re.escape(teacher_key)):
        cfgmod.load("configs/recipe_default.yaml", [override])
    # without the teacher the input may weigh as it likes
    cfgmod.load("configs/recipe_default.yaml", [override, "ppo.teacher_coef=0"])


def test_near_miss_key_suggests_the_right_name():
    with pytest.raises(ConfigError, match="did you mean 'world.size'"):
        cfgmod.load(None, ["world.sise=50"])
    with pytest.raises(ConfigError, match="did you mean 'radio'"):
        cfgmod.from_dict({"radoi": {"range": 1.0}})


def test_preset_with_an_unknown_key_is_refused_in_one_line(tmp_path):
    preset = tmp_path / "typo.yaml"
    preset.write_text(f"base: {CONFIGS / 'recipe_quick.yaml'}\neval:\n  wordls: 3\n")
    with pytest.raises(ConfigError) as err:
        cfgmod.load(preset)
    message = str(err.value)
    assert message.startswith("typo.yaml: eval.wordls: unknown key; did you mean 'eval.worlds'?")
    assert "\n" not in message


def test_a_removed_setting_loads_only_at_its_built_in_value(tmp_path):
    """An older run's config.yaml holds the removed keys at the value the code now builds
    in: it loads as the config without them, and a preset or override with another value
    is refused."""
    for key, value in cfgmod.REMOVED.items():
        section, name = key.split(".")
        assert name not in dataclasses.asdict(getattr(Config(), section)), key
        older = tmp_path / "config.yaml"
        older.write_text(yaml.safe_dump({section: {name: value}, "world": {"size": 30}}))
        assert cfgmod.load(older) == cfgmod.load(None, ["world.size=30"])
    with pytest.raises(ConfigError, match="train.radio_ranges: got \\[0.1\\], a removed"):
        cfgmod.load(None, ["train.radio_ranges=[0.1]"])


def test_malformed_override_and_missing_file():
    with pytest.raises(ConfigError, match="section.key=value"):
        cfgmod.load(None, ["size=3"])
    with pytest.raises(ConfigError, match="no such config file"):
        cfgmod.load("configs/nope.yaml")


def test_derived_counts_scale_with_world_size():
    for size, buildings, targets in [(50, 25, 250), (75, 56, 562), (100, 100, 1000), (125, 156, 1562)]:
        world = dataclasses.replace(Config().world, size=size)
        assert world.n_buildings == buildings
        assert world.target_capacity == targets
