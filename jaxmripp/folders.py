"""What a folder named on the command line is, checked before a command writes anything.

Two kinds hold a policy:
- a training run, what train.py writes: config.yaml, metrics.jsonl and
  checkpoints/last/<step>/ (and checkpoints/best/<step>/);
- an export, what `python -m jaxmripp.export` writes: policy.json and policy.npz, with the
  run's config.yaml beside them when `python -m jaxmripp.ship` wrote it (pretrained/*).

The checks read files only (YAML, JSON and the NumPy weights, whose hash is verified), so
a mistaken command fails before it imports the trainer; a checkpoint that is present but
unreadable is found when it is restored, still before anything is written.
"""

from __future__ import annotations

import json
from pathlib import Path

from jaxmripp import config as cfgmod
from jaxmripp.runtime import weights as weights_format

RUN_ALLOWED = ("a training run (a folder train.py wrote: config.yaml and "
               "checkpoints/last/<step>/)")
EXPORT_ALLOWED = ("an export (a folder with policy.json and policy.npz, written by python -m "
                  "jaxmripp.export or python -m jaxmripp.ship, e.g. pretrained/default)")


class FolderError(ValueError):
    """A folder is not the kind the command needs; the message is one line naming what it
    is and what is allowed."""


def checkpoint_steps(run_dir: str | Path, best: bool = False) -> list[int]:
    """The steps saved under run_dir/checkpoints/last (or best), oldest first; orbax names
    a finished step's folder by its number (a save in progress carries a suffix)."""
    folder = Path(run_dir) / "checkpoints" / ("best" if best else "last")
    if not folder.is_dir():
        return []
    return sorted(int(p.name) for p in folder.iterdir() if p.is_dir() and p.name.isdigit())


def is_training_run(folder: str | Path) -> bool:
    """Whether `folder` holds a checkpoint train.py saved (an empty checkpoints/ does not
    make a training run)."""
    return bool(checkpoint_steps(folder))


def is_export(folder: str | Path) -> bool:
    folder = Path(folder)
    return any((folder / name).is_file()
               for name in (weights_format.HEADER_FILE, weights_format.WEIGHTS_FILE))


def _what(folder: Path) -> str:
    """What `folder` holds, in a few words, for a message that refuses it."""
    if not folder.exists():
        return "no such folder"
    if not folder.is_dir():
        return "a file, not a folder"
    if is_training_run(folder):
        return "a training run, not an export (export it: python -m jaxmripp.export RUN_DIR)"
    if is_export(folder):
        return "an export, not a training run"
    if not any(folder.iterdir()):
        return "an empty folder"
    return f"neither a training run nor an export (it holds {_contents(folder)})"


def _contents(folder: Path) -> str:
    """The first few names in `folder`, for a message."""
    names = sorted(p.name for p in folder.iterdir())
    return ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")


def new_run(folder: str | Path) -> Path:
    """`folder` for a new training run (train.py --run-dir): one that does not exist yet or
    an empty folder; FolderError otherwise, so that no run is written over another."""
    folder = Path(folder)
    if not folder.exists() or (folder.is_dir() and not any(folder.iterdir())):
        return folder
    if not folder.is_dir():
        what = "a file, not a folder"
    elif is_training_run(folder):
        what = f"holds a training run (continue it with --resume {folder})"
    else:
        what = f"not empty (it holds {_contents(folder)})"
    raise FolderError(f"--run-dir {folder}: {what}; allowed: a new or empty folder")


def training_run(folder: str | Path, best: bool = False) -> cfgmod.Config:
    """The config of the training run in `folder`, which must hold a checkpoint to restore
    (checkpoints/best with `best`); FolderError or ConfigError otherwise."""
    folder = Path(folder)
    if not checkpoint_steps(folder, best):
        what = _what(folder)
        if is_training_run(folder):  # --best on a run without a best checkpoint
            what = "no checkpoint in checkpoints/best"
        raise FolderError(f"{folder}: {what}; allowed: {RUN_ALLOWED}")
    return cfgmod.load(folder / "config.yaml")


def export(folder: str | Path, with_config: bool = False) -> weights_format.ExportedPolicy:
    """The export in `folder`, loaded and its weights' hash verified (RuntimeInputError if
    a file is corrupt); with `with_config`, its config.yaml must load too (what eval.py
    needs to rebuild the policy's environment)."""
    folder = Path(folder)
    if not (folder.is_dir() and is_export(folder)):
        raise FolderError(f"{folder}: {_what(folder)}; allowed: {EXPORT_ALLOWED}")
    exported = weights_format.load(folder)
    if with_config:
        config_of(folder)
    return exported


def config_of(folder: Path) -> cfgmod.Config:
    if not (folder / "config.yaml").is_file():
        raise FolderError(f"{folder}: an export without config.yaml; allowed: a shipped "
                          "folder (python -m jaxmripp.ship) or a training run")
    return cfgmod.load(folder / "config.yaml")


def policy(folder: str | Path, best: bool = False, with_config: bool = True) -> str:
    """Checks that `folder` holds a policy eval.py or train.init_from can load: a training
    run with a checkpoint, or an export (with config.yaml if `with_config`). Returns
    "run" or "export"."""
    folder = Path(folder)
    if is_training_run(folder):
        training_run(folder, best)
        return "run"
    if folder.is_dir() and is_export(folder):
        export(folder, with_config)
        return "export"
    raise FolderError(f"{folder}: {_what(folder)}; allowed: {RUN_ALLOWED} or "
                      f"{EXPORT_ALLOWED}")


def metrics(folder: str | Path) -> list[dict]:
    """The records of folder/metrics.jsonl (one per training update; [] without the file;
    a last line cut mid-write left out); FolderError if another line is not a record."""
    from jaxmripp.learn.metrics import MetricsError, read_metrics

    try:
        return read_metrics(folder)
    except MetricsError as err:
        raise FolderError(str(err)) from None


def train_minutes(folder: str | Path) -> float | None:
    """The training time of a run or shipped folder: its chunks' seconds in metrics.jsonl,
    in minutes (None without records)."""
    records = metrics(folder)
    return sum(r["seconds"] for r in records) / 60 if records else None
