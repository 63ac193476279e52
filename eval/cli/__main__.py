"""``python -m eval.cli``: the `cosim` command (eval/cli/__init__.py)."""

import sys

from eval.cli import main

sys.exit(main())
