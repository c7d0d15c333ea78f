"""``python -m dinerdash_bench``: the same command as ``python -m dinerdash bench``."""

import sys

from .cli import main

sys.exit(main(prog="python -m dinerdash_bench"))
