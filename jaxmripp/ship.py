"""Ships a trained run as a pretrained policy folder (e.g. pretrained/default).

    python -m jaxmripp.ship RUN_DIR OUT_DIR [--best] [--results FILE ...] [--commit SHA]
    python -m jaxmripp.ship --metadata FOLDER [--results FILE ...] [--commit SHA]

OUT_DIR gets the export the runtime and `eval.py --policy NAME=OUT_DIR` load
(policy.npz, policy.json), the run's config.yaml, metrics.jsonl and learning curve, and
metadata.json, every figure of which is read from a file a command wrote:

    commit               HEAD, or --commit (the commit the run trained with)
    command, init_from   the training command: the packaged preset that loads to the
                         run's config (but for train.name, the run folder's name), else
                         the shipped config.yaml; where it started from
    train_minutes        the sum of the chunks' times in metrics.jsonl
    updates, agent_steps, training_discovered   metrics.jsonl's last record
    evaluations          per result FILE (the JSON lines benchmarks/quality.py or
                         benchmarks/scale.py --eval print): its path, the command that
                         printed it and the rules it evaluated under (its `*.command`
                         and `*.rules` lines; for a file printed before those, the command
                         and the sweep's `eval` settings its --out wrote beside it in
                         results.md and summary.json) and its figures

--metadata rewrites FOLDER/metadata.json of a shipped folder from the folder's own files
(metrics.jsonl, config.yaml, policy.json) and the result files, and writes nothing else.
Nothing is written until every input has been read and checked.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

from jaxmripp import config as cfgmod, folders
from jaxmripp.config import presets
from jaxmripp.config.cli import ArgumentParser, fail
from jaxmripp.learn.metrics import episode_mean

METADATA = "metadata.json"
# Lines of a result file that are not figures: how it was made, and a training figure
# whose source is the run's own metrics.jsonl.
NOT_FIGURES = (".command", ".rules", ".train_minutes")


class ShipError(ValueError):
    """A result file or the run's metrics cannot be read as ship needs them."""


def _commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def read_results(path: Path) -> dict:
    """One result file as metadata records it: {"results", "command", "rules", "figures"}
    (ShipError naming the file if it is not a benchmark's output)."""
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except OSError as err:
        raise ShipError(f"--results {path}: cannot read ({err.strerror or err})") from None
    figures, command, rules = {}, None, None
    for number, line in enumerate(lines, 1):
        try:
            record = json.loads(line)
            name, value = record["name"], record["value"]
        except (json.JSONDecodeError, TypeError, KeyError):
            raise ShipError(f"--results {path}: line {number} is not a benchmark figure "
                            '(a JSON object with "name" and "value")') from None
        if name.endswith(".command"):
            command = value
        elif name.endswith(".rules"):
            rules = value
        elif not name.endswith(NOT_FIGURES):
            figures[name] = value
    if command is None or rules is None:  # printed before the lines that name them
        beside = written_beside(path)
        command, rules = command or beside[0], rules or beside[1]
    missing = [what for what, value in (
        ("command (a *.command line, or results.md beside it)", command),
        ("rules (a *.rules line, or summary.json beside it)", rules),
        ("figures", figures)) if not value]
    if missing:
        raise ShipError(f"--results {path}: no {', no '.join(missing)}; allowed: the output "
                        "of benchmarks/quality.py or benchmarks/scale.py --eval")
    return {"results": str(path), "command": command, "rules": rules, "figures": figures}


def written_beside(path: Path) -> tuple[str | None, dict | None]:
    """What an evaluation run with --out wrote beside its JSON lines: its command (the
    "Command:" line of results.md) and its sweep's settings (summary.json's "eval");
    None for what is not there."""
    command = rules = None
    table = path.parent / "results.md"
    if table.is_file():
        command = next((line.strip()[len("Command: `"):-1] for line in
                        table.read_text().splitlines() if line.startswith("Command: `")), None)
    summary = path.parent / "summary.json"
    if summary.is_file():
        try:
            rules = {"eval": json.loads(summary.read_text())["eval"]}
        except (json.JSONDecodeError, KeyError, TypeError):
            raise ShipError(f"{summary}: not an evaluation summary (no 'eval' settings)"
                            ) from None
    return command, rules


# Settings a training command may give beside its preset: they choose the run's folder,
# its random seed and where it starts from, not the recipe.
COMMAND_OVERRIDES = ("name", "seed", "init_from")


def training_command(cfg: cfgmod.Config, shipped_config: Path) -> str:
    """`jaxmripp train --config X [train.seed=S] [train.init_from=DIR]`: X the name of the
    first packaged preset that loads to `cfg` but for `COMMAND_OVERRIDES` (train.name only
    names the run's folder, so it is left out), else the shipped config.yaml (which loads
    to `cfg` exactly)."""
    for name in presets.names():
        try:
            preset = cfgmod.load(name)
        except cfgmod.ConfigError:
            continue
        kept = {key: getattr(cfg.train, key) for key in COMMAND_OVERRIDES}
        if dataclasses.replace(preset, train=dataclasses.replace(preset.train, **kept)) == cfg:
            overrides = [f"train.{key}={kept[key]}" for key in COMMAND_OVERRIDES[1:]
                         if kept[key] != getattr(preset.train, key)]
            return " ".join(["jaxmripp train --config", name, *overrides])
    return f"jaxmripp train --config {shipped_config}"


def metadata(cfg: cfgmod.Config, trained: Path, config_path: Path, checkpoint: str,
             evaluations: list[dict], commit: str | None) -> dict:
    """metadata.json's content (see the module's docstring); `trained` holds the run's
    metrics.jsonl."""
    records = _metrics(trained)
    meta = {
        "commit": commit or _commit(),
        "command": training_command(cfg, config_path),
        "train_minutes": round(folders.train_minutes(trained), 1),
        "checkpoint": checkpoint,
        "updates": records[-1]["update"],
        "agent_steps": records[-1]["env_steps"],
        # over the episodes that ended in the last chunk's updates (some end in none); by
        # update number, as a run's records may be one per update or one per chunk
        "training_discovered": round(episode_mean(
            [r for r in records
             if r["update"] > records[-1]["update"] - cfg.train.updates_per_chunk],
            "discovered"), 4),
    }
    if cfg.train.init_from:
        meta["init_from"] = cfg.train.init_from
    meta["evaluations"] = evaluations
    return meta


def _metrics(folder: Path) -> list[dict]:
    records = folders.metrics(folder)
    if not records:
        raise ShipError(f"{folder}: no training metrics (metrics.jsonl)")
    return records


def _write(path: Path, meta: dict) -> Path:
    path.write_text(json.dumps(meta, indent=2) + "\n")
    return path


def _check_out_dir(out_dir: Path, run_dir: Path) -> None:
    """OUT_DIR is new, empty or a shipped folder to replace: never the run itself nor a
    folder of other files."""
    if out_dir.resolve() == run_dir.resolve():
        raise folders.FolderError(f"{out_dir}: the run itself; allowed: another folder")
    if out_dir.exists() and not (out_dir.is_dir() and (folders.is_export(out_dir)
                                                       or not any(out_dir.iterdir()))):
        raise folders.FolderError(f"{out_dir}: holds other files; allowed: a new or empty "
                                  "folder, or a shipped folder to replace")


def ship(run_dir: Path, out_dir: Path, best: bool = False, results: list[Path] = (),
         commit: str | None = None) -> Path:
    from jaxmripp.evaluation import viz
    from jaxmripp.export import export, restore_run

    folders.training_run(run_dir, best)  # the cheap checks first: files only
    _check_out_dir(out_dir, run_dir)
    _metrics(run_dir)
    evaluations = [read_results(Path(path)) for path in results]
    cfg, params, source = restore_run(run_dir, best)
    meta = metadata(cfg, run_dir, out_dir / "config.yaml", source["checkpoint"], evaluations,
                    commit)
    export(cfg, params, out_dir, source)
    for name in ("config.yaml", "metrics.jsonl"):
        shutil.copyfile(run_dir / name, out_dir / name)
    viz.learning_curve(out_dir / "learning_curve.png", folders.metrics(run_dir),
                       keys=("discovered", "return", "entropy"))
    return _write(out_dir / METADATA, meta)


def rewrite_metadata(folder: Path, results: list[Path] = (), commit: str | None = None
                     ) -> Path:
    """FOLDER/metadata.json of a shipped folder, from its own files and `results`."""
    exported = folders.export(folder, with_config=True)
    cfg = cfgmod.load(folder / "config.yaml")
    evaluations = [read_results(Path(path)) for path in results]
    checkpoint = exported.header.get("source", {}).get("checkpoint", "last")
    return _write(folder / METADATA, metadata(cfg, folder, folder / "config.yaml",
                                              checkpoint, evaluations, commit))


def main(argv: list[str] | None = None, prog: str = "python -m jaxmripp.ship") -> int:
    parser = ArgumentParser(prog=prog, description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path, nargs="?")
    parser.add_argument("out_dir", type=Path, nargs="?")
    parser.add_argument("--metadata", type=Path, metavar="FOLDER",
                        help="rewrite a shipped folder's metadata.json only")
    parser.add_argument("--best", action="store_true", help="ship the best checkpoint")
    parser.add_argument("--results", "--quality", type=Path, action="append", default=[],
                        metavar="FILE", help="a benchmark's output (repeatable)")
    parser.add_argument("--commit", help="the commit the run trained with (default: HEAD)")
    args = parser.parse_args(argv)
    given = [path for path in (args.run_dir, args.out_dir) if path is not None]
    if len(given) != (0 if args.metadata else 2):
        parser.error("give RUN_DIR OUT_DIR, or --metadata FOLDER alone")

    from jaxmripp.export import ExportError
    from jaxmripp.learn.checkpoint import CheckpointError
    from jaxmripp.runtime.errors import RuntimeInputError

    refused = (ShipError, folders.FolderError, cfgmod.ConfigError, ExportError, CheckpointError,
               RuntimeInputError)
    try:
        if args.metadata is not None:
            path = rewrite_metadata(args.metadata, args.results, args.commit)
            print(f"wrote {path}")
        else:
            path = ship(args.run_dir, args.out_dir, args.best, args.results, args.commit)
            print(f"shipped {args.run_dir} to {args.out_dir} ({path.name})")
    except refused as err:
        return fail(err)
    except OSError as err:
        return fail(f"{err.filename or ''}: cannot write ({err.strerror or err})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
