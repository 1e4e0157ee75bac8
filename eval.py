"""Evaluate planners: `python eval.py --config protocol_table1 [--policy NAME=RUN_DIR
...] [--out DIR] [section.key=value ...]`, the same as `jaxmripp eval`
(jaxmripp/cli/evaluate.py)."""

import sys

from jaxmripp.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
