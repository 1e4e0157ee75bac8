"""Every entry point refuses a folder or file of the wrong kind the same way: one line
`error: ...` on stderr, exit status 2, no traceback, and every folder on disk exactly as it
was (files and folders hashed before and after).

The kinds of bad input: a missing folder, an empty one, one holding config.yaml only, an
export whose policy.npz is corrupt, a training run whose checkpoint is corrupt, an export
where a training run is needed (a copy of a shipped folder) and a training run where an
export is needed. The entry points run in-process (their `main(argv)`), which is what a
user sees but the interpreter's own start; two subprocess runs check that too, and the
whole matrix as subprocesses is the slow test's.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import pytest

from jaxmripp import config as cfgmod, demo, export, ship
from jaxmripp.flight import __main__ as flight
from jaxmripp.learn.checkpoint import Checkpoints

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "pretrained" / "default_fast"
SMOKE = REPO / "tests" / "smoke.yaml"
for path in (REPO, REPO / "benchmarks"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import eval as eval_cli  # noqa: E402
import quality  # noqa: E402  (benchmarks/quality.py)
import train as train_cli  # noqa: E402


@pytest.fixture(scope="module")
def bad(tmp_path_factory) -> dict[str, Path]:
    """One folder of each kind under a common root (`bad["root"]`)."""
    root = tmp_path_factory.mktemp("folders")
    made = {"root": root, "missing": root / "missing", "empty": root / "empty",
            "config_only": root / "config_only", "corrupt_npz": root / "corrupt_npz",
            "corrupt_checkpoint": root / "corrupt_checkpoint", "shipped": root / "shipped"}
    made["empty"].mkdir()
    made["config_only"].mkdir()
    shutil.copyfile(SMOKE, made["config_only"] / "config.yaml")
    shutil.copytree(SHIPPED, made["shipped"])
    shutil.copytree(SHIPPED, made["corrupt_npz"])
    npz = made["corrupt_npz"] / "policy.npz"
    npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
    # A training run whose checkpoint files were damaged after a save.
    run = made["corrupt_checkpoint"]
    run.mkdir()
    (run / "config.yaml").write_text(cfgmod.to_yaml(cfgmod.load(SMOKE)))
    (run / "metrics.jsonl").write_text('{"update": 1, "env_steps": 32, "seconds": 6.0, '
                                       '"discovered": 0.1}\n')
    checkpoints = Checkpoints(run / "checkpoints", keep=1)
    try:
        checkpoints.save(0, {"x": jnp.zeros(3)}, score=0.0)
    finally:
        checkpoints.close()
    for path in (run / "checkpoints").rglob("*"):
        if path.is_file():
            path.write_bytes(b"\x00garbage" * 8)
    return made


def snapshot(root: Path) -> dict[str, str]:
    """Every file's sha256 and every folder (an empty one too) under root."""
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest()
                                       if p.is_file() else "folder")
            for p in sorted(root.rglob("*"))}


def refused(capsys, run) -> tuple[str, str]:
    """Runs `run()` (an entry point's main) and checks the convention: status 2, stderr
    exactly one line `error: ...`; returns that line and stdout."""
    try:
        status = run()
    except SystemExit as exit_:  # python -m jaxmripp.demo ends with SystemExit
        status = exit_.code
    out, err = capsys.readouterr()
    assert status == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err.strip(), out


def unchanged(bad, capsys, run) -> tuple[str, str]:
    """`refused`, with every folder under bad["root"] as it was before."""
    before = snapshot(bad["root"])
    refusal = refused(capsys, run)
    assert snapshot(bad["root"]) == before
    return refusal


# What each entry point needs, and the folders that are not that.
NOT_A_RUN = ["missing", "empty", "config_only", "shipped", "corrupt_npz", "corrupt_checkpoint"]
NOT_AN_EXPORT = ["missing", "empty", "config_only", "corrupt_npz", "corrupt_checkpoint"]
NOT_A_POLICY = ["missing", "empty", "config_only", "corrupt_npz", "corrupt_checkpoint"]
WORDS = {"missing": "no such folder", "empty": "an empty folder",
         "config_only": "neither a training run nor an export (it holds config.yaml)",
         "shipped": "an export, not a training run", "corrupt_npz": "policy.npz",
         "corrupt_checkpoint": "cannot restore"}


@pytest.mark.parametrize("kind", NOT_A_RUN)
def test_export_refuses_anything_but_a_run_with_a_checkpoint(bad, capsys, kind):
    """The shipped folder is the reported case: export used to leave empty
    checkpoints/best and checkpoints/last behind, which made it look like a run."""
    line, _ = unchanged(bad, capsys, lambda: export.main([str(bad[kind])]))
    expected = "an export, not a training run" if kind == "corrupt_npz" else WORDS[kind]
    assert expected in line


@pytest.mark.parametrize("kind", NOT_A_RUN)
def test_ship_refuses_anything_but_a_run_and_leaves_its_target_alone(bad, capsys, kind):
    # The target is an existing shipped folder: a refused ship must not touch it either.
    line, _ = unchanged(bad, capsys, lambda: ship.main([str(bad[kind]), str(bad["shipped"])]))
    if kind != "shipped":  # shipping a folder onto itself: refused as not a run first
        assert (WORDS["shipped"] if kind == "corrupt_npz" else WORDS[kind]) in line


def test_ship_refuses_a_target_of_other_files_and_a_metadata_rewrite_of_a_run(bad, capsys):
    run = str(bad["corrupt_checkpoint"])
    line, _ = unchanged(bad, capsys, lambda: ship.main([run, str(bad["config_only"])]))
    assert "holds other files; allowed: a new or empty folder, or a shipped folder" in line
    line, _ = unchanged(bad, capsys, lambda: ship.main([run, run]))
    assert "the run itself" in line
    line, _ = unchanged(bad, capsys, lambda: ship.main(["--metadata", run]))
    assert "a training run, not an export" in line
    line, _ = unchanged(bad, capsys, lambda: ship.main(["--metadata", str(bad["corrupt_npz"])]))
    assert "policy.npz" in line
    line, _ = unchanged(bad, capsys, lambda: ship.main(["--metadata", str(bad["shipped"]),
                                                       "--results", str(SMOKE)]))
    assert "line 1 is not a benchmark figure" in line


@pytest.mark.parametrize("kind", NOT_A_POLICY)
def test_eval_refuses_a_policy_folder_of_no_kind_or_corrupt(bad, capsys, kind):
    line, _ = unchanged(bad, capsys, lambda: eval_cli.main([
        "--config", str(SMOKE), "--policy", f"mine={bad[kind]}", "--out",
        str(bad["root"] / "missing"), "--no-render"]))
    assert line.startswith("error: --policy mine: ") and WORDS[kind] in line


@pytest.mark.parametrize("kind", NOT_A_RUN)
def test_train_resume_refuses_anything_but_a_run_with_a_checkpoint(bad, capsys, kind):
    """Resuming a shipped folder used to train afresh into it, overwriting its
    config.yaml and metrics.jsonl."""
    runs = bad["root"] / "missing"  # a new run would create it
    line, _ = unchanged(bad, capsys, lambda: train_cli.main(
        ["--resume", str(bad[kind]), "--runs", str(runs), "--no-eval"]))
    expected = "an export, not a training run" if kind == "corrupt_npz" else WORDS[kind]
    assert expected in line


@pytest.mark.parametrize("kind", NOT_A_POLICY)
def test_train_init_from_refuses_before_choosing_a_run_folder(bad, capsys, kind):
    runs = bad["root"] / "missing"
    line, out = unchanged(bad, capsys, lambda: train_cli.main(
        ["--config", str(SMOKE), "--runs", str(runs), "--no-eval",
         f"train.init_from={bad[kind]}"]))
    assert line.startswith("error: train.init_from: ") and WORDS[kind] in line
    assert "run folder" not in out


@pytest.mark.parametrize("kind", ["config_only", "shipped", "corrupt_checkpoint"])
def test_train_run_dir_refuses_a_folder_that_holds_anything(bad, capsys, kind):
    """--run-dir names the folder a new run is created in: never one with files."""
    folder = bad[kind]
    line, out = unchanged(bad, capsys, lambda: train_cli.main(
        ["--config", str(SMOKE), "--run-dir", str(folder), "--no-eval"]))
    what = {"config_only": "not empty (it holds config.yaml)",
            "shipped": "not empty (it holds config.yaml, learning_curve.png, metadata.json, "
                       "metrics.jsonl, ...)",
            "corrupt_checkpoint": f"holds a training run (continue it with --resume {folder})"}
    assert line == f"error: --run-dir {folder}: {what[kind]}; allowed: a new or empty folder"
    assert "run folder" not in out


@pytest.mark.parametrize("other", ["--resume", "--runs"])
def test_train_run_dir_goes_with_neither_resume_nor_runs(bad, capsys, other):
    line, _ = unchanged(bad, capsys, lambda: train_cli.main(
        ["--run-dir", str(bad["missing"]), other, str(bad["corrupt_checkpoint"]), "--no-eval"]))
    assert line.startswith(f"error: argument --run-dir: not allowed with argument {other}")


@pytest.mark.parametrize("kind", NOT_AN_EXPORT)
def test_flight_and_demo_refuse_anything_but_an_intact_export(bad, capsys, kind):
    out = bad["root"] / "missing"
    unchanged(bad, capsys, lambda: flight.main(["--export", str(bad[kind]), "--out", str(out),
                                                "--no-pictures"]))
    line, _ = unchanged(bad, capsys, lambda: demo.main(["--export", str(bad[kind]), "--quiet"]))
    expected = {"corrupt_checkpoint": "a training run, not an export (export it: python -m "
                                      "jaxmripp.export RUN_DIR)"}.get(kind, WORDS[kind])
    assert expected in line


@pytest.mark.parametrize("kind", NOT_A_POLICY)
def test_a_benchmark_refuses_a_policy_folder_of_no_kind_or_corrupt(bad, capsys, kind):
    line, _ = unchanged(bad, capsys, lambda: quality.main(
        ["--policy", str(bad[kind]), "--worlds", "1", "--trials", "1", "--planners", "policy",
         "world.size=20"]))
    assert WORDS[kind] in line


def test_usage_mistakes_are_one_line_too(bad, capsys):
    line, _ = unchanged(bad, capsys, lambda: export.main([str(bad["shipped"]), "--bogus"]))
    assert line == ("error: unrecognized arguments: --bogus; allowed: see "
                    "python -m jaxmripp.export --help")
    unchanged(bad, capsys, lambda: ship.main([str(bad["shipped"])]))
    unchanged(bad, capsys, lambda: quality.main(["--planners", "policy,magic"]))


def _as_user(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300)


def test_what_a_user_sees_from_the_reported_commands(bad):
    """As processes: export on a shipped folder, and eval.py on a corrupt policy.npz."""
    before = snapshot(bad["root"])
    for args in (["-m", "jaxmripp.export", str(bad["shipped"])],
                 ["eval.py", "--policy", f"policy={bad['corrupt_npz']}"]):
        done = _as_user(args)
        assert done.returncode == 2 and done.stderr.startswith("error: "), done.stderr
        assert done.stderr.count("\n") == 1, done.stderr
    assert snapshot(bad["root"]) == before


ENTRY_POINTS = {
    "train": lambda folder: ["train.py", "--resume", str(folder), "--no-eval"],
    "eval": lambda folder: ["eval.py", "--config", str(SMOKE), "--policy", f"p={folder}"],
    "export": lambda folder: ["-m", "jaxmripp.export", str(folder)],
    "ship": lambda folder: ["-m", "jaxmripp.ship", str(folder), str(folder.parent / "out")],
    "flight": lambda folder: ["-m", "jaxmripp.flight", "--export", str(folder), "--out",
                              str(folder.parent / "out"), "--no-pictures"],
    "demo": lambda folder: ["-m", "jaxmripp.demo", "--export", str(folder), "--quiet"],
    "quality": lambda folder: ["benchmarks/quality.py", "--policy", str(folder)],
}
CASES = [(entry, kind) for entry in ENTRY_POINTS for kind in
         {"train": NOT_A_RUN, "export": NOT_A_RUN, "ship": NOT_A_RUN,
          "flight": NOT_AN_EXPORT, "demo": NOT_AN_EXPORT}.get(entry, NOT_A_POLICY)]


@pytest.mark.slow
@pytest.mark.parametrize("entry, kind", CASES, ids=[f"{e}-{k}" for e, k in CASES])
def test_every_entry_point_as_a_process(bad, entry, kind):
    before = snapshot(bad["root"])
    done = _as_user(ENTRY_POINTS[entry](bad[kind]))
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: ") and done.stderr.count("\n") == 1, done.stderr
    assert snapshot(bad["root"]) == before
