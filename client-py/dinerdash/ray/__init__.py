"""Ray and RLlib (the ``dinerdash[ray]`` extra; docs/clusters.md#ray): :func:`start_servers`
(``_servers``) runs each ``dinerdash-server`` under a Ray actor pinned to its node; :func:`register`
and :func:`masked_ppo` (``rllib``) give each EnvRunner one batched session and an RLlib PPO that
never samples an illegal action. The RLlib half is imported on first use, so that the servers'
actors start without RLlib and torch.
"""

from __future__ import annotations

from typing import Any

from ._servers import MAX_RESTARTS, SERVER_RESOURCE, ServerPool, ServerPoolError, start_servers

#: The names of :mod:`dinerdash.ray.rllib` this package exports.
_RLLIB = (
    "ENV_CONFIG_KEYS",
    "ENV_NAME",
    "MaskedObservation",
    "MaskedPPOTorchRLModule",
    "VectorMaskedObservation",
    "make_env",
    "masked_ppo",
    "register",
)

__all__ = [
    "MAX_RESTARTS",
    "SERVER_RESOURCE",
    "ServerPool",
    "ServerPoolError",
    "start_servers",
    *_RLLIB,
]


def __getattr__(name: str) -> Any:
    if name in _RLLIB:
        from . import rllib

        return getattr(rllib, name)
    raise AttributeError(f"module 'dinerdash.ray' has no attribute {name!r}")
