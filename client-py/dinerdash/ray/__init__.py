"""Ray and RLlib: servers placed by Ray, one batched session per EnvRunner, masked PPO (needs the
``dinerdash[ray]`` extra)::

    import ray
    from dinerdash.ray import masked_ppo, start_servers

    ray.init()                                   # or ray.init(address="auto") on a cluster
    with start_servers() as pool:                # one dinerdash-server per Ray node
        algo = masked_ppo(pool.addresses).build_algo()
        for _ in range(100):
            algo.train()

- :func:`start_servers` (``_servers``) runs each ``dinerdash-server`` under a Ray actor pinned to
  its node, on the node's IP and a free port. A server that dies (its process or its actor) is
  restarted by Ray on the same port, so clients with ``reconnect=True`` find it again.
  :class:`ServerPool`: ``pool.addresses``, ``pool.close()``, a context manager.
- :func:`register` (``rllib``) registers the RLlib environment ``"DinerDash-v0"``: one batched
  :class:`~dinerdash.DinerDashVectorEnv` per EnvRunner (``env_config``: ``address``, ``token``,
  ``timeout``, ``reconnect``, ``expert``, ``mask_observation``).
- :func:`masked_ppo` (``rllib``): an RLlib PPO config (new API stack) on that environment with
  :class:`MaskedPPOTorchRLModule`, which never samples an illegal action.

The binary: each actor looks for ``dinerdash-server`` on its own node as the embedded default
does (:func:`dinerdash.server.find_server_binary`: ``DINERDASH_SERVER``, the ``dinerdash-server``
wheel, ``PATH``). On a real cluster either install ``dinerdash[ray,server]`` on every node, or
point every node at a binary: ``ray.init(runtime_env={"env_vars": {"DINERDASH_SERVER": path}})``
with ``path`` valid on every node.

The RLlib half is imported on first use: the servers' actors import only ``_servers``, without
RLlib and torch (whose import takes seconds in every actor process).
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
