"""`jaxmripp bench NAME [ARGS ...]`: runs benchmarks/NAME.py of the source checkout the
package is installed from (`pip install -e .`), with ARGS as its command line, in this
process. The benchmarks are scripts beside the package, not part of it: an installed copy
without the checkout has none."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

from jaxmripp.config import presets
from jaxmripp.config.cli import fail

# The scripts of benchmarks/ (its helper modules, common, figures and scale_report, are
# imported by them, not run).
BENCHMARKS = ("ablation", "blocks", "distributed", "env", "env_ab", "flight", "generalize",
              "gp", "quality", "runtime", "safety", "scale", "sensing", "train")


def scripts_folder() -> Path:
    return presets.CHECKOUT / "benchmarks"


def main(argv: list[str] | None = None, prog: str = "jaxmripp bench") -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    allowed = ", ".join(BENCHMARKS)
    if argv[:1] in (["-h"], ["--help"]):
        print(f"usage: {prog} NAME [ARGS ...]\n\n{__doc__}\nnames: {allowed}\n\n"
              f"{prog} NAME --help lists a benchmark's options.")
        return 0
    if not argv or argv[0] not in BENCHMARKS:
        got = f"got {argv[0]!r}" if argv else "a benchmark name is needed"
        return fail(f"{prog}: {got}; allowed: {allowed}")
    script = scripts_folder() / f"{argv[0]}.py"
    if not script.is_file():
        return fail(f"{prog} {argv[0]}: no {script} (the benchmarks run from a source "
                    f"checkout installed with pip install -e); allowed: {allowed}")
    saved = sys.argv
    sys.argv = [str(script), *argv[1:]]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exit_:  # the scripts end with sys.exit(main())
        if exit_.code is None or isinstance(exit_.code, int):
            return exit_.code or 0
        raise
    finally:
        sys.argv = saved
    return 0
