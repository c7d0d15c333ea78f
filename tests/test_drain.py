"""A draining server (issue 26): after SIGTERM it refuses new sessions, and the client raises the
typed ``ServerDraining`` (a ``ServiceTransportError``, so old ``except`` clauses still catch it)
without retrying; the sessions it has keep stepping, each Batch saying how long is left."""

from __future__ import annotations

import signal
import time

import dinerdash
import gymnasium
import numpy as np
import pytest
from dinerdash import Connection, ServerDraining, ServiceTransportError
from dinerdash._proto import pb

#: Far beyond any test's length: the server drains for the whole test.
DRAIN_TIMEOUT_S = 600
#: Longest a test waits for the server to handle its signal.
PATIENCE_S = 30.0


def _drain(server, conn: Connection) -> ServerDraining:
    """Sends SIGTERM and waits (bounded) until CreateSession is refused; returns the refusal."""
    server.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + PATIENCE_S
    while True:
        try:
            reply = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=1))
        except ServerDraining as e:
            return e
        # The signal is not handled yet: the session was made; close it again.
        conn.call("CloseSession", pb.CloseSessionRequest(session_id=reply.session_id))
        assert time.monotonic() < deadline, "the server never started draining"
        time.sleep(0.01)


@pytest.mark.usefixtures("each_transport")
def test_a_draining_server_refuses_new_sessions_with_server_draining(start_server) -> None:
    server = start_server("--drain-timeout", str(DRAIN_TIMEOUT_S))
    env = gymnasium.make("dinerdash:DinerDash-v0", address=server.address)
    conn = Connection(server.address)
    try:
        _, info = env.reset(seed=3)
        kept = env.unwrapped.snapshot()
        held = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=2))
        batch = conn.call("Reset", pb.ResetRequest(session_id=held.session_id, seed=1))
        assert batch.drain_remaining_ms == 0

        refused = _drain(server, conn)
        assert isinstance(refused, ServiceTransportError)
        assert refused.reason == "DRAINING"
        assert 0 < refused.drain_remaining_ms <= DRAIN_TIMEOUT_S * 1000
        assert refused.address == server.address
        assert dinerdash.ServerDraining is ServerDraining

        # Through the environments, as a user meets it.
        with pytest.raises(ServerDraining):
            gymnasium.make("dinerdash:DinerDash-v0", address=server.address).reset()
        with pytest.raises(ServerDraining):
            env.unwrapped.fork()
        with pytest.raises(ServerDraining):
            env.unwrapped.restore(kept)
        # Old code that caught the transport error catches it still.
        with pytest.raises(ServiceTransportError):
            gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=2, address=server.address).reset()

        # The sessions it has are served on, each Batch counting down the time left.
        obs, reward, terminated, truncated, info = env.step(int(np.argmax(info["action_mask"])))
        assert obs.shape == (40,)
        actions = np.zeros(2, "<i4").tobytes()
        first = conn.call("Step", pb.StepRequest(session_id=held.session_id, actions=actions))
        time.sleep(0.05)
        second = conn.call("Step", pb.StepRequest(session_id=held.session_id, actions=actions))
        assert 0 < second.drain_remaining_ms < first.drain_remaining_ms
        assert first.drain_remaining_ms <= refused.drain_remaining_ms
    finally:
        env.close()
        conn.close()


def test_a_refusal_is_not_retried(start_server) -> None:
    """Retrying a draining server cannot succeed: the first refusal is raised at once, however
    many retries and however long a backoff the connection has."""
    server = start_server("--drain-timeout", str(DRAIN_TIMEOUT_S))
    conn = Connection(server.address)
    slow = Connection(server.address, retries=3, retry_backoff=60.0)
    try:
        held = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=1))
        _drain(server, conn)
        started = time.monotonic()
        with pytest.raises(ServerDraining):
            slow.call("CreateSession", pb.CreateSessionRequest(num_envs=1))
        # One backoff would be 60 s.
        assert time.monotonic() - started < 60.0
        conn.call("CloseSession", pb.CloseSessionRequest(session_id=held.session_id))
    finally:
        conn.close()
        slow.close()
