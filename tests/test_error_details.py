"""The typed errors carry the server's structured details (reason, field, environment index) and
are the same for both envs; a closed env raises a typed error, and ``reset()`` after ``close()``
opens a new session."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from dinerdash import (
    Connection,
    DinerDashEnv,
    DinerDashVectorEnv,
    EnvClosed,
    EpisodeOver,
    FailedPrecondition,
    InvalidArgument,
    ServiceError,
    SessionNotFound,
)
from dinerdash._proto import pb
from gymnasium.vector import AutoresetMode


def test_server_errors_carry_reason_field_and_environment(address: str) -> None:
    with Connection(address) as conn:
        with pytest.raises(SessionNotFound) as e:
            conn.call("Step", pb.StepRequest(session_id="ab" * 16, actions=bytes(4)))
        assert e.value.reason == "SESSION_NOT_FOUND"
        assert e.value.metadata == {"session_id": "ab" * 16}
        sid = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=3)).session_id
        try:
            with pytest.raises(FailedPrecondition) as e:
                conn.call("Step", pb.StepRequest(session_id=sid, actions=bytes(12)))
            assert e.value.reason == "NOT_RESET"
            conn.call("Reset", pb.ResetRequest(session_id=sid))
            actions = np.array([0, 0, 99], dtype="<i4").tobytes()
            with pytest.raises(InvalidArgument) as e:
                conn.call("Step", pb.StepRequest(session_id=sid, actions=actions))
            assert (e.value.reason, e.value.field, e.value.env_index) == (
                "ACTION_OUT_OF_RANGE",
                "actions[2]",
                2,
            )
            bad = pb.ResetRequest(session_id=sid, seeds=[1, 2])
            with pytest.raises(InvalidArgument) as e:
                conn.call("Reset", bad)
            assert (e.value.reason, e.value.field, e.value.env_index) == (
                "INVALID_ARGUMENT",
                "seeds",
                None,
            )
        finally:
            conn.call("CloseSession", pb.CloseSessionRequest(session_id=sid))


def test_bad_actions_are_refused_alike_by_both_envs(address: str) -> None:
    env = DinerDashEnv(address)
    envs = DinerDashVectorEnv(3, address)
    try:
        env.reset(seed=0)
        envs.reset(seed=0)
        for bad in (57, -1, 2**32 + 1):
            with pytest.raises(InvalidArgument) as single:
                env.step(bad)
            actions = np.zeros(3, dtype=np.int64)
            actions[0] = bad
            with pytest.raises(InvalidArgument) as vector:
                envs.step(actions)
            assert (
                str(single.value) == str(vector.value) == f"actions[0] must be in 0..=56, got {bad}"
            )
            for e in (single.value, vector.value):
                assert (e.reason, e.field, e.env_index) == ("ACTION_OUT_OF_RANGE", "actions[0]", 0)
        assert env.step(0)[4]["tick"] == 1  # nothing was stepped by the refusals
    finally:
        env.close()
        envs.close()


def test_episode_over_names_the_environment(address: str) -> None:
    env = DinerDashEnv(address, config={"time_limit": 2})
    envs = DinerDashVectorEnv(
        3, address, autoreset_mode=AutoresetMode.DISABLED, config={"time_limit": 2}
    )
    try:
        env.reset(seed=0)
        env.step(0)
        assert env.step(0)[3]
        with pytest.raises(EpisodeOver) as e:
            env.step(0)
        assert (e.value.reason, e.value.env_index) == ("EPISODE_OVER", 0)
        envs.reset(seed=0)
        envs.step(np.zeros(3, dtype=np.int64))
        assert envs.step(np.zeros(3, dtype=np.int64))[3].all()
        envs.reset(options={"reset_mask": np.array([True, False, True])})
        with pytest.raises(EpisodeOver) as e:
            envs.step(np.zeros(3, dtype=np.int64))
        assert e.value.env_index == 1 and isinstance(e.value, FailedPrecondition)
    finally:
        env.close()
        envs.close()


@pytest.mark.parametrize("render_mode", ["ansi", "rgb_array"])
def test_a_closed_env_raises_typed_errors_and_reset_reopens(address: str, render_mode) -> None:
    env = DinerDashEnv(address, render_mode=render_mode)
    env.reset(seed=5)
    first = env.step(0)[0]
    old = env.session_id
    env.close()
    env.close()  # twice is fine
    calls = (lambda: env.step(0), env.render, env.action_masks, env.snapshot, env.fork)
    for call in calls:
        with pytest.raises(EnvClosed) as e:
            call()
        assert isinstance(e.value, ServiceError) and "reset()" in str(e.value)
    obs, info = env.reset(seed=5)
    try:
        assert env.session_id not in (None, old)
        np.testing.assert_array_equal(env.step(0)[0], first)  # the same episode again
        assert env.render() is not None and env.action_masks().shape == (57,)
    finally:
        env.close()


def test_an_action_that_is_not_an_integer_is_refused(address: str) -> None:
    """As Gymnasium's ``Discrete`` space: 3.7 is not action 3, nor is the string '3'. Integers of
    any kind (Python, numpy, a one-element integer array) are actions."""
    env = DinerDashEnv(address)
    env.reset(seed=5)
    try:
        for bad in (3.7, "3", np.float32(3.0), np.array([1, 2]), None):
            with pytest.raises(InvalidArgument, match="action must be an integer") as e:
                env.step(bad)
            assert e.value.reason == "ACTION_NOT_INTEGER" and e.value.field == "action"
        twin = DinerDashEnv(address)
        twin.reset(seed=5)
        try:
            for good in (np.int64(3), np.uint8(3), np.array(3), np.array([3], dtype=np.int32)):
                ours, theirs = env.step(good), twin.step(3)
                np.testing.assert_array_equal(ours[0], theirs[0])
                assert ours[1:4] == theirs[1:4] and ours[4]["score"] == theirs[4]["score"]
        finally:
            twin.close()
    finally:
        env.close()


def test_a_closed_vector_env_reopens_at_reset(address: str) -> None:
    envs = DinerDashVectorEnv(3, address, render_mode="ansi")
    envs.reset(seed=1)
    expected = envs.step(np.zeros(3, dtype=np.int64))[0]
    envs.close()
    zeros = np.zeros(3, dtype=np.int64)
    calls = (lambda: envs.step(zeros), lambda: envs.step_async(zeros), envs.action_masks)
    for call in (*calls, envs.render, envs.watch_url):
        with pytest.raises(EnvClosed):
            call()
    with pytest.raises(EnvClosed, match="full reset"):
        envs.reset(options={"reset_mask": np.ones(3, dtype=np.bool_)})
    envs.reset(seed=1)
    try:
        np.testing.assert_array_equal(envs.step(np.zeros(3, dtype=np.int64))[0], expected)
    finally:
        envs.close()
    assert envs.closed


def test_a_closed_local_server_env_starts_a_new_server_at_reset() -> None:
    env = DinerDashEnv()
    try:
        env.reset(seed=0)
        first = env.server
        env.close()
        assert first is None or not first.is_running()
        _, info = env.reset(seed=0)
        assert info["tick"] == 0 and env.server is not None and env.server.is_running()
    finally:
        env.close()


@pytest.mark.parametrize("kind", ["env", "vector"])
def test_an_env_never_closed_frees_its_session_at_exit(address: str, kind) -> None:
    """A script that forgets close(): its session is closed as the interpreter exits, not held
    for the server's session TTL."""
    make = (
        "dinerdash.DinerDashEnv(address)"
        if kind == "env"
        else "dinerdash.DinerDashVectorEnv(2, address)"
    )
    script = (
        "import sys, dinerdash\n"
        f"address = sys.argv[1]\nenv = {make}\nenv.reset(seed=1)\n"
        "print(env.session_id if hasattr(env, 'session_id') else env.session_ids[0])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script, address],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    session_id = out.stdout.split()[-1]
    conn = Connection(address)
    try:
        with pytest.raises(SessionNotFound):
            conn.call("Snapshot", pb.SnapshotRequest(session_id=session_id))
    finally:
        conn.close()
