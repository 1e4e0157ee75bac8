"""Ships a trained run as a pretrained policy folder (e.g. pretrained/default).

    python -m jaxmripp.ship RUN_DIR OUT_DIR [--best] [--quality FILE] [--wall-minutes M]
                            [--commit SHA]

OUT_DIR gets the export the runtime and `eval.py --policy NAME=OUT_DIR` load
(policy.npz, policy.json), the run's config.yaml, metrics.jsonl and learning curve, and
metadata.json: the commit (HEAD, or --commit: the one the run trained with), the training
command, its wall time (the sum of the chunks' times, or --wall-minutes when measured from
outside), the updates and samples, and the evaluation figures of FILE (the JSON lines
`benchmarks/quality.py` prints) with the command that printed them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path


def _commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def _figures(path: Path | None) -> tuple[dict, str | None]:
    """The figures of a `benchmarks/quality.py` output, and the command that printed them."""
    if path is None:
        return {}, None
    figures = {}
    for line in path.read_text().splitlines():
        if line.strip().startswith("{"):
            record = json.loads(line)
            figures[record["name"]] = record["value"]
    return figures, figures.pop("quality.command", None)


def ship(run_dir: Path, out_dir: Path, best: bool = False, quality: Path | None = None,
         wall_minutes: float | None = None, commit: str | None = None) -> Path:
    from jaxmripp import config as cfgmod
    from jaxmripp.evaluation import viz
    from jaxmripp.export import export_run
    from jaxmripp.learn.metrics import episode_mean, read_metrics

    cfg = cfgmod.load(run_dir / "config.yaml")
    records = read_metrics(run_dir)
    if not records:
        raise FileNotFoundError(f"{run_dir}: no training metrics (metrics.jsonl)")
    export_run(run_dir, best, out_dir)
    for name in ("config.yaml", "metrics.jsonl"):
        shutil.copyfile(run_dir / name, out_dir / name)
    viz.learning_curve(out_dir / "learning_curve.png", records,
                       keys=("discovered", "return", "entropy"))
    preset = Path("configs") / f"{cfg.train.name}.yaml"
    config_arg = preset if preset.is_file() else run_dir / "config.yaml"
    chunks_minutes = sum(r["seconds"] for r in records) / 60
    figures, evaluation_command = _figures(quality)
    metadata = {
        "commit": commit or _commit(),
        "command": f"python train.py --config {config_arg}",
        "train_minutes": round(wall_minutes if wall_minutes is not None else chunks_minutes, 1),
        "train_minutes_in_chunks": round(chunks_minutes, 1),
        "checkpoint": "best" if best else "last",
        "updates": records[-1]["update"],
        "agent_steps": records[-1]["env_steps"],
        # over the episodes that ended in the last chunk's updates
        "training_discovered": round(
            episode_mean(records[-cfg.train.updates_per_chunk:], "discovered"), 4),
        "evaluation": figures,
    }
    if evaluation_command is not None:
        metadata["evaluation_command"] = evaluation_command
    path = out_dir / "metadata.json"
    path.write_text(json.dumps(metadata, indent=2) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxmripp.ship", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--best", action="store_true", help="ship the best checkpoint")
    parser.add_argument("--quality", type=Path, help="benchmarks/quality.py output")
    parser.add_argument("--wall-minutes", type=float, help="training wall time, measured")
    parser.add_argument("--commit", help="the commit the run trained with (default: HEAD)")
    args = parser.parse_args(argv)
    if not (args.run_dir / "config.yaml").is_file():
        print(f"error: {args.run_dir}: not a training run (no config.yaml)", file=sys.stderr)
        return 1
    try:
        path = ship(args.run_dir, args.out_dir, args.best, args.quality, args.wall_minutes,
                    args.commit)
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"shipped {args.run_dir} to {args.out_dir} ({path.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
