"""Train a policy: `python train.py --config recipe_quick [section.key=value ...]`,
the same as `jaxmripp train` (jaxmripp/cli/train.py)."""

import sys

from jaxmripp.cli.train import main

if __name__ == "__main__":
    sys.exit(main())
