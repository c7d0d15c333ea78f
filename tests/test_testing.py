"""Issue 26, part 5: ``dinerdash.testing``. Each ``LocalCluster`` method against real servers, each
``FaultProxy`` fault seen by a gRPC client through the proxy, and the pytest plugin's fixtures in a
user's test file run by pytester."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import grpc
import gymnasium
import numpy as np
import pytest
from dinerdash import (
    Connection,
    DinerDashVectorEnv,
    ResourceExhausted,
    ServiceTimeout,
    ServiceTransportError,
)
from dinerdash._proto import pb
from dinerdash.testing import FaultProxy, LocalCluster, server_args

pytest_plugins = ["pytester"]

#: The generous part of every time bound: what a loaded machine may add to the waits.
SLACK = 10.0


def answers(address: str, timeout: float = 5.0) -> bool:
    """Whether a server at ``address`` answers a ServerInfo within ``timeout`` seconds."""
    try:
        with Connection(address, connect_timeout=timeout, timeout=timeout) as conn:
            conn.server_info()
        return True
    except (ServiceTransportError, ServiceTimeout):
        return False


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def server_info(conn: Connection, timeout: float, retries: int = 0) -> pb.ServerInfoResponse:
    return conn.call("ServerInfo", pb.ServerInfoRequest(), timeout=timeout, retries=retries)


# LocalCluster


def test_server_args_from_keywords() -> None:
    assert server_args(
        {"max_sessions": 8, "session_ttl": "5m", "flag": True, "off": False, "none": None}
    ) == ["--max-sessions", "8", "--session-ttl", "5m", "--flag"]
    assert server_args({"auth_tokens_file": ["a", "b"]}) == [
        "--auth-tokens-file",
        "a",
        "--auth-tokens-file",
        "b",
    ]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"n": -1}, "n: expected"), ({"port": 50051}, "port"), ({"host": "0.0.0.0"}, "host")],
)
def test_a_cluster_refuses_bad_arguments(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        LocalCluster(**kwargs)


def test_a_cluster_serves_on_its_addresses_and_stops_them_all() -> None:
    with LocalCluster(3) as cluster:
        addresses = cluster.addresses
        pids = [cluster.pid(i) for i in range(3)]
        assert len(cluster) == 3 and len(cluster.servers) == 3
        assert len(set(addresses)) == 3 and len(set(pids)) == 3
        for i, address in enumerate(addresses):
            host, port = address.rsplit(":", 1)
            assert host == "127.0.0.1" and int(port) > 0
            assert cluster.address(i) == address
            assert cluster.is_running(i) and not cluster.is_hung(i)
            assert answers(address)
        cluster.hang(2)  # a hung server is stopped too: resumed, then terminated
        assert cluster.is_hung(2)
    assert all(gone(pid) for pid in pids)
    assert not any(cluster.is_running(i) for i in range(3))
    cluster.close()  # twice is fine


def test_server_flags_reach_every_server() -> None:
    with LocalCluster(2, max_sessions=1) as cluster:
        i = cluster.add()
        for address in cluster.addresses[0], cluster.addresses[i]:
            envs = DinerDashVectorEnv(1, address)
            try:
                with pytest.raises(ResourceExhausted):
                    DinerDashVectorEnv(1, address)
            finally:
                envs.close()


def test_kill_is_a_crash() -> None:
    with LocalCluster(2) as cluster:
        envs = DinerDashVectorEnv(2, cluster.addresses[1])
        envs.reset(seed=0)
        cluster.kill(1)
        assert not cluster.is_running(1)
        assert cluster.wait(1, timeout=1) == -signal.SIGKILL
        with pytest.raises(ServiceTransportError):
            envs.step(np.zeros(2, dtype=np.int64))
        envs.close()
        assert not answers(cluster.addresses[1], timeout=1)
        assert answers(cluster.addresses[0])


def test_hang_stops_answering_and_resume_goes_on() -> None:
    with LocalCluster(1) as cluster, Connection(cluster.addresses[0]) as conn:
        server_info(conn, 5)
        cluster.hang(0)
        assert cluster.is_hung(0) and cluster.is_running(0)
        began = time.monotonic()
        with pytest.raises(ServiceTimeout):
            server_info(conn, 1)
        assert 1 <= time.monotonic() - began < 1 + SLACK
        cluster.resume(0)
        assert not cluster.is_hung(0)
        assert server_info(conn, 5).server_version


def test_drain_returns_at_once_and_the_server_exits() -> None:
    with LocalCluster(1) as cluster:
        pid = cluster.pid(0)
        began = time.monotonic()
        cluster.drain(0)
        assert time.monotonic() - began < 1.0  # the signal only: no waiting
        # SIGTERM is a graceful stop: status 0 (after the drain, if the server drains).
        assert cluster.wait(0, timeout=60) == 0
        assert not cluster.is_running(0) and gone(pid)
        cluster.restart(0)
        cluster.hang(0)
        with pytest.raises(TimeoutError, match=r"still running after 0\.2 s"):
            cluster.wait(0, timeout=0.2)
        cluster.resume(0)
        assert answers(cluster.addresses[0])


@pytest.mark.parametrize("wait_drain", [True, False], ids=["drained", "killed"])
def test_restart_comes_back_on_the_same_port(wait_drain) -> None:
    with LocalCluster(2) as cluster:
        address, pid = cluster.addresses[1], cluster.pid(1)
        with Connection(address) as conn:
            server_info(conn, 5)
            cluster.restart(1, wait_drain=wait_drain, drain_timeout=60)
            assert cluster.addresses[1] == address and cluster.pid(1) != pid and gone(pid)
            assert cluster.is_running(1)
            # The same channel reaches the new process (a few retries: the old connection died).
            assert server_info(conn, 5, retries=10).live_sessions == 0
        assert answers(cluster.addresses[0])


def test_restart_after_a_kill_and_a_hung_restart() -> None:
    with LocalCluster(1) as cluster:
        address = cluster.addresses[0]
        cluster.kill(0)
        cluster.restart(0)  # not running: started again
        assert cluster.addresses[0] == address and answers(address)
        pid = cluster.pid(0)
        cluster.hang(0)
        cluster.restart(0, wait_drain=False)  # a hung server is killed and replaced
        assert gone(pid) and not cluster.is_hung(0) and answers(address)


def test_a_server_restarted_from_a_thread_outlives_the_thread() -> None:
    """A server dies with the thread that started it (PR_SET_PDEATHSIG): the cluster starts its
    servers from a thread of its own, so a chaos monkey's thread may restart them and end."""
    with LocalCluster(1) as cluster:
        monkey = threading.Thread(target=cluster.restart, args=(0,), kwargs={"wait_drain": False})
        monkey.start()
        monkey.join()
        pid = cluster.pid(0)
        watched = time.monotonic()
        while time.monotonic() - watched < 2.0:  # a SIGTERM would end it well within this
            assert cluster.is_running(0) and cluster.pid(0) == pid
            time.sleep(0.05)
        assert answers(cluster.addresses[0])


def test_add_starts_one_more_server() -> None:
    with LocalCluster(0) as cluster:
        assert cluster.addresses == []
        assert cluster.add() == 0 and cluster.add() == 1
        assert len(set(cluster.addresses)) == 2
        assert all(answers(a) for a in cluster.addresses)


# FaultProxy


@pytest.fixture
def proxied():
    """One server and a FaultProxy in front of it."""
    with LocalCluster(1) as cluster, FaultProxy(cluster.addresses[0]) as proxy:
        yield cluster, proxy


def test_a_proxy_forwards_a_whole_training_loop(proxied) -> None:
    cluster, proxy = proxied
    assert proxy.address != cluster.addresses[0] and proxy.address.startswith("127.0.0.1:")
    direct = DinerDashVectorEnv(4, cluster.addresses[0], expert=True)
    through = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=4,
        address=proxy.address,
        expert=True,
        transport="grpc",  # shared memory would step past the proxy
    )
    try:
        a, b = through.reset(seed=3), direct.reset(seed=3)
        np.testing.assert_array_equal(a[0], b[0])
        assert proxy.connections >= 1
        for _ in range(50):
            actions = b[-1]["expert_action"]
            a, b = through.step(actions), direct.step(actions)
            for x, y in zip(a[:4], b[:4], strict=True):
                np.testing.assert_array_equal(x, y)
    finally:
        through.close()
        direct.close()


def test_latency_delays_both_directions(proxied) -> None:
    _, proxy = proxied
    with Connection(proxy.address) as conn:
        server_info(conn, 5)
        proxy.latency(0.25)
        began = time.monotonic()
        server_info(conn, 10)
        took = time.monotonic() - began
        assert took >= 2 * 0.25, took  # the request, then the reply
        proxy.heal()
        server_info(conn, 5)


def test_blackhole_swallows_bytes_and_keeps_the_connection(proxied) -> None:
    _, proxy = proxied
    with Connection(proxy.address) as conn:
        server_info(conn, 5)
        proxy.blackhole()
        assert proxy.mode == "blackhole"
        began = time.monotonic()
        with pytest.raises(ServiceTimeout):
            server_info(conn, 1)
        assert 1 <= time.monotonic() - began < 1 + SLACK
        assert proxy.connections == 1  # nothing was closed: the hung-network case
        # A new connection gets through TCP and no further.
        channel = grpc.insecure_channel(proxy.address)
        try:
            with pytest.raises(grpc.FutureTimeoutError):
                grpc.channel_ready_future(channel).result(timeout=1)
        finally:
            channel.close()
        proxy.heal()
        assert proxy.mode == "normal"
        assert server_info(conn, 5, retries=10).server_version


def test_reset_fails_the_calls_in_flight_with_unavailable(proxied) -> None:
    _, proxy = proxied
    # retries=0: the channel would retry the call on a new connection (a proxy's fault, not the
    # client's retries, is under test here).
    with Connection(proxy.address, retries=0) as conn:
        server_info(conn, 5)
        proxy.latency(2.0)  # keeps the next call in flight while the connection is reset
        before = proxy.bytes_from_clients
        future = conn.stub.ServerInfo.future(pb.ServerInfoRequest(), timeout=30)
        # The call is in flight once its bytes reached the proxy (held there by the latency).
        deadline = time.monotonic() + SLACK
        while proxy.bytes_from_clients == before and time.monotonic() < deadline:
            time.sleep(0.001)
        assert proxy.bytes_from_clients > before, "the call never reached the proxy"
        proxy.reset()
        with pytest.raises(grpc.RpcError) as e:
            future.result(timeout=SLACK)
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE
        assert proxy.connections == 0
        proxy.heal()
        assert server_info(conn, 5, retries=10).server_version  # new connections work


def test_cut_refuses_every_connection_until_healed(proxied) -> None:
    _, proxy = proxied
    with Connection(proxy.address) as conn:
        server_info(conn, 5)
        proxy.cut()
        assert proxy.mode == "cut"
        with pytest.raises(ServiceTransportError, match="UNAVAILABLE"):
            server_info(conn, 5, retries=2)
        with pytest.raises(ServiceTransportError):
            Connection(proxy.address, connect_timeout=1)
        assert proxy.connections == 0
        proxy.heal()
        assert server_info(conn, 5, retries=10).server_version


def test_a_proxy_refuses_a_bad_target_and_closes_twice() -> None:
    with pytest.raises(ValueError, match="host:port"):
        FaultProxy("nowhere")
    proxy = FaultProxy("127.0.0.1:1")  # nothing listens: each connection is reset
    proxy.close()
    proxy.close()
    with pytest.raises(RuntimeError, match="closed"):
        proxy.blackhole()


# The pytest plugin


USER_TESTS = """
import json
import os

import numpy as np
import pytest
from dinerdash import Connection, DinerDashVectorEnv, ResourceExhausted

PIDS = os.environ["PIDS_FILE"]


def note(*pids):
    with open(PIDS, "a") as f:
        for pid in pids:
            f.write(f"{pid}\\n")


def test_one_server(dinerdash_server):
    with Connection(dinerdash_server) as conn:
        assert conn.server_info().live_sessions == 0
    envs = DinerDashVectorEnv(2, dinerdash_server)
    envs.reset(seed=0)
    envs.step(np.zeros(2, dtype=np.int64))
    envs.close()


def test_default_cluster(dinerdash_cluster):
    assert len(dinerdash_cluster.addresses) == 3
    note(*(dinerdash_cluster.pid(i) for i in range(3)))


@pytest.mark.dinerdash_cluster(2, max_sessions=2)
def test_marked_cluster_survives_a_kill(dinerdash_cluster):
    assert len(dinerdash_cluster.addresses) == 2
    note(dinerdash_cluster.pid(0), dinerdash_cluster.pid(1))
    envs = DinerDashVectorEnv(
        4, dinerdash_cluster.addresses, reconnect=True, failover_after=0.5
    )
    second = DinerDashVectorEnv(1, dinerdash_cluster.addresses[1])
    with pytest.raises(ResourceExhausted):  # --max-sessions 2
        DinerDashVectorEnv(1, dinerdash_cluster.addresses[1])
    second.close()
    envs.reset(seed=0)
    dinerdash_cluster.kill(1)
    *_, truncated, info = envs.step(np.zeros(4, dtype=np.int64))
    assert truncated[2:].all() and envs.lost_addresses == [dinerdash_cluster.addresses[1]]
    envs.close()


def test_factory_and_a_hung_server(dinerdash_cluster_factory):
    one = dinerdash_cluster_factory(1)
    two = dinerdash_cluster_factory(2, session_ttl="1m")
    note(one.pid(0), two.pid(0), two.pid(1))
    two.hang(1)  # left hung: the fixture still stops it
"""


def test_the_plugin_in_a_users_test_file(
    pytester: pytest.Pytester, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pids_file = tmp_path / "pids"
    pytester.makepyfile(test_user=USER_TESTS)
    monkeypatch.setenv("PIDS_FILE", str(pids_file))
    result = pytester.runpytest("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=4)
    pids = [int(line) for line in pids_file.read_text().split()]
    assert len(pids) == 8
    assert all(gone(pid) for pid in pids)  # every server the fixtures started is stopped


def test_the_plugin_registers_its_marker(pytester: pytest.Pytester) -> None:
    result = pytester.runpytest("--markers")
    result.stdout.fnmatch_lines(["@pytest.mark.dinerdash_cluster(n=3, **server_flags):*"])


def test_the_users_test_file_of_the_client_guide(pytester: pytest.Pytester) -> None:
    guide = (Path(__file__).resolve().parent.parent / "docs" / "client.md").read_text()
    section = guide.split("## Testing your own training code", 1)[1].split("\n## ", 1)[0]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    pytester.makepyfile(test_my_training=code)
    result = pytester.runpytest("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=3)
