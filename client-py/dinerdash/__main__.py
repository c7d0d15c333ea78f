"""``python -m dinerdash``: see :mod:`dinerdash.cli`."""

from .cli import main

raise SystemExit(main())
