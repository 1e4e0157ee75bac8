"""The command line's error convention, shared by every entry point (`jaxmripp COMMAND`,
train.py, eval.py, the `python -m jaxmripp.*` commands, benchmarks/*.py): whatever the
user or a file got wrong is one line `error: ...` on stderr and exit status 2, with nothing
changed on disk; a traceback means a bug. Also the options every command that reads a
config shares: `--config` (a preset's name or a file), `--print-config` and the dotted
overrides `section.key=value` as positional arguments."""

from __future__ import annotations

import argparse
import sys

from jaxmripp.config import presets
from jaxmripp.config.loading import to_yaml
from jaxmripp.config.sections import Config

USAGE_EXIT = 2


def error_line(message: object) -> str:
    """`message` as the one line an entry point prints (line breaks folded)."""
    return "error: " + " ".join(str(message).split())


def fail(message: object) -> int:
    """Prints `error_line(message)` to stderr; returns the exit status to end with."""
    print(error_line(message), file=sys.stderr)
    return USAGE_EXIT


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose usage errors follow the convention: one line naming the mistake and
    where the allowed flags are listed, exit status 2."""

    def error(self, message: str):
        if "allowed" not in message:
            message = f"{message}; allowed: see {self.prog} --help"
        self.exit(USAGE_EXIT, error_line(message) + "\n")


def presets_epilog() -> str:
    """The packaged presets with their summaries, for a command's `--help`."""
    return "presets (--config NAME, or a path to a YAML file):\n" + presets.listing()


def add_config_arguments(parser: argparse.ArgumentParser, default: str | None,
                         overrides_help: str = "dotted overrides, e.g. world.size=64") -> None:
    """`--config` (`default`: a preset's name), `--print-config` and the
    positional dotted overrides; `default=None` leaves `--config` out (a command whose
    base config is fixed)."""
    if default is not None:
        parser.add_argument("--config", default=default, metavar="PRESET_OR_FILE",
                            help=f"a packaged preset's name or a YAML file (default: "
                                 f"{default})")
    parser.add_argument("--print-config", action="store_true",
                        help="print the merged config as YAML and exit")
    parser.add_argument("overrides", nargs="*", metavar="section.key=value",
                        help=overrides_help)


def print_config(cfg: Config) -> int:
    """Prints `cfg` as the YAML `config.load` reads back equal; the exit status 0."""
    print(to_yaml(cfg), end="")
    return 0
