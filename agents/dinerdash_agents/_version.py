"""The installed package's version (``0.0.0`` from a source tree that is not installed)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dinerdash-agents")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0"
