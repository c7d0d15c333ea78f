"""The pytest plugin of ``dinerdash.testing`` (entry point ``pytest11``; ``-p no:dinerdash`` turns
it off): the fixtures ``dinerdash_server``, ``dinerdash_cluster`` (sized and flagged by the marker
``@pytest.mark.dinerdash_cluster(n=3, **server_flags)``) and ``dinerdash_cluster_factory``, each
stopping the servers it started after the test (docs/client.md#testing-your-own-training-code).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from .cluster import LocalCluster

MARKER = "dinerdash_cluster"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        f"{MARKER}(n=3, **server_flags): the size of the dinerdash_cluster fixture's "
        "LocalCluster and its servers' flags as keywords (max_sessions=8 is --max-sessions 8)",
    )


@pytest.fixture
def dinerdash_cluster_factory() -> Iterator[Callable[..., LocalCluster]]:
    """``factory(n=3, **server_flags)``: a started :class:`~dinerdash.testing.LocalCluster`; every
    one it made is stopped after the test."""
    from .cluster import LocalCluster

    clusters: list[LocalCluster] = []

    def factory(n: int = 3, **server_flags: Any) -> LocalCluster:
        cluster = LocalCluster(n, **server_flags)
        clusters.append(cluster)
        return cluster

    try:
        yield factory
    finally:
        errors = []
        for cluster in reversed(clusters):
            try:
                cluster.close()
            except Exception as e:  # stop the others anyway, then report
                errors.append(e)
        if errors:
            raise errors[0]


@pytest.fixture
def dinerdash_cluster(
    request: pytest.FixtureRequest, dinerdash_cluster_factory: Callable[..., LocalCluster]
) -> LocalCluster:
    """A :class:`~dinerdash.testing.LocalCluster` of ``n`` servers (default 3), sized and flagged
    by the nearest ``@pytest.mark.dinerdash_cluster(n, **server_flags)``."""
    marker = request.node.get_closest_marker(MARKER)
    args, kwargs = (marker.args, marker.kwargs) if marker is not None else ((), {})
    return dinerdash_cluster_factory(*args, **kwargs)


@pytest.fixture
def dinerdash_server(dinerdash_cluster_factory: Callable[..., LocalCluster]) -> str:
    """The address (``"127.0.0.1:PORT"``) of one ``dinerdash-server`` started for this test."""
    return dinerdash_cluster_factory(1).addresses[0]
