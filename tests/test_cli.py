"""The one command line, `jaxmripp COMMAND` (jaxmripp/cli): the console script pyproject
declares resolves to the dispatcher, which lists and runs every command; presets load by
name from any directory; the benchmarks take positional dotted overrides. In-process calls
(`main(argv)`), one slow test as a process from outside the repository."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from jaxmripp import config as cfgmod
from jaxmripp.cli import bench
from jaxmripp.cli import main as cli
from jaxmripp.config import presets

REPO = Path(__file__).resolve().parents[1]
for path in (REPO, REPO / "benchmarks"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import quality  # noqa: E402  (benchmarks/quality.py)

PRESET_FILES = sorted((REPO / "jaxmripp" / "configs").glob("*.yaml"))


def run(capsys, argv: list[str]) -> tuple[int, str, str]:
    """`jaxmripp ARGV` in this process: exit status, stdout, stderr."""
    try:
        status = cli.main(argv)
    except SystemExit as exit_:  # argparse's --help
        status = exit_.code
    out, err = capsys.readouterr()
    return status, out, err


def refused(status: int, err: str) -> str:
    """The error convention: status 2, exactly one line `error: ...` on stderr."""
    assert status == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err.strip()


def test_the_console_script_resolves_to_the_dispatcher():
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    module, _, function = declared["jaxmripp"].partition(":")
    assert getattr(importlib.import_module(module), function) is cli.main
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "configs/*.yaml" in data["package-data"]["jaxmripp"]


def test_help_lists_every_command_and_each_resolves(capsys):
    status, out, _ = run(capsys, ["--help"])
    assert status == 0
    listed = [line.split()[0] for line in out.split("commands:\n")[1].split("\n\n")[0]
              .splitlines()]
    assert listed == ["train", "eval", "export", "ship", "demo", "fly", "bench"]
    for command in listed:
        assert callable(importlib.import_module(cli.COMMANDS[command][0]).main)


def test_a_missing_or_unknown_command_is_one_error_line(capsys):
    line = refused(*run(capsys, [])[::2])
    assert "a command is needed; allowed: train, eval, export, ship, demo, fly, bench" in line
    line = refused(*run(capsys, ["trian"])[::2])
    assert line.startswith("error: jaxmripp trian: no such command; allowed: train, eval")


def test_print_config_from_outside_the_repository_is_the_packaged_preset(
        capsys, tmp_path, monkeypatch):
    """From a folder with no configs/: `--config recipe_quick` is
    jaxmripp/configs/recipe_quick.yaml, also train's default. The printed YAML holds every
    value the preset file sets (read with yaml alone) and the defaults elsewhere, and loads
    back to the same config."""
    monkeypatch.chdir(tmp_path)
    status, out, _ = run(capsys, ["train", "--config", "recipe_quick", "--print-config"])
    assert status == 0
    assert run(capsys, ["train", "--print-config"])[1] == out  # --config's default
    printed = yaml.safe_load(out)
    raw = yaml.safe_load((REPO / "jaxmripp" / "configs" / "recipe_quick.yaml").read_text())
    assert "base" not in raw  # every value below is the file's own
    for section, values in raw.items():
        for key, value in values.items():
            assert printed[section][key] == value, (section, key)
    defaults = cfgmod.to_dict(cfgmod.Config())
    for section, values in defaults.items():
        for key, value in values.items():
            if key not in raw.get(section, {}):
                assert printed[section][key] == value, (section, key)
    assert cfgmod.from_dict(printed) == cfgmod.load(REPO / "configs" / "recipe_quick.yaml")
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_print_config_applies_overrides_on_eval_too(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    status, out, _ = run(capsys, ["eval", "--config", "protocol_table1", "--print-config",
                                  "eval.worlds=2", "robots.count=4"])
    assert status == 0
    printed = yaml.safe_load(out)
    assert (printed["eval"]["worlds"], printed["robots"]["count"]) == (2, 4)
    assert printed["eval"]["trials"] == yaml.safe_load(
        (REPO / "configs" / "protocol_table1.yaml").read_text())["eval"]["trials"]


def test_an_unknown_preset_name_lists_the_presets(capsys):
    line = refused(*run(capsys, ["train", "--config", "smokey", "--print-config"])[::2])
    assert "smokey: no such preset; allowed: a config file or a preset name" in line
    assert all(path.stem in line for path in PRESET_FILES)


@pytest.mark.parametrize("command", ["train", "eval"])
def test_help_lists_every_preset_with_its_header_line(capsys, command):
    status, out, _ = run(capsys, [command, "--help"])
    assert status == 0
    listing = out.split("presets (--config NAME")[1]
    assert PRESET_FILES and len(PRESET_FILES) == len(presets.names())
    for path in PRESET_FILES:
        header = path.read_text().splitlines()[0]
        assert header.startswith("# ") and len(header) > 10, path.name
        assert f"  {path.stem} " in listing and header[2:] in listing, path.name


def test_a_benchmark_takes_positional_overrides(capsys):
    status = quality.main(["--print-config", "--worlds", "3", "eval.worlds=2",
                           "sensor.gain_occlusion=true"])
    printed = yaml.safe_load(capsys.readouterr().out)
    assert status == 0
    assert printed["eval"]["worlds"] == 2  # after the protocol's --worlds
    assert printed["sensor"]["gain_occlusion"] is True
    assert printed["eval"]["team_sizes"] == [3]  # the protocol's own settings stay


def test_a_bad_override_in_a_benchmark_is_one_error_line(capsys):
    status = quality.main(["eval.wordls=2"])
    line = refused(status, capsys.readouterr().err)
    assert "eval.wordls: unknown key; did you mean 'eval.worlds'?" in line
    status = quality.main(["worlds=2"])
    assert "overrides look like section.key=value" in refused(status, capsys.readouterr().err)


def test_bench_names_are_the_scripts_of_benchmarks(capsys):
    helpers = {"__init__", "common", "figures", "scale_report"}
    scripts = {p.stem for p in (REPO / "benchmarks").glob("*.py")} - helpers
    assert set(bench.BENCHMARKS) == scripts
    line = refused(*run(capsys, ["bench", "nosuch"])[::2])
    assert line == f"error: jaxmripp bench: got 'nosuch'; allowed: {', '.join(bench.BENCHMARKS)}"
    refused(*run(capsys, ["bench"])[::2])


def test_bench_without_a_source_checkout_says_so(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "scripts_folder", lambda: tmp_path / "benchmarks")
    line = refused(*run(capsys, ["bench", "quality"])[::2])
    assert f"no {tmp_path / 'benchmarks' / 'quality.py'}" in line
    assert "pip install -e" in line and ", ".join(bench.BENCHMARKS) in line


def test_bench_runs_a_script_with_its_arguments(capsys, tmp_path, monkeypatch):
    """A benchmark run through `jaxmripp bench` parses its own command line: here
    safety.py printing its merged config (no simulation), from outside the repository."""
    monkeypatch.chdir(tmp_path)
    status, out, err = run(capsys, ["bench", "safety", "--worlds", "3", "--print-config",
                                    "safety.flight=optimistic"])
    assert status == 0, err
    printed = yaml.safe_load(out)
    assert printed["safety"]["flight"] == "optimistic" and printed["eval"]["worlds"] == 3
    status, _, err = run(capsys, ["bench", "safety", "--bogus"])
    assert refused(status, err).startswith("error: unrecognized arguments: --bogus")


def test_init_from_in_the_checkout_resolves_from_anywhere(tmp_path, monkeypatch):
    """train.init_from=pretrained/default_fast, a path in the repository: from another
    folder it is the checkout's, while a folder of that name in the working directory comes
    first."""
    monkeypatch.chdir(tmp_path)
    from jaxmripp import pipeline  # noqa: PLC0415

    cfg = cfgmod.load("recipe_quick", ["train.init_from=pretrained/default_fast"])
    assert pipeline.initial_source(cfg) == REPO / "pretrained" / "default_fast"
    pipeline.check_initial_params(cfg)
    (tmp_path / "pretrained" / "default_fast").mkdir(parents=True)
    assert pipeline.initial_source(cfg) == Path("pretrained/default_fast")


@pytest.mark.slow
def test_train_as_a_process_from_outside_the_repository(tmp_path):
    """`python -m jaxmripp train --config SMOKE` (tests/smoke.yaml) in an empty folder: the
    run folder is made there, with the config the file and overrides load to, and its
    TensorBoard events hold every scalar of metrics.jsonl for the two updates asked for."""
    import numpy as np  # noqa: PLC0415

    from event_files import scalars  # noqa: PLC0415  (tests/event_files.py)
    from jaxmripp.learn import metrics as metricsmod  # noqa: PLC0415

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    overrides = ["train.updates=2", "train.updates_per_chunk=1", "train.name=outside"]
    done = subprocess.run([sys.executable, "-m", "jaxmripp", "train", "--config",
                           str(REPO / "tests" / "smoke.yaml"),
                           "--no-eval", "--quiet", *overrides],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    run_dir = tmp_path / "runs" / "outside"
    assert cfgmod.load(run_dir / "config.yaml") == cfgmod.load(
        REPO / "tests" / "smoke.yaml", overrides)
    records = [json.loads(line) for line in
               (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    assert [r["update"] for r in records] == [1, 2]
    expected = {(key, r["update"]): [np.float32(value)] for r in records
                for key, value in r.items() if key != "update"}
    assert scalars(run_dir / metricsmod.TENSORBOARD_DIR) == expected


def test_eval_help_names_the_folders_results_go_to_by_default(capsys):
    from jaxmripp import pipeline

    _, out, _ = run(capsys, ["eval", "--help"])
    text = " ".join(out.split())
    # a shipped export stays as shipped: its evaluation goes under runs/
    assert "runs/<folder name>/eval for a shipped export" in text
    assert pipeline.eval_dir("protocol_table1", [REPO / "pretrained" / "default"]) == Path(
        "runs/default/eval")
    assert "runs/<config name>/eval" in text
    assert pipeline.eval_dir("protocol_table1", []) == Path("runs/protocol_table1/eval")
