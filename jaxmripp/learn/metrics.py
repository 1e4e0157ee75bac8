"""Every update's metrics, and where `train.log` sends them.

A chunk returns its updates' metrics stacked on a leading update axis; `records` makes one
record per update, and `MetricsLog` writes them to metrics.jsonl (one JSON line per
update), TensorBoard event files (tensorboard/) and Weights & Biases, as `train.log`
lists them. A record holds the update count, agent steps so far, the episodes that ended
in the update with their mean discovered fraction and return (those two only when an
episode ended), the PPO losses, the mean reward parts per active sample, and the seconds
and agent-steps per second of the chunk the update ran in (its seconds shared evenly).

A chunk's records are written before its checkpoint is saved. After a crash metrics.jsonl
may hold records past the last checkpoint, and its last line may be cut mid-write:
`read_metrics` leaves a cut last line out and says so, and a resumed run keeps only the
records up to its checkpoint (`keep_until`) before training those updates again;
TensorBoard hides the repeated updates' first events (the writer's purge step).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from jaxmripp import config as cfgmod
from jaxmripp.config import Config

METRICS_FILE = "metrics.jsonl"
TENSORBOARD_DIR = "tensorboard"
WANDB_PROJECT = "jaxmripp"
LOSSES = ("policy_loss", "value_loss", "entropy", "approx_kl", "imitation")
# Only with ppo.search_coef > 0 (jaxmripp.learn.search); the second with search_value=learned.
SEARCH_LOSSES = ("search", "action_value_loss")
REWARD_PARTS = ("r_exploration", "r_discovery", "r_communication")


class MetricsError(ValueError):
    """metrics.jsonl holds a line that is not a record (other than a cut last line)."""


def records(metrics: dict, done: int, samples_per_update: int, seconds: float) -> list[dict]:
    """One record per update of a chunk that started after `done` updates, from its
    stacked metrics (host or device arrays, leading axis U) and its wall seconds."""
    m = {k: np.asarray(v) for k, v in metrics.items()}
    count = len(m["episodes"])
    out = []
    for i in range(count):
        update = done + i + 1
        episodes = int(m["episodes"][i])
        record: dict[str, Any] = {"update": update, "env_steps": update * samples_per_update,
                                  "episodes": episodes}
        if episodes:
            record["discovered"] = float(m["discovered_sum"][i] / episodes)
            record["return"] = float(m["return_sum"][i] / episodes)
        record.update({name: float(m[name][i]) for name in (*LOSSES, *SEARCH_LOSSES) if name in m})
        record.update({name: float(m["reward_parts"][i][j]) for j, name in enumerate(REWARD_PARTS)})
        record.update(seconds=round(seconds / count, 4),
                      agent_steps_per_s=round(count * samples_per_update / seconds, 1))
        out.append(record)
    return out


def episode_mean(chunk: list[dict], key: str) -> float:
    """`key` (discovered or return) over every episode that ended in these records (0 if
    none did); a record without an episode count counts as one."""
    weighted = [(r[key], r.get("episodes", 1)) for r in chunk if key in r]
    episodes = sum(w for _, w in weighted)
    return sum(v * w for v, w in weighted) / episodes if episodes else 0.0


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def read_metrics(run_dir: str | Path, log: Callable[[str], None] = _stderr) -> list[dict]:
    """The records of a run's metrics.jsonl (none if it has none); a last line cut
    mid-write is left out, with a note to `log`; any other bad line raises MetricsError."""
    path = Path(run_dir) / METRICS_FILE
    if not path.exists():
        return []
    lines = path.read_text().split("\n")  # a complete file ends with "\n": lines[-1] == ""
    out = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            if number == len(lines):
                log(f"note: {path}: the last line is cut short (the run stopped while "
                    "writing it); left out")
                continue
            raise MetricsError(f"{path}: line {number} is not a JSON record: "
                               f"{line[:60]!r}") from None
    return out


def keep_until(run_dir: Path, update: int, log: Callable[[str], None]) -> None:
    """Rewrites metrics.jsonl (atomically) with only the records of updates <= `update`,
    the checkpoint a run resumes from; says what it dropped."""
    path = run_dir / METRICS_FILE
    if not path.exists():
        return
    every = read_metrics(run_dir, log)
    kept = [r for r in every if r["update"] <= update]
    text = "".join(json.dumps(r) + "\n" for r in kept)
    if text == path.read_text():
        return
    if len(kept) < len(every):
        log(f"note: {path}: {len(every) - len(kept)} record(s) past the checkpoint at update "
            f"{update} dropped; those updates are trained again")
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    os.replace(partial, path)


def check_sinks(sinks: tuple[str, ...]) -> None:
    """Raises ConfigError for a sink of `train.log` this installation cannot write."""
    if "wandb" in sinks and importlib.util.find_spec("wandb") is None:
        raise cfgmod.ConfigError(
            f"train.log: got {list(sinks)}, but wandb is not installed; allowed: jsonl and "
            "tensorboard, or wandb after `pip install wandb`")


class MetricsLog:
    """Writes records to the sinks of `cfg.train.log` (process 0 only); a run resumed
    after `done` updates appends, a new one (`fresh`) starts the files over."""

    def __init__(self, cfg: Config, run_dir: Path, done: int, fresh: bool):
        sinks = cfg.train.log
        check_sinks(sinks)
        self.jsonl = run_dir / METRICS_FILE if "jsonl" in sinks else None
        if self.jsonl is not None and fresh:
            self.jsonl.write_text("")
        self.tensorboard = None
        if "tensorboard" in sinks:
            events = run_dir / TENSORBOARD_DIR
            if fresh and events.is_dir():
                for old in events.glob("events.out.tfevents.*"):
                    old.unlink()
            self.tensorboard = EventFile(events, done + 1)
        self.wandb = _wandb_run(cfg, run_dir) if "wandb" in sinks else None

    def write(self, chunk: list[dict]) -> None:
        """Every record of a chunk, flushed so that a crash loses none of them."""
        if self.jsonl is not None:
            with open(self.jsonl, "a") as fh:
                fh.write("".join(json.dumps(r) + "\n" for r in chunk))
        for record in chunk:
            scalars = {k: v for k, v in record.items() if k != "update"}
            if self.tensorboard is not None:
                self.tensorboard.scalars(record["update"], scalars)
            if self.wandb is not None:
                self.wandb.log(scalars, step=record["update"])
        if self.tensorboard is not None:
            self.tensorboard.flush()

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()
        if self.wandb is not None:
            self.wandb.finish()


class EventFile:
    """A TensorBoard event file written as records come, with tensorboardX's record writer
    and protobuf classes. (Its SummaryWriter hands events to a thread through a queue,
    and `flush` does not wait for the queue: a killed process loses the last events.)"""

    def __init__(self, directory: Path, purge_step: int):
        from tensorboardX.event_file_writer import EventsWriter  # noqa: PLC0415
        from tensorboardX.proto.event_pb2 import Event, SessionLog  # noqa: PLC0415

        directory.mkdir(parents=True, exist_ok=True)
        # The suffix keeps files apart, and in order, when two writers start within one
        # second (the name has the time in seconds), as a run resumed at once may.
        self.writer = EventsWriter(str(directory / "events"), f".{time.time_ns():019d}")
        # Updates from `purge_step` on may have been logged before a crash: TensorBoard
        # hides earlier files' events at those steps after a session start there.
        self.writer.write_event(Event(wall_time=time.time(), step=purge_step,
                                      session_log=SessionLog(status=SessionLog.START)))
        self.writer.flush()

    def scalars(self, step: int, values: dict[str, float]) -> None:
        from tensorboardX.proto.event_pb2 import Event  # noqa: PLC0415
        from tensorboardX.summary import scalar  # noqa: PLC0415

        for tag, value in values.items():
            self.writer.write_event(Event(wall_time=time.time(), step=step,
                                          summary=scalar(tag, value)))

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def _wandb_run(cfg: Config, run_dir: Path):
    """A W&B run for the run folder (the same id whenever it resumes), offline unless
    the environment's WANDB_MODE says otherwise."""
    import wandb  # noqa: PLC0415 (an optional dependency, checked by check_sinks)

    run_id = hashlib.sha1(str(run_dir.resolve()).encode()).hexdigest()[:16]
    return wandb.init(project=WANDB_PROJECT, name=run_dir.name, id=run_id, resume="allow",
                      dir=str(run_dir), config=cfgmod.to_dict(cfg),
                      mode=os.environ.get("WANDB_MODE", "offline"))
