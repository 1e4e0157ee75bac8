"""Orbax checkpoints of the training state: the last k chunks and the best one.

A chunk's state goes to best/ first and to last/ after: last/ is what a run resumes from,
so a run killed between the two resumes from the chunk before, trains this one again to
the same state and offers it to best/ again, where orbax keeps the better of the two
(a step best/ already holds is that same state and stays as it is). Orbax writes each
step into a temporary folder and renames it when complete, so a run killed while saving
leaves no half-written step behind.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupt or of another shape than this config builds."""


class Checkpoints:
    """`last/` keeps the newest `keep` chunks, `best/` the one with the highest score.

    Opening them writes nothing: the folders are made by the first `save`, so a command
    that only restores (export, eval, a refused resume) leaves the run folder as it was."""

    def __init__(self, directory: str | Path, keep: int):
        directory = Path(directory).absolute()
        sync = dict(enable_async_checkpointing=False, create=False)
        # The handler named, so that `fields` can read a checkpoint's tree before restoring.
        handler = dict(item_handlers=ocp.StandardCheckpointHandler())
        with reading(directory):  # opening reads every step's metadata and metrics
            self.last = ocp.CheckpointManager(
                directory / "last",
                options=ocp.CheckpointManagerOptions(max_to_keep=keep, **sync), **handler)
            self.best = ocp.CheckpointManager(
                directory / "best", options=ocp.CheckpointManagerOptions(
                    max_to_keep=1, best_fn=lambda m: m["score"], best_mode="max", **sync),
                **handler)

    def save(self, step: int, state: Any, score: float, best_state: Any = None) -> None:
        """`state` to last/ and `best_state` (default: `state`) to best/, which is for
        evaluation and export and need not hold what only resuming reads."""
        for manager in (self.last, self.best):
            Path(manager.directory).mkdir(parents=True, exist_ok=True)
        if step not in self.best.all_steps():
            self.best.save(step, args=ocp.args.StandardSave(
                state if best_state is None else best_state), metrics={"score": float(score)})
            self.best.wait_until_finished()
        self.last.save(step, args=ocp.args.StandardSave(state))
        self.last.wait_until_finished()

    def latest_step(self) -> int | None:
        return self.last.latest_step()

    def _step(self, best: bool) -> tuple[ocp.CheckpointManager, int]:
        manager = self.best if best else self.last
        step = manager.best_step() if best else manager.latest_step()
        if step is None:
            raise CheckpointError(f"{manager.directory}: no checkpoint to restore")
        return manager, step

    def fields(self, best: bool = False) -> dict[str, bool]:
        """{name: whether it holds arrays} for the top-level fields of the state in the
        checkpoint `restore` would read (a field saved as None holds none)."""
        manager, step = self._step(best)
        return {name: value is not None
                for name, value in manager.item_metadata(step).tree.items()}

    def restore(self, template: Any, best: bool = False) -> Any:
        """The whole checkpoint, in `template`'s structure, shapes and shardings."""
        manager, step = self._step(best)
        return restore_checked(manager, step, template, ocp.args.StandardRestore(template))

    def restore_part(self, template: dict, best: bool = False) -> dict:
        """Only the top-level fields `template` names (e.g. the network parameters), read
        from a checkpoint that may hold more."""
        manager, step = self._step(best)
        args = ocp.args.PyTreeRestore(
            template, restore_args=ocp.checkpoint_utils.construct_restore_args(template),
            partial_restore=True)
        # A reader of its own: a partial restore needs orbax's PyTree handler, which a
        # manager holding the standard one refuses.
        with reading(Path(manager.directory)):
            reader = ocp.CheckpointManager(manager.directory)
        try:
            return restore_checked(reader, step, template, args)
        finally:
            reader.close()

    def close(self) -> None:
        self.last.close()
        self.best.close()


@contextlib.contextmanager
def reading(directory: Path):
    """Orbax reports a damaged checkpoint as ERROR log lines and one of many exception
    types; inside this block the log lines are held back and the exception becomes one
    CheckpointError line naming `directory`."""
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    except CheckpointError:
        raise
    except Exception as err:  # orbax raises many types; the caller needs one message
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{directory}: cannot restore this checkpoint "
                              f"({type(err).__name__}: {first[:300]})") from None
    finally:
        logger.setLevel(level)


def restore_checked(manager: ocp.CheckpointManager, step: int, template: Any,
                    args: ocp.args.CheckpointArgs) -> Any:
    """Restores into `template`'s structure, turning shape mismatches into one clear line."""
    try:
        with reading(Path(manager.directory) / str(step)):
            restored = manager.restore(step, args=args)
    except CheckpointError as err:
        raise CheckpointError(f"{err} (written with another config or damaged?)") from None
    want = jax.tree.map(lambda x: (x.shape, x.dtype), template)
    got = jax.tree.map(lambda x: (x.shape, x.dtype), restored)
    if want != got:
        raise CheckpointError(f"{manager.directory}/{step}: checkpoint shapes differ from "
                              "this config (was it written with another policy width?)")
    return restored
