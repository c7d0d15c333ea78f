"""``python -m dinerdash bench``: the client's speed beside the machine's floors and a plain-Python
reference, measured in one run.

Layout:
    harness    the measurements and the ``bench`` command's report (:func:`run`)
    reference  the rules in plain Python: the reference the rates are measured against
"""

from __future__ import annotations

from .harness import run, tcp_floor

__all__ = ["run", "tcp_floor"]
