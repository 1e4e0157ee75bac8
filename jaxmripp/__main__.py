"""`python -m jaxmripp COMMAND ...`: the `jaxmripp` console script (jaxmripp/cli/main.py)."""

import sys

from jaxmripp.cli.main import main

sys.exit(main(name="python -m jaxmripp"))
