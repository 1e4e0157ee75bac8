"""Points in a training run where tests stop it as a crash would: `install(point, crash)`
patches the run's code so that `crash()` is called there, at update 2 of the smoke run
(the second of its three one-update chunks). The in-process tests crash by raising, the
slow ones (and `python -c` children) by SIGKILL.

- cut_line: half of update 2's line written to metrics.jsonl
- before_checkpoint: update 2's metrics written, no checkpoint of it yet
- between_best_and_last: update 2 saved to checkpoints/best, not to checkpoints/last
- mid_checkpoint: update 2 written to last/'s temporary folder, not yet renamed
- after_checkpoint: update 2 saved to both
"""

from __future__ import annotations

import json
import os
import signal

import orbax.checkpoint as ocp
from orbax.checkpoint._src.path import atomicity

from jaxmripp.learn import metrics as metricsmod
from jaxmripp.learn.checkpoint import Checkpoints

POINTS = ("cut_line", "before_checkpoint", "between_best_and_last", "mid_checkpoint",
          "after_checkpoint")
AT_UPDATE = 2


class Crash(Exception):
    """What the in-process tests raise where a process would die."""


def raise_crash() -> None:
    raise Crash


def kill() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def install(point: str, crash, monkeypatch=None) -> None:
    """Patches one crash point (through pytest's `monkeypatch` when given, so it is
    undone after the test; else for the rest of the process)."""
    patch = monkeypatch.setattr if monkeypatch is not None else setattr

    if point == "cut_line":
        write = metricsmod.MetricsLog.write

        def cut(self, chunk):
            if chunk[0]["update"] == AT_UPDATE:
                line = json.dumps(chunk[0]) + "\n"
                with open(self.jsonl, "a") as fh:
                    fh.write(line[: len(line) // 2])
                crash()
            write(self, chunk)

        patch(metricsmod.MetricsLog, "write", cut)
    elif point in ("before_checkpoint", "after_checkpoint"):
        save = Checkpoints.save

        def around(self, step, *args, **kwargs):
            if step == AT_UPDATE and point == "before_checkpoint":
                crash()
            save(self, step, *args, **kwargs)
            if step == AT_UPDATE and point == "after_checkpoint":
                crash()

        patch(Checkpoints, "save", around)
    elif point == "between_best_and_last":
        save = ocp.CheckpointManager.save

        def before_last(self, step, *args, **kwargs):
            if step == AT_UPDATE and os.path.basename(str(self.directory)) == "last":
                crash()
            return save(self, step, *args, **kwargs)

        patch(ocp.CheckpointManager, "save", before_last)
    elif point == "mid_checkpoint":
        finalize = atomicity.AtomicRenameTemporaryPath.finalize

        async def before_rename(self, *args, **kwargs):
            final = str(self._final_path)
            if final.endswith(os.path.join("last", str(AT_UPDATE))):
                crash()
            return await finalize(self, *args, **kwargs)

        patch(atomicity.AtomicRenameTemporaryPath, "finalize", before_rename)
    else:
        raise ValueError(f"unknown crash point {point!r}; known: {', '.join(POINTS)}")
