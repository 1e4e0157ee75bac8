"""Run folders: a fresh one for every new run, and what resuming one may change.

A resumed run (`train.py --resume RUN key=value ...`) may change only settings that leave
the trained parameters as they are: how long it trains (`train.updates`), how often it
reports and saves (`train.updates_per_chunk`, `train.keep_checkpoints`, `train.log`) and
the evaluation after training (`train.eval_*`, `eval.*`). The run's config.yaml is then
rewritten with them, and resumes.jsonl gets a line with the update the run resumed at
and every change, so the folder always describes the run it holds. Any other change
would make the rest of the run train something else than config.yaml says: refused.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from jaxmripp import config as cfgmod
from jaxmripp.config import Config

CONFIG_FILE = "config.yaml"
RESUMES_FILE = "resumes.jsonl"
RESUMABLE_KEYS = ("train.updates", "train.updates_per_chunk", "train.keep_checkpoints",
                  "train.log", "train.eval_worlds", "train.eval_budget")
RESUMABLE_SECTIONS = ("eval",)


def fresh_run_dir(root: Path, name: str) -> Path:
    """runs/<name>, or runs/<name>-2, -3, ... so an earlier run is never overwritten."""
    candidate, n = root / name, 1
    while candidate.exists():
        n += 1
        candidate = root / f"{name}-{n}"
    return candidate


def _flat(cfg: Config) -> dict[str, Any]:
    return {f"{section}.{key}": value
            for section, values in cfgmod.to_dict(cfg).items() for key, value in values.items()}


def resumable(key: str) -> bool:
    return key in RESUMABLE_KEYS or key.split(".")[0] in RESUMABLE_SECTIONS


def training_part(cfg: Config) -> Config:
    """`cfg` with everything a resumed run may change at its default: what decides the
    trained parameters."""
    defaults = Config()
    train = dataclasses.replace(cfg.train, **{
        key.split(".")[1]: getattr(defaults.train, key.split(".")[1])
        for key in RESUMABLE_KEYS})
    return dataclasses.replace(cfg, train=train, **{
        section: getattr(defaults, section) for section in RESUMABLE_SECTIONS})


def resume_changes(run_dir: Path, cfg: Config) -> dict[str, dict[str, Any]]:
    """What `cfg` changes of the run's config.yaml ({key: {"from": ..., "to": ...}});
    raises ConfigError, naming the first such key, for a change a resumed run may not
    make."""
    saved = _flat(cfgmod.load(run_dir / CONFIG_FILE))
    changes = {key: {"from": saved[key], "to": value} for key, value in _flat(cfg).items()
               if saved[key] != value}
    refused = [key for key in changes if not resumable(key)]
    if refused:
        key = refused[0]
        raise cfgmod.ConfigError(
            f"{key}: got {changes[key]['to']!r} to resume {str(run_dir)!r}, which trained "
            f"with {changes[key]['from']!r}; allowed on resume: changes to "
            f"{', '.join(RESUMABLE_KEYS)} and eval.* (a new run for anything else)")
    return changes


def record_resume(run_dir: Path, cfg: Config, update: int,
                  changes: dict[str, dict[str, Any]]) -> None:
    """config.yaml rewritten with `cfg` and a line in resumes.jsonl, when there are
    changes."""
    if not changes:
        return
    (run_dir / CONFIG_FILE).write_text(cfgmod.to_yaml(cfg))
    with open(run_dir / RESUMES_FILE, "a") as fh:
        fh.write(json.dumps({"update": update, "changes": changes}) + "\n")
