"""Issue 5's client side: one vector env spread over three real servers behaves, step for step,
like the same vector env on one server; a killed replica gives a clear error or is recovered."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from dinerdash import (
    Connection,
    DinerDashVectorEnv,
    EpisodeOver,
    FailedPrecondition,
    InvalidArgument,
    ServiceTransportError,
)
from dinerdash.connection import resolve_replicas
from gymnasium.vector import AutoresetMode

from .trajectories import assert_same, trajectory

N = 7  # uneven on purpose: slices of 3, 2 and 2


@pytest.fixture
def three(start_server):
    return [start_server() for _ in range(3)]


@pytest.mark.parametrize(("mode", "n"), [(mode, N) for mode in AutoresetMode] + [(None, 3)])
def test_three_servers_give_the_trajectories_of_one(three, mode, n) -> None:
    # n = 3: one environment per server, in the default NEXT_STEP mode.
    kwargs = {"expert": True, "config": {"lives": 2}}
    if mode is not None:
        kwargs["autoreset_mode"] = mode
    one = DinerDashVectorEnv(n, three[0].address, **kwargs)
    spread = DinerDashVectorEnv(n, [s.address for s in three], **kwargs)
    try:
        assert [a for a, _ in spread.env_slices] == [s.address for s in three]
        slices = [slice(0, 3), slice(3, 5), slice(5, 7)]
        if n == 3:
            slices = [slice(i, i + 1) for i in range(3)]
        assert [sl for _, sl in spread.env_slices] == slices
        for server in three:  # one batched session on each server
            with Connection(server.address) as conn:
                assert conn.server_info().live_sessions == (2 if server is three[0] else 1)
        a, b = trajectory(one), trajectory(spread)
        assert any(step[2].any() for step in a[1:])  # episodes ended and were autoreset
        assert_same(a, b)
    finally:
        one.close()
        spread.close()


def test_comma_separated_addresses(three) -> None:
    envs = DinerDashVectorEnv(3, ",".join(s.address for s in three))
    try:
        assert envs.addresses == [s.address for s in three]
        _, info = envs.reset(seed=10)
        np.testing.assert_array_equal(info["seed"], [10, 11, 12])
    finally:
        envs.close()


def test_fewer_envs_than_servers_uses_fewer_servers(three) -> None:
    envs = DinerDashVectorEnv(2, [s.address for s in three])
    try:
        assert envs.addresses == [three[0].address, three[1].address]
    finally:
        envs.close()


def test_a_dns_name_with_several_addresses_is_several_replicas(monkeypatch) -> None:
    # No resolver on this machine returns several loopback addresses for one name, so the
    # resolver's answer is given here; the expansion is what is tested.
    answers = [
        (socket.AF_INET, socket.SOCK_STREAM, 6, "", (f"10.0.0.{i}", 50051)) for i in (1, 2, 3)
    ]
    answers.append((socket.AF_INET6, socket.SOCK_STREAM, 6, "", ("fd00::1", 50051, 0, 0)))
    monkeypatch.setattr(socket, "getaddrinfo", lambda *a, **k: answers)
    assert resolve_replicas("dinerdash-headless:50051") == [
        "10.0.0.1:50051",
        "10.0.0.2:50051",
        "10.0.0.3:50051",
    ]
    monkeypatch.undo()
    assert resolve_replicas("localhost:1234") == ["localhost:1234"]  # one server, not two
    assert resolve_replicas(["127.0.0.1:1", "127.0.0.1:2"]) == ["127.0.0.1:1", "127.0.0.1:2"]


def test_bad_actions_are_refused_before_any_server_steps(three) -> None:
    envs = DinerDashVectorEnv(N, [s.address for s in three])
    try:
        envs.reset(seed=0)
        for bad in (57, -1, 2**32 + 1):  # the last would wrap to 1 as an int32
            actions = np.zeros(N, dtype=np.int64)
            actions[5] = bad
            message = rf"^actions\[5\] must be in 0..=56, got {bad}$"
            with pytest.raises(InvalidArgument, match=message):
                envs.step(actions)
        _, _, _, _, info = envs.step(np.zeros(N, dtype=np.int64))
        np.testing.assert_array_equal(info["tick"], np.ones(N))  # no server stepped before
    finally:
        envs.close()


def test_errors_name_environments_by_their_index_in_the_vector_env(three) -> None:
    envs = DinerDashVectorEnv(
        N, [s.address for s in three], autoreset_mode=AutoresetMode.DISABLED, max_episode_steps=1
    )
    try:
        envs.reset(seed=0)
        assert envs.step(np.zeros(N, dtype=np.int64))[3].all()
        envs.reset(options={"reset_mask": np.arange(N) < 4})  # all of server 1, one of server 2
        with pytest.raises(FailedPrecondition) as e:
            envs.step(np.zeros(N, dtype=np.int64))
        # Server 2 holds environments 3 and 4; its environment 1 is environment 4 here. The
        # index comes from the error's structured details (reason EPISODE_OVER, env_index).
        assert isinstance(e.value, EpisodeOver) and e.value.reason == "EPISODE_OVER"
        assert e.value.env_index == 4
        assert "episode is over; call reset" in str(e.value)
        assert "environment 4 of the vector env" in str(e.value)
        assert "environments 3..4" in str(e.value)
    finally:
        envs.close()


def test_killing_one_replica_is_a_clear_error(three) -> None:
    envs = DinerDashVectorEnv(N, [s.address for s in three])
    try:
        envs.reset(seed=0)
        envs.step(np.zeros(N, dtype=np.int64))
        three[1].kill()
        with pytest.raises(ServiceTransportError) as e:
            envs.step(np.zeros(N, dtype=np.int64))
        assert three[1].address in str(e.value) and "environments 3..4" in str(e.value)
    finally:
        envs.close()


def test_killed_replica_recovers_with_reconnect(three, start_server) -> None:
    kwargs = {"expert": True, "reconnect": True, "reconnect_timeout": 30}
    reference = DinerDashVectorEnv(N, three[0].address, expert=True)
    envs = DinerDashVectorEnv(N, [s.address for s in three], **kwargs)
    try:
        _, info = envs.reset(seed=0)
        _, ref_info = reference.reset(seed=0)
        for _ in range(20):
            _, _, _, _, info = envs.step(info["expert_action"])
            _, _, _, _, ref_info = reference.step(ref_info["expert_action"])
        three[2].kill()
        start_server.started.append(three[2].restart())
        actions = info["expert_action"]
        obs, reward, terminated, truncated, info = envs.step(actions)
        ref = reference.step(actions)
        np.testing.assert_array_equal(truncated, [False] * 5 + [True] * 2)
        np.testing.assert_array_equal(info["reconnected"], [False] * 5 + [True] * 2)
        # The replicas that stayed up go on exactly as before.
        np.testing.assert_array_equal(obs[:5], ref[0][:5])
        np.testing.assert_array_equal(reward[:5], ref[1][:5])
        obs, reward, terminated, truncated, info = envs.step(info["expert_action"])
        # The autoreset: new episodes, seeded by the restarted replica (64-bit entropy), the
        # others' seeds kept.
        np.testing.assert_array_equal(info["seed"][:5], np.arange(5))
        assert (info["seed"][5:] != [5, 6]).all(), info["seed"]
        np.testing.assert_array_equal(info["tick"][5:], [0, 0])
        assert (info["tick"][:5] == 22).all()
    finally:
        envs.close()
        reference.close()
