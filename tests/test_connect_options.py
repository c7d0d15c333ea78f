"""``ConnectOptions``: one value for every way of reaching a server, accepted as ``connect=`` by
``gymnasium.make``, ``make_vec`` and ``rollout``; the old keywords are sugar that overrides it."""

from __future__ import annotations

import dataclasses
import socket

import dinerdash
import gymnasium
import numpy as np
import pytest
from dinerdash import ConnectOptions
from dinerdash.connection import CONNECT_FIELDS


def test_one_value_reaches_make_make_vec_and_rollout(address: str) -> None:
    connect = ConnectOptions(address, timeout=7.5, reconnect=True, failover_after=3)
    env = gymnasium.make("dinerdash:DinerDash-v0", connect=connect, expert=True)
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=3, connect=connect)
    try:
        inner = env.unwrapped
        assert inner.address == address
        assert inner._options is connect
        assert inner.reconnect is True
        assert envs.failover_after == 3.0 and envs.reconnect is True
        assert envs._options.timeout == 7.5
        obs, info = env.reset(seed=5)
        _, vinfo = envs.reset(seed=5)
        assert np.array_equal(obs, envs.reset(seed=5)[0][0])
        assert info["seed"] == vinfo["seed"][0] == 5
    finally:
        env.close()
        envs.close()
    (episode,) = dinerdash.rollout("expert", seeds=[5], connect=connect, max_steps=50)
    assert episode.seed == 5 and episode.steps == 50


def test_keywords_beside_connect_override_its_fields(address: str) -> None:
    connect = ConnectOptions("127.0.0.1:1", timeout=5.0)
    # The address keyword wins over the options' unreachable one, and the timeout is kept.
    with dinerdash.DinerDashEnv(address, connect=connect, connect_timeout=2.0) as env:
        assert env.address == address
        assert env._options.timeout == 5.0
        assert env._options.connect_timeout == 2.0
    assert connect.address == "127.0.0.1:1"  # the caller's value is not changed


def test_merged_keeps_the_value_when_nothing_is_given() -> None:
    connect = ConnectOptions("h:1", token="t")
    assert ConnectOptions.merged(connect, "f", address=None) is connect
    assert ConnectOptions.merged(None, "f") == ConnectOptions()
    assert ConnectOptions.merged(connect, "f", tls=True) == dataclasses.replace(connect, tls=True)


def test_every_field_is_a_keyword_of_the_envs(address: str) -> None:
    # The keywords predate ConnectOptions: each one still works as a keyword.
    assert CONNECT_FIELDS[:10] == (
        "address",
        "token",
        "connect_timeout",
        "timeout",
        "tls",
        "tls_ca",
        "server_binary",
        "reconnect",
        "reconnect_timeout",
        "failover_after",
    )
    envs = dinerdash.DinerDashVectorEnv(
        2,
        address,
        token=None,
        connect_timeout=5,
        timeout=9,
        tls=False,
        tls_ca=None,
        server_binary=None,
        reconnect=True,
        reconnect_timeout=4,
        failover_after=None,
    )
    try:
        assert envs._options.timeout == 9.0 and envs.failover_after is None
        assert envs.reconnect_timeout == 4
    finally:
        envs.close()


def test_an_unknown_keyword_is_refused_by_name(address: str) -> None:
    with pytest.raises(
        TypeError, match=r"DinerDashEnv\(\) got an unexpected keyword argument 'adress'"
    ):
        dinerdash.DinerDashEnv(adress=address)
    with pytest.raises(TypeError, match=r"rollout\(\).*'tiemout'"):
        next(dinerdash.rollout("expert", seeds=[0], address=address, tiemout=3))
    with pytest.raises(TypeError, match="connect: expected a ConnectOptions, got dict"):
        dinerdash.DinerDashEnv(connect={"address": address})


@pytest.mark.parametrize(
    ("field", "value", "error"),
    [
        ("timeout", 0, ValueError),
        ("connect_timeout", -1, ValueError),
        ("reconnect_timeout", "soon", ValueError),
        ("failover_after", 0, ValueError),
        ("failover_after", True, TypeError),
    ],
)
def test_bad_values_are_refused_when_the_value_is_built(field, value, error) -> None:
    with pytest.raises(error, match=field):
        ConnectOptions(**{field: value})


def test_the_connect_timeout_follows_a_shorter_call_timeout() -> None:
    assert ConnectOptions().connect_timeout == 10.0
    assert ConnectOptions(timeout=2.5).connect_timeout == 2.5
    assert ConnectOptions(timeout=30).connect_timeout == 10.0
    assert ConnectOptions(timeout=2.5, connect_timeout=4).connect_timeout == 4.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_a_wrong_address_says_what_is_there_and_names_connect_timeout(start_server) -> None:
    """Nothing listening, and the server's web port instead of its gRPC port: each error says
    which, and names the keyword that bounds the wait."""
    with pytest.raises(dinerdash.ServiceTransportError) as e:
        dinerdash.DinerDashEnv(f"127.0.0.1:{_free_port()}", timeout=1)
    assert "connect_timeout=1 s" in str(e.value) and "nothing accepts connections" in str(e.value)

    server = start_server("--http-port", "0")
    conn = dinerdash.Connection(server.address)
    try:
        http_port = conn.server_info().http_port
    finally:
        conn.close()
    with pytest.raises(dinerdash.ServiceTransportError, match=r"answers HTTP/1\.1, not gRPC") as e:
        dinerdash.DinerDashEnv(f"127.0.0.1:{http_port}", connect_timeout=1)
    assert "--http-port" in str(e.value)
