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
from jaxmripp.config.cli import ArgumentParser, fail
from jaxmripp.runtime import weights as fmt
from jaxmripp.sim import privileged
from jaxmripp.spec.layout import N_GLOBAL_EXTRA, ROBOT_STATE


class ExportError(ValueError):
    """The policy does not fit the layout the runtime will feed it; nothing was written."""


def header(cfg: Config, source: dict | None = None) -> dict[str, Any]:
    """The policy.json header of `cfg` (without the weights block, which `export` adds)."""
    central_critic = cfg.ppo.algo == "mappo"
    policy = policymod.runtime_config(cfg.policy, central_critic)
    if cfg.ppo.privileged_critic:  # the critic's training-only inputs (sim.privileged)
        policy["critic_extra_inputs"] = privileged.size(cfg.robots.count)
    return fmt.header(cfg, policy, source)


def runtime_spec(cfg: Config) -> fmt.RuntimeSpec:
    """What the onboard runtime reads from `cfg`'s export: the header as policy.json stores
    it (plain JSON data), without writing a file."""
    return fmt.RuntimeSpec.from_header(fmt.jsonable(header(cfg)))


def check_layout(head: dict[str, Any], weights: dict[str, Any]) -> None:
    """Refuses an export the runtime would feed wrongly: the header's layout must be the
    spec's (`jaxmripp.spec.layout`, which the runtime builds), and the weights' input
    widths must be the layout's (embed: one row per feature, state_embed: per robot-state
    column, global_embed: N robot states plus the team values). Checked here, at export
    time, so that a drift fails on the workstation rather than onboard."""
    layout = head.get("layout") or {}
    wanted = fmt.RuntimeSpec.from_header(head).features
    for key, spec in (("features", wanted), ("robot_state", ROBOT_STATE)):
        if list(layout.get(key) or ()) != list(spec):
            raise ExportError(f"header layout.{key} {layout.get(key)!r} differs from "
                              f"jaxmripp.spec.layout's {list(spec)!r}")
    n_features, n_state = len(layout["features"]), len(layout["robot_state"])
    inputs = {"embed": n_features, "state_embed": n_state}
    if head.get("policy", {}).get("central_critic"):
        inputs["global_embed"] = (head["config"]["robots"]["count"] * n_state + N_GLOBAL_EXTRA
                                  + head["policy"].get("critic_extra_inputs", 0))
    for name, width in inputs.items():
        kernel = weights.get(f"{name}/kernel")
        if kernel is None:
            raise ExportError(f"the policy has no layer {name}; the header's layout needs "
                              f"one reading {width} inputs")
        if kernel.shape[0] != width:
            raise ExportError(f"policy layer {name} reads {kernel.shape[0]} inputs; the "
                              f"header's layout gives {width}")


def export(cfg: Config, params, out_dir: str | Path, source: dict | None = None
           ) -> tuple[Path, Path]:
    """Writes out_dir/policy.npz and out_dir/policy.json for Flax `params` (after
    `check_layout`; raises ExportError and writes nothing on a mismatch)."""
    weights = policymod.flatten_params(params)
    head = header(cfg, source)
    check_layout(head, weights)
    return fmt.save(out_dir, weights, head)


def restore_run(run_dir: str | Path, best: bool = False):
    """A training run's config, its last (or best) checkpoint's parameters and the
    provenance an export records; raises FolderError, ConfigError or CheckpointError
    before anything is written."""
    from jaxmripp import folders
    from jaxmripp.learn.train import restore

    run_dir = Path(run_dir)
    cfg = folders.training_run(run_dir, best)
    state = restore(cfg, run_dir, best)
    source = {"run_dir": str(run_dir), "checkpoint": "best" if best else "last",
              "update": int(state.update)}
    return cfg, state.params, source


def export_run(run_dir: str | Path, best: bool = False, out_dir: str | Path | None = None
               ) -> tuple[Path, Path]:
    """Restores a training run's checkpoint and exports it (default: RUN_DIR/export)."""
    cfg, params, source = restore_run(run_dir, best)
    return export(cfg, params, out_dir or Path(run_dir) / "export", source)


def main(argv: list[str] | None = None, prog: str = "python -m jaxmripp.export") -> int:
    parser = ArgumentParser(prog=prog, description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--best", action="store_true", help="export the best checkpoint")
    parser.add_argument("--out", type=Path, default=None, help="default: RUN_DIR/export")
    args = parser.parse_args(argv)
    from jaxmripp import folders
    from jaxmripp.config import ConfigError

    try:  # before importing the trainer: a folder of another kind fails at once
        folders.training_run(args.run_dir, args.best)
    except (folders.FolderError, ConfigError) as err:
        return fail(err)
    from jaxmripp.learn.checkpoint import CheckpointError

    try:
        npz, header_path = export_run(args.run_dir, args.best, args.out)
    except (ConfigError, folders.FolderError, CheckpointError, ExportError) as err:
        return fail(err)
    except OSError as err:  # --out not writable
        return fail(f"{err.filename or args.out}: cannot write ({err.strerror or err})")
    print(f"wrote {npz} and {header_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
