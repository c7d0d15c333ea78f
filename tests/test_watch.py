"""Where the web pages are, without a browser: ``python -m dinerdash watch``, ``watch_url()``,
and the URL's host when the pages listen on a wildcard address."""

from __future__ import annotations

import urllib.request

import dinerdash  # noqa: F401  (registers the environments)
import gymnasium as gym
import pytest
from dinerdash import cli
from dinerdash.errors import FailedPrecondition
from dinerdash.watch import pages_url, watch_url


def test_watch_prints_the_pages_url(start_server, capsys) -> None:
    server = start_server("--http-port", "0")
    assert cli.main(["watch", "--address", server.address, "--no-browser"]) == 0
    url = capsys.readouterr().out.strip()
    assert url.startswith("http://127.0.0.1:") and url.endswith("/")
    with urllib.request.urlopen(url, timeout=10) as page:
        assert page.status == 200
        assert b"/static/sessions.js" in page.read()

    with gym.make("dinerdash:DinerDash-v0", address=server.address) as env:
        env.reset(seed=1)
        session_id = env.unwrapped.session_id
        assert env.unwrapped.watch_url() == f"{url}watch/{session_id}?env=0"
        argv = ["watch", "--address", server.address, "--no-browser", "--session", session_id]
        assert cli.main([*argv, "--env", "0"]) == 0
        watch = capsys.readouterr().out.strip()
        assert watch == env.unwrapped.watch_url()
        with urllib.request.urlopen(watch, timeout=10) as page:
            assert b"<canvas" in page.read()

    envs = gym.make_vec("dinerdash:DinerDash-v0", num_envs=3, address=server.address)
    try:
        envs.reset(seed=1)
        (session_id,) = envs.unwrapped.session_ids
        assert envs.unwrapped.watch_url(2) == f"{url}watch/{session_id}?env=2"
        with pytest.raises(IndexError):
            envs.unwrapped.watch_url(3)
    finally:
        envs.close()


def test_a_server_without_pages_says_how_to_serve_them(start_server, capsys) -> None:
    server = start_server()
    assert cli.main(["watch", "--address", server.address, "--no-browser"]) == 1
    assert "--http-port" in capsys.readouterr().err
    with gym.make("dinerdash:DinerDash-v0", address=server.address) as env:
        with pytest.raises(FailedPrecondition, match="--http-port"):
            env.unwrapped.watch_url()


class _Info:
    def __init__(self, port: int, host: str) -> None:
        self.http_port = port
        self.http_host = host


class _Conn:
    """What ``pages_url`` reads of a connection."""

    def __init__(self, address: str, port: int, host: str) -> None:
        self.address = address
        self._info = _Info(port, host)

    def server_info(self) -> _Info:
        return self._info


def test_the_pages_host_is_the_servers_unless_it_is_a_wildcard() -> None:
    assert pages_url(_Conn("gpu-box:50051", 8080, "127.0.0.1")) == "http://127.0.0.1:8080/"
    assert pages_url(_Conn("gpu-box:50051", 8080, "0.0.0.0")) == "http://gpu-box:8080/"
    assert pages_url(_Conn("[::1]:50051", 8080, "::")) == "http://[::1]:8080/"
    assert pages_url(_Conn("a:1", 9, "10.0.0.5")) == "http://10.0.0.5:9/"
    assert (
        watch_url(_Conn("a:1", 9, "::1"), "ab" * 16, 3) == f"http://[::1]:9/watch/{'ab' * 16}?env=3"
    )
