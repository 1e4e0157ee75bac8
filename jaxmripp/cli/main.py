"""`jaxmripp COMMAND [ARGS ...]`: every command of the package behind one name (the console
script of pyproject.toml; `python -m jaxmripp` is the same). `jaxmripp COMMAND --help`
gives each command's options."""

from __future__ import annotations

import importlib
import sys

from jaxmripp.config.cli import fail

# command: (module whose main(argv, prog) runs it, what it does)
COMMANDS = {
    "train": ("jaxmripp.cli.train", "train a policy from a preset or YAML file, with dotted "
                                    "overrides"),
    "eval": ("jaxmripp.cli.evaluate", "evaluate trained or shipped policies against the "
                                      "baselines"),
    "export": ("jaxmripp.export", "export a training run for the NumPy runtime"),
    "ship": ("jaxmripp.ship", "ship a run as a pretrained folder with its figures"),
    "demo": ("jaxmripp.demo", "fly a team with the NumPy runtime in a voxel city"),
    "fly": ("jaxmripp.flight.__main__", "fly simulated quadrotors with the runtime "
                                        "(pybullet)"),
    "bench": ("jaxmripp.cli.bench", "run benchmarks/NAME.py of the source checkout"),
}


def usage(name: str) -> str:
    """The top-level help: the commands, one a line."""
    width = max(map(len, COMMANDS))
    lines = [f"usage: {name} COMMAND [ARGS ...]", "", "Trains, evaluates and deploys "
             "decentralised planners for multi-robot informative path planning.", "",
             "commands:"]
    lines += [f"  {command:<{width}}  {summary}" for command, (_, summary) in COMMANDS.items()]
    lines += ["", f"{name} COMMAND --help lists a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None, name: str = "jaxmripp") -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    allowed = ", ".join(COMMANDS)
    if argv[:1] in (["-h"], ["--help"]):
        print(usage(name))
        return 0
    if not argv:
        return fail(f"{name}: a command is needed; allowed: {allowed} (see {name} --help)")
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        return fail(f"{name} {command}: no such command; allowed: {allowed} "
                    f"(see {name} --help)")
    module = importlib.import_module(COMMANDS[command][0])
    status = module.main(rest, prog=f"{name} {command}")
    return status if isinstance(status, int) else 0  # demo returns its run


if __name__ == "__main__":
    sys.exit(main())
