"""Issue 26, the network's faults: a vector env over three real servers, one of them behind a
fault-injecting TCP proxy (:class:`dinerdash.testing.FaultProxy`), gives up the server whose
network black-holes its packets within ``failover_after`` + 2 s (+ what load measurably took:
:mod:`tests.test_membership`'s time bounds), with the other environments'
trajectories those of an undisturbed run, and keeps a server that is merely slow.

Over gRPC only: on the servers' host a session's Steps would go through shared memory, past the
proxy (the tests of :mod:`tests.test_membership` run over both transports)."""

from __future__ import annotations

import numpy as np
import pytest
from dinerdash import DinerDashVectorEnv
from dinerdash.testing import FaultProxy

from .test_failover import assert_same_envs
from .test_membership import CONFIG, FAILOVER_AFTER, SLACK, N, actions_for, make, run_loss
from .trajectories import plain_step

#: dinerdash_cluster: three servers (dinerdash.testing's pytest plugin).
pytestmark = pytest.mark.dinerdash_cluster(3)


def test_a_black_holed_server_is_given_up(dinerdash_cluster) -> None:
    s0, s1, s2 = dinerdash_cluster.addresses
    proxy = FaultProxy(s1)
    reference = DinerDashVectorEnv(N, s0, expert=True, config=CONFIG)
    envs = make([s0, proxy.address, s2], timeout=60, transport="grpc")  # through the proxy
    try:
        took, load = run_loss(envs, reference, proxy.blackhole, plain_step, dinerdash_cluster)
        print(f"\n[black-holed server] given up in {took:.3f} s (waited for a CPU: {load:.3f} s)")
        assert FAILOVER_AFTER <= took < FAILOVER_AFTER + SLACK + load
        assert envs.lost_addresses == [proxy.address]
    finally:
        envs.close()
        reference.close()
        proxy.close()


def test_a_slow_server_is_kept(dinerdash_cluster) -> None:
    """Every chunk to and from the middle server waits 0.6 s: a Step takes about 1.2 s, past
    the point where health checks go out (1 s), and well under ``failover_after`` (4 s, so that a
    loaded machine cannot make it look silent): it is kept."""
    s0, s1, s2 = dinerdash_cluster.addresses
    proxy = FaultProxy(s1)
    proxy.latency(0.6)
    envs = make([s0, proxy.address, s2], failover_after=4.0, transport="grpc")
    reference = DinerDashVectorEnv(N, s0, expert=True, config=CONFIG)
    try:
        rng = np.random.default_rng(1)
        a, b = envs.reset(seed=3), reference.reset(seed=3)
        for t in range(5):
            actions = actions_for(b[-1], rng)
            a, b = envs.step(actions), reference.step(actions)
            assert_same_envs(a, b, range(N), f"step {t}")
            assert "reconnected" not in a[-1]
        assert envs.lost_addresses == [] and envs.failovers == 0
    finally:
        envs.close()
        reference.close()
        proxy.close()
