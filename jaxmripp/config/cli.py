"""The command line's error convention, shared by every entry point (train.py, eval.py, the
`python -m jaxmripp.*` commands, benchmarks/*.py): whatever the user or a file got wrong
is one line `error: ...` on stderr and exit status 2, with nothing changed on disk; a
traceback means a bug."""

from __future__ import annotations

import argparse
import sys

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
