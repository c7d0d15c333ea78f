"""The exceptions of the agents package: each names the file or field that is wrong.

::

    AgentsError             any refusal of this package (the CLI prints it and exits 1)
    ├── DemosError          a demonstrations file that is missing, corrupt, or too short
    └── CheckpointError     a checkpoint directory that is missing, corrupt, of another
                            algorithm or of another format version
"""

from __future__ import annotations

__all__ = ["AgentsError", "CheckpointError", "DemosError"]


class AgentsError(Exception):
    """A refusal of the agents package, with a message naming the file or field."""


class DemosError(AgentsError, ValueError):
    """A demonstrations file (``python -m dinerdash collect``'s ``.npz``) cannot be used."""


class CheckpointError(AgentsError, ValueError):
    """A checkpoint directory cannot be loaded."""
