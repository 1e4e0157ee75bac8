"""Exports a trained policy for the NumPy onboard runtime (`jaxmripp.runtime`).

    python -m jaxmripp.export RUN_DIR [--best] [--out DIR]

restores RUN_DIR's latest (or best) checkpoint with RUN_DIR/config.yaml and writes
DIR (default RUN_DIR/export)/policy.npz and policy.json; the format is documented in
`jaxmripp.runtime.weights`. `export(cfg, params, out_dir)` does the same for params in
memory (e.g. freshly initialised ones in tests).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from jaxmripp.learn import policy as policymod
from jaxmripp.config import Config
from jaxmripp.sim.observation import FEATURES, ROBOT_STATE
from jaxmripp.runtime import weights as fmt


def header(cfg: Config, source: dict | None = None) -> dict[str, Any]:
    """The policy.json header of `cfg` (without the weights block, which `export` adds).

    The layout comes from jaxmripp.sim.observation; `fmt.header` writes the runtime's copy, so
    a drift between the two fails here, at export time, instead of onboard.
    """
    if (tuple(FEATURES), tuple(ROBOT_STATE)) != (fmt.FEATURES, fmt.ROBOT_STATE):
        raise RuntimeError("jaxmripp.sim.observation's layout differs from jaxmripp.runtime's")
    central_critic = cfg.ppo.algo == "mappo"
    return fmt.header(cfg, policymod.runtime_config(cfg.policy, central_critic), source)


def export(cfg: Config, params, out_dir: str | Path, source: dict | None = None
           ) -> tuple[Path, Path]:
    """Writes out_dir/policy.npz and out_dir/policy.json for Flax `params`."""
    return fmt.save(out_dir, policymod.flatten_params(params), header(cfg, source))


def export_run(run_dir: str | Path, best: bool = False, out_dir: str | Path | None = None
               ) -> tuple[Path, Path]:
    """Restores a training run's checkpoint and exports it (default: RUN_DIR/export)."""
    from jaxmripp import config as cfgmod
    from jaxmripp.learn.checkpoint import Checkpoints
    from jaxmripp.learn.train import Trainer

    import jax

    run_dir = Path(run_dir)
    cfg = cfgmod.load(run_dir / "config.yaml")
    trainer = Trainer.build(cfg)
    checkpoints = Checkpoints(run_dir / "checkpoints", cfg.train.keep_checkpoints)
    try:
        # Shapes only: tracing init is enough for orbax and skips an eager env reset.
        state = checkpoints.restore(jax.eval_shape(trainer.init), best=best)
    finally:
        checkpoints.close()
    source = {"run_dir": str(run_dir), "checkpoint": "best" if best else "last",
              "update": int(state.update)}
    return export(cfg, state.params, out_dir or run_dir / "export", source)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxmripp.export", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--best", action="store_true", help="export the best checkpoint")
    parser.add_argument("--out", type=Path, default=None, help="default: RUN_DIR/export")
    args = parser.parse_args(argv)
    from jaxmripp.learn.checkpoint import CheckpointError
    from jaxmripp.config import ConfigError

    try:
        npz, header_path = export_run(args.run_dir, args.best, args.out)
    except (ConfigError, CheckpointError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {npz} and {header_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
