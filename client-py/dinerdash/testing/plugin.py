"""The pytest plugin of ``dinerdash.testing`` (entry point ``pytest11``: loaded by every pytest run
where ``dinerdash`` is installed; ``-p no:dinerdash`` turns it off).

Fixtures, each starting real ``dinerdash-server`` processes on 127.0.0.1 for one test and stopping
them after it (the binary: ``DINERDASH_SERVER``, the ``dinerdash-server`` wheel, ``PATH``, ...):

``dinerdash_server``
    the address (``"127.0.0.1:PORT"``) of one server.
``dinerdash_cluster``
    a :class:`~dinerdash.testing.LocalCluster`; its size and server flags come from the marker
    ``@pytest.mark.dinerdash_cluster(n=3, **server_flags)`` (default: 3 servers, no flags).
``dinerdash_cluster_factory``
    ``factory(n=3, **server_flags)`` starts another cluster; all are stopped after the test.

::

    @pytest.mark.dinerdash_cluster(2, max_sessions=8)
    def test_training_survives_a_crash(dinerdash_cluster):
        envs = DinerDashVectorEnv(4, dinerdash_cluster.addresses, reconnect=True,
                                  failover_after=1)
        envs.reset(seed=0)
        dinerdash_cluster.kill(1)
        envs.step(np.zeros(4, dtype=np.int64))
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
