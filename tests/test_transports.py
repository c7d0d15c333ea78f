"""Which transport serves a session, and that a change is never silent (issue 37): with
``transport="auto"`` on the server's host the Steps go through shared memory and stay there for a
long run (thousands of steps, episodes ending, every autoreset mode); when the server's side of
the doorbell hangs up, the session changes to gRPC with one warning, one count and
``envs.transports`` saying so; a session reopened after a restart takes shared memory again."""

from __future__ import annotations

import logging
import sys
import time

import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv
from gymnasium.vector import AutoresetMode

from .test_shm import regions

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="shared memory needs Linux")

PATIENCE = 60.0


@pytest.mark.parametrize("mode", list(AutoresetMode))
def test_auto_takes_shared_memory_and_a_long_run_stays_on_it(server, caplog, mode) -> None:
    n, steps = 8, 2500
    env = DinerDashVectorEnv(n, server.address, autoreset_mode=mode, max_episode_steps=25)
    rng = np.random.default_rng(0)
    ends = 0
    try:
        with caplog.at_level(logging.WARNING, logger="dinerdash"):
            _, info = env.reset(seed=0)
            assert env.transports == {server.address: "shm"}
            assert regions(server.pid) >= 1
            for _ in range(steps):
                actions = np.argmax(rng.random((n, 57)) * info["action_mask"], axis=1)
                _, _, terminated, truncated, info = env.step(actions)
                done = terminated | truncated
                ends += int(done.sum())
                if mode == AutoresetMode.DISABLED and done.any():
                    _, fresh = env.reset(options={"reset_mask": done})
                    info["action_mask"] = fresh["action_mask"]
        assert ends >= steps * n // 25 // 2  # episodes ended all along
        assert env.transports == {server.address: "shm"}
        assert env.transport_changes == 0
        assert not [r for r in caplog.records if "instead of" in r.getMessage()]
    finally:
        env.close()


def test_a_single_env_takes_shared_memory_and_stays_on_it(server) -> None:
    env = DinerDashEnv(server.address, config={"time_limit": 20})
    try:
        env.reset(seed=0)
        ends = 0
        for _ in range(2000):
            _, _, terminated, truncated, _ = env.step(0)
            if terminated or truncated:
                ends += 1
                env.reset()
        assert ends >= 50
        assert env.transports == {server.address: "shm"} and env.transport_changes == 0
    finally:
        env.close()


def _hang_up(env: DinerDashVectorEnv) -> None:
    """Makes the server give up its side of the env's doorbell: the doorbell is rung without a
    reply ever being read, until the server hangs up rather than wait."""
    channel = env.fleet.cores[0].transport.channel
    channel.sock.setblocking(False)
    deadline = time.monotonic() + PATIENCE
    while True:
        try:
            channel.sock.send(b"S")
        except BlockingIOError:
            assert time.monotonic() < deadline, "the server never hung up"
            time.sleep(0.001)
        except (BrokenPipeError, ConnectionResetError):
            return


def test_losing_shared_memory_is_a_warning_a_count_and_shows_in_transports(server, caplog) -> None:
    env = DinerDashVectorEnv(8, server.address)  # auto
    try:
        env.reset(seed=0)
        env.step(np.zeros(8, dtype=np.int64))
        assert env.transports == {server.address: "shm"} and env.transport_changes == 0
        _hang_up(env)
        with caplog.at_level(logging.WARNING, logger="dinerdash"):
            for _ in range(20):
                obs, *_ = env.step(np.zeros(8, dtype=np.int64))
        assert obs.shape == (8, 40)
        assert env.transports == {server.address: "grpc"}
        assert env.transport_changes == 1
        warnings = [
            r
            for r in caplog.records
            if r.levelno == logging.WARNING and "instead of shared memory" in r.getMessage()
        ]
        assert len(warnings) == 1, [r.getMessage() for r in caplog.records]
        assert "steps over gRPC" in warnings[0].getMessage()
        assert "doorbell" in warnings[0].getMessage()
    finally:
        env.close()


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_session_reopened_after_a_restart_takes_shared_memory_again(
    start_server, caplog, mode
) -> None:
    server = start_server()
    env = DinerDashVectorEnv(4, server.address, reconnect=True, autoreset_mode=mode)
    try:
        env.reset(seed=0)
        env.step(np.zeros(4, dtype=np.int64))
        server.kill()
        again = server.restart()
        start_server.started.append(again)
        with caplog.at_level(logging.WARNING, logger="dinerdash"):
            _, reward, terminated, truncated, info = env.step(np.zeros(4, dtype=np.int64))
            for _ in range(5):
                env.step(np.zeros(4, dtype=np.int64))
        assert truncated.all() and not terminated.any() and not reward.any()
        assert info["reconnected"].all()
        assert env.transports == {again.address: "shm"}
        assert regions(again.pid) == 1  # the new server holds the new session's region
        # Lost (to gRPC, whose Step met the dead server), then taken up again: two events.
        assert env.transport_changes == 2
        said = [r.getMessage() for r in caplog.records if "instead of" in r.getMessage()]
        assert len(said) == 2 and "steps over shared memory instead of gRPC" in said[1]
    finally:
        env.close()
