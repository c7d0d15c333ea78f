"""Integration testing against real servers on localhost: for the project's tests and yours.

Layout:
    cluster   LocalCluster: n ``dinerdash-server`` processes on 127.0.0.1, killed, hung, resumed,
              drained and restarted on the same port by signals
    proxy     FaultProxy: a TCP proxy that adds latency, black-holes, resets or cuts connections
    plugin    the pytest plugin (entry point ``pytest11``): the ``dinerdash_server``,
              ``dinerdash_cluster`` and ``dinerdash_cluster_factory`` fixtures and the
              ``dinerdash_cluster`` marker

::

    from dinerdash.testing import FaultProxy, LocalCluster

    with LocalCluster(3) as cluster, FaultProxy(cluster.addresses[0]) as proxy:
        envs = DinerDashVectorEnv(6, [proxy.address, *cluster.addresses[1:]], reconnect=True,
                                  failover_after=2)
        proxy.blackhole()
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .cluster import LocalCluster, server_args
    from .proxy import FaultProxy

__all__ = ["FaultProxy", "LocalCluster", "server_args"]

_HOME = {"LocalCluster": "cluster", "server_args": "cluster", "FaultProxy": "proxy"}


def __getattr__(name: str) -> Any:
    # Imported on first use: pytest imports this package (for its plugin) in every run.
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    globals()[name] = value
    return value
