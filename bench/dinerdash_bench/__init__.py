"""``python -m dinerdash bench``: the client's speed beside the machine's floors and a plain-Python
reference, measured in one run. A package of its own (``dinerdash-bench``), not the client's: a
trainer never imports it.

Layout:
    cli        the ``bench`` command's arguments (``python -m dinerdash bench`` forwards here)
    harness    the measurements and the command's report (:func:`run`)
    reference  the rules in plain Python: the reference the rates are measured against
"""

from __future__ import annotations

from .harness import run, tcp_floor

__all__ = ["run", "tcp_floor"]
