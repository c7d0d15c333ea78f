"""A server killed mid-run: a clear error, or with reconnect=True a loop that goes on once the
server is back (restarted on the same port)."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv, ServiceTransportError

from .trajectories import async_step, plain_step


def test_killed_server_gives_a_clear_error(start_server) -> None:
    server = start_server()
    env = DinerDashEnv(server.address)
    try:
        env.reset(seed=0)
        for _ in range(20):
            env.step(0)
        server.kill()
        with pytest.raises(ServiceTransportError) as e:
            env.step(0)
        message = str(e.value)
        assert server.address in message and "unavailable" in message
        assert "Step" in message
    finally:
        env.close()  # closing after the server is gone does not raise


def test_reconnect_after_restart_on_the_same_port(start_server, caplog) -> None:
    server = start_server()
    env = DinerDashEnv(server.address, reconnect=True, reconnect_timeout=30)
    caplog.set_level(logging.INFO, logger="dinerdash")
    try:
        _, info = env.reset(seed=1)
        old_session = env.session_id
        for _ in range(10):
            env.step(0)
        server.kill()
        start_server.started.append(restarted := server.restart())
        obs, reward, terminated, truncated, info = env.step(0)
        assert truncated and not terminated and reward == 0.0 and info["reconnected"]
        assert info["tick"] == 10  # the last state seen of the interrupted episode
        assert env.session_id != old_session
        # The logger's name says whose line it is; the message does not say it again.
        assert not [r.message for r in caplog.records if r.message.startswith("dinerdash")]
        obs, info = env.reset(seed=1)  # the loop goes on, on the restarted server
        assert info["tick"] == 0
        for _ in range(5):
            _, _, _, truncated, info = env.step(0)
        assert not truncated and info["tick"] == 5 and restarted.address == server.address
    finally:
        env.close()


def test_reconnect_waits_for_a_server_that_comes_back_later(start_server) -> None:
    server = start_server()
    env = DinerDashEnv(server.address, reconnect=True, reconnect_timeout=30)
    try:
        env.reset(seed=2)
        server.kill()
        restarting: list[float] = []  # when the restart began (monotonic)

        def restart() -> None:
            time.sleep(1.0)
            restarting.append(time.monotonic())
            start_server.started.append(server.restart())

        thread = threading.Thread(target=restart)
        began = time.monotonic()  # before the thread's sleep starts, however loaded the machine
        thread.start()
        _, _, _, truncated, info = env.step(0)  # blocks until the server is back
        returned = time.monotonic()
        thread.join(timeout=30)
        assert truncated and info["reconnected"]
        # The step waited: it came back only after the restart had begun (no server answered
        # before), so at least the second the restart was held back.
        assert restarting and returned >= restarting[0] >= began + 1.0, (began, restarting)
        _, info = env.reset(seed=2)
        _, _, _, truncated, info = env.step(0)
        assert not truncated and info["tick"] == 1
    finally:
        env.close()


def test_reconnect_gives_up_after_its_timeout(start_server) -> None:
    server = start_server()
    env = DinerDashEnv(server.address, reconnect=True, reconnect_timeout=1.0)
    try:
        env.reset(seed=0)
        server.kill()
        with pytest.raises(ServiceTransportError, match="could not reconnect"):
            env.step(0)
    finally:
        env.close()


def test_vector_env_killed_server(start_server) -> None:
    server = start_server()
    envs = DinerDashVectorEnv(4, server.address)
    try:
        envs.reset(seed=0)
        envs.step(np.zeros(4, dtype=np.int64))
        server.kill()
        with pytest.raises(ServiceTransportError, match="unavailable"):
            envs.step(np.zeros(4, dtype=np.int64))
    finally:
        envs.close()


@pytest.mark.parametrize("step", [plain_step, async_step], ids=["step", "step_async"])
def test_vector_env_reconnects_next_step(start_server, step) -> None:
    server = start_server()
    envs = DinerDashVectorEnv(4, server.address, reconnect=True, reconnect_timeout=30)
    try:
        envs.reset(seed=0)
        for _ in range(3):
            step(envs, np.zeros(4, dtype=np.int64))
        server.kill()
        start_server.started.append(server.restart())
        obs, reward, terminated, truncated, info = step(envs, np.zeros(4, dtype=np.int64))
        assert truncated.all() and not terminated.any() and (reward == 0).all()
        assert info["reconnected"].all()
        np.testing.assert_array_equal(info["tick"], [3] * 4)  # the interrupted episodes' last state
        # NEXT_STEP: the following step is the autoreset into the new session's episodes.
        obs, reward, terminated, truncated, info = step(envs, np.zeros(4, dtype=np.int64))
        assert info["_seed"].all() and (info["tick"] == 0).all() and not truncated.any()
        _, _, _, _, info = step(envs, np.zeros(4, dtype=np.int64))
        assert (info["tick"] == 1).all()
    finally:
        envs.close()
