"""The embedded default: no address and no DINERDASH_ADDRESS starts a local server, and close()
stops it, leaving no process behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import dinerdash
import gymnasium
import pytest
from dinerdash import LocalServer, ServerBinaryNotFound

from .conftest import server_binary


def children_named_server() -> list[int]:
    """Live (or zombie) child processes of this test process that run dinerdash-server."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            comm = stat.read_text().split("(", 1)[1].rsplit(")", 1)[0]
        except OSError:
            continue
        if int(fields[1]) == os.getpid() and comm.startswith("dinerdash-serv"):
            pids.append(int(stat.parent.name))
    return pids


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.fixture
def binary_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DINERDASH_SERVER", str(server_binary()))


def _expert_steps(env, steps: int) -> list[tuple]:
    """``steps`` expert steps from ``reset(seed=0)``: (observation, reward, score) of each."""
    obs, info = env.reset(seed=0)
    seen = [(obs.tolist(), 0.0, info["score"])]
    for _ in range(steps):
        obs, reward, _, _, info = env.step(info["expert_action"])
        seen.append((obs.tolist(), float(reward), info["score"]))
    return seen


def test_env_starts_and_stops_its_own_server(binary_env, address: str) -> None:
    before = set(children_named_server())
    env = gymnasium.make("dinerdash:DinerDash-v0", expert=True)
    server = env.unwrapped.server
    assert isinstance(server, LocalServer) and server.is_running()
    pid = server.pid
    assert env.unwrapped.address == server.address and server.address.startswith("127.0.0.1:")
    assert pid in set(children_named_server()) - before
    # It plays the game: the same expert episode, step for step, as the test server's.
    played = _expert_steps(env, 60)
    env.close()
    assert gone(pid) and pid not in children_named_server()
    reference = gymnasium.make("dinerdash:DinerDash-v0", expert=True, address=address)
    try:
        assert played == _expert_steps(reference, 60)
    finally:
        reference.close()
    assert played[-1][2] > 0  # the expert has scored by then


def test_local_server_ignores_dinerdash_tls_ca(binary_env, monkeypatch, tmp_path: Path) -> None:
    # DINERDASH_TLS_CA is for remote servers: the local server is plaintext on loopback, and an
    # env that starts one must not try TLS against it (nor read the file).
    monkeypatch.setenv("DINERDASH_TLS_CA", str(tmp_path / "not-a-ca.pem"))
    env = gymnasium.make("dinerdash:DinerDash-v0", expert=True)
    try:
        _, info = env.reset(seed=0)
        _, _, _, _, info = env.step(info["expert_action"])
        assert info["tick"] == 1
    finally:
        env.close()


def test_vector_env_starts_and_stops_its_own_server(binary_env, address: str) -> None:
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=4)
    pid = envs.server.pid
    assert not gone(pid) and pid in children_named_server()
    obs, _ = envs.reset(seed=0)
    envs.close()
    assert gone(pid) and pid not in children_named_server()
    # Environment i is seeded 0 + i, as a single env on the test server seeded i starts.
    for i in range(4):
        single = dinerdash.DinerDashEnv(address)
        try:
            assert (obs[i] == single.reset(seed=i)[0]).all(), i
        finally:
            single.close()


def test_rollout_starts_and_stops_its_own_server(binary_env, address: str) -> None:
    before = set(children_named_server())
    episodes = list(dinerdash.rollout("expert", episodes=2))
    assert [ep.seed for ep in episodes] == [0, 1]
    assert set(children_named_server()) <= before
    # The same episodes as the test server plays (the expert's scores are deterministic).
    reference = list(dinerdash.rollout("expert", episodes=2, address=address))
    assert [(ep.score, ep.steps) for ep in episodes] == [(ep.score, ep.steps) for ep in reference]
    assert all(ep.score > 0 for ep in episodes)


def test_dinerdash_address_is_used_instead(binary_env, address: str, monkeypatch) -> None:
    monkeypatch.setenv("DINERDASH_ADDRESS", address)
    env = gymnasium.make("dinerdash:DinerDash-v0")
    try:
        assert env.unwrapped.server is None and env.unwrapped.address == address
    finally:
        env.close()


def test_missing_binary_says_how_to_get_one(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("DINERDASH_SERVER", str(tmp_path / "no-such-server"))
    with pytest.raises(ServerBinaryNotFound) as e:
        gymnasium.make("dinerdash:DinerDash-v0")
    message = str(e.value)
    assert "cargo build --release -p dinerdash-server" in message and "DINERDASH_SERVER" in message
    assert isinstance(e.value, FileNotFoundError)


def test_local_server_that_fails_to_start_reports_why(tmp_path: Path) -> None:
    with pytest.raises(dinerdash.LocalServerError) as e:
        LocalServer(server_binary(), args=["--no-such-flag"])
    assert "exited" in str(e.value) and "no-such-flag" in str(e.value)


def test_reconnect_restarts_a_local_server_that_died(binary_env) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", reconnect=True, reconnect_timeout=30)
    server = env.unwrapped.server
    first_pid = server.pid
    try:
        env.reset(seed=0)
        os.kill(first_pid, 9)
        _, _, _, truncated, info = env.step(0)
        assert truncated and info["reconnected"]
        assert server.is_running() and server.pid != first_pid
        env.reset(seed=0)
        _, _, _, truncated, info = env.step(0)
        assert not truncated and info["tick"] == 1 and "reconnected" not in info
    finally:
        env.close()
    assert gone(first_pid) and gone(server.pid)


def test_grpc_tuning_respects_the_callers_choice() -> None:
    probe = "import os, dinerdash; print(os.environ.get('GRPC_EXPERIMENTS'))"
    clean = {
        k: v
        for k, v in os.environ.items()
        if k not in ("GRPC_EXPERIMENTS", "DINERDASH_GRPC_TUNING")
    }

    def seen(**extra: str) -> str:
        out = subprocess.run(
            [sys.executable, "-c", probe],
            env={**clean, **extra},
            capture_output=True,
            text=True,
            timeout=60,
        )
        return out.stdout.strip()

    assert seen() == "-event_engine_client"
    assert seen(GRPC_EXPERIMENTS="") == ""
    assert seen(DINERDASH_GRPC_TUNING="0") == "None"
