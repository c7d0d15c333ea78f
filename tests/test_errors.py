"""Every typed exception, raised by the real server for real bad input, with its message."""

from __future__ import annotations

import dinerdash
import gymnasium
import pytest
from dinerdash import (
    Connection,
    DinerDashEnv,
    DinerDashVectorEnv,
    FailedPrecondition,
    InvalidArgument,
    ResourceExhausted,
    ServiceError,
    ServiceTransportError,
    SessionNotFound,
    Unauthenticated,
)
from dinerdash._proto import pb


def test_session_not_found(address: str) -> None:
    env = DinerDashEnv(address)
    try:
        env.reset(seed=0)
        with Connection(address) as conn:  # the session is closed behind the env's back
            conn.call("CloseSession", pb.CloseSessionRequest(session_id=env.session_id))
        with pytest.raises(SessionNotFound) as e:
            env.step(0)
        assert e.value.details and e.value.address == address
        with Connection(address) as conn, pytest.raises(SessionNotFound):
            conn.call("Step", pb.StepRequest(session_id="0" * 32, actions=b"\0\0\0\0"))
    finally:
        env.close()


@pytest.mark.parametrize("action", [57, -1, 1000])
def test_invalid_action(address: str, action: int) -> None:
    env = DinerDashEnv(address)
    try:
        env.reset(seed=0)
        with pytest.raises(InvalidArgument) as e:
            env.step(action)
        assert isinstance(e.value, ValueError)
        assert "56" in str(e.value)  # the server names the allowed range
    finally:
        env.close()


def test_invalid_configuration_and_arrivals(address: str) -> None:
    with pytest.raises(InvalidArgument, match="lives"):
        DinerDashEnv(address, config={"lives": 0})
    with pytest.raises(InvalidArgument, match="patience"):
        gymnasium.make("dinerdash:DinerDash-v0", address=address, config={"patience_type1": 1000})
    env = DinerDashEnv(address)
    try:
        with pytest.raises(InvalidArgument) as e:
            env.reset(options={"arrivals": [(3, 2)]})
        assert "1..=2" in str(e.value) or "type" in str(e.value)
        with pytest.raises(InvalidArgument):
            env.reset(options={"arrivals": [(1, 7)]})
        with pytest.raises(InvalidArgument):
            env.reset(options={"arrivals": [(1, 1)] * 201})
    finally:
        env.close()


def test_invalid_vector_arguments(address: str) -> None:
    with Connection(address) as conn:
        limit = conn.server_info().max_envs_per_session
    with pytest.raises(InvalidArgument, match="num_envs"):
        DinerDashVectorEnv(limit + 1, address)
    envs = DinerDashVectorEnv(2, address)
    try:
        with pytest.raises(InvalidArgument):
            envs.reset(options={"arrivals": [[(1, 1)], [(1, 1)], [(1, 1)]]})
        with Connection(address) as conn:
            sid = envs.session_ids[0]
            with pytest.raises(InvalidArgument):  # seeds not of length N
                conn.call("Reset", pb.ResetRequest(session_id=sid, seeds=[1, 2, 3]))
            with pytest.raises(InvalidArgument):  # both seed and seeds
                conn.call("Reset", pb.ResetRequest(session_id=sid, seed=1, seeds=[1, 2]))
            with pytest.raises(InvalidArgument):  # actions not N int32
                conn.call("Step", pb.StepRequest(session_id=sid, actions=b"\0\0\0"))
            with pytest.raises(InvalidArgument):  # env_index out of 0..N
                conn.call("Render", pb.RenderRequest(session_id=sid, env_index=2))
    finally:
        envs.close()


def test_invalid_snapshot_and_rollout(address: str) -> None:
    with Connection(address) as conn, pytest.raises(InvalidArgument):
        conn.call("Restore", pb.RestoreRequest(snapshot=b"not a snapshot"))
    with pytest.raises(InvalidArgument):
        list(dinerdash.rollout("expert", seeds=[], address=address))
    with pytest.raises(InvalidArgument):
        list(dinerdash.rollout("expert", seeds=[0], address=address, max_steps=0))


def test_failed_precondition(address: str) -> None:
    env = DinerDashEnv(address, config={"lives": 1}, render_mode="ansi")
    try:
        with pytest.raises(FailedPrecondition):
            env.render()  # never reset: nothing to draw
        with pytest.raises(FailedPrecondition):
            env.step(0)  # never reset
        env.reset(seed=0)
        for _ in range(3000):
            _, _, terminated, _, _ = env.step(0)
            if terminated:
                break
        assert terminated
        with pytest.raises(FailedPrecondition, match="reset"):
            env.step(0)  # the episode is over
    finally:
        env.close()


def test_resource_exhausted(start_server) -> None:
    server = start_server("--max-sessions", "1")
    first = DinerDashEnv(server.address)
    try:
        with pytest.raises(ResourceExhausted) as e:
            DinerDashEnv(server.address)
        assert e.value.details
    finally:
        first.close()
    DinerDashEnv(server.address).close()  # the closed session freed its slot


def test_unauthenticated(start_server) -> None:
    server = start_server("--auth-token", "s3cret-0123456789")
    hint = "token= or DINERDASH_AUTH_TOKEN"  # the client's words, not gRPC metadata's
    with pytest.raises(Unauthenticated, match=hint):
        DinerDashEnv(server.address)
    with pytest.raises(Unauthenticated, match=hint):
        DinerDashEnv(server.address, token="wrong")
    env = DinerDashEnv(server.address, token="s3cret-0123456789")
    try:
        env.reset(seed=0)
        env.step(0)
    finally:
        env.close()


def test_connect_timeout_is_readable(start_server) -> None:
    gone = start_server()
    gone.stop()  # nothing listens on its port any more
    with pytest.raises(ServiceTransportError) as e:
        DinerDashEnv(gone.address, connect_timeout=1.0)
    assert isinstance(e.value, OSError) and isinstance(e.value, ServiceError)
    assert gone.address in str(e.value) and "could not connect" in str(e.value)


def test_a_lost_server_without_reconnect_says_what_would_ride_it_out(start_server) -> None:
    server = start_server()
    env = DinerDashEnv(server.address)
    try:
        env.reset(seed=0)
        server.kill()
        with pytest.raises(ServiceTransportError, match="reconnect=True would wait") as e:
            env.step(0)
        assert "several addresses" in str(e.value)
    finally:
        env.close()
