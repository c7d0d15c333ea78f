"""Integration testing against real servers on localhost, for the project's tests and yours
(docs/client.md#testing-your-own-training-code).

Layout:
    cluster   LocalCluster: n ``dinerdash-server`` processes on 127.0.0.1, signals to lose them,
              and wait_stopped: until a SIGSTOP has stopped every thread of a process
    proxy     FaultProxy: a TCP proxy that adds latency, black-holes, resets or cuts connections
    plugin    the pytest plugin (entry point ``pytest11``): its fixtures and marker
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .cluster import LocalCluster, server_args, wait_stopped
    from .proxy import FaultProxy

__all__ = ["FaultProxy", "LocalCluster", "server_args", "wait_stopped"]

_HOME = {
    "LocalCluster": "cluster",
    "server_args": "cluster",
    "wait_stopped": "cluster",
    "FaultProxy": "proxy",
}


def __getattr__(name: str) -> Any:
    # Imported on first use: pytest imports this package (for its plugin) in every run.
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    globals()[name] = value
    return value
