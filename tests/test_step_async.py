"""Issue 14: ``step_async`` / ``step_wait`` on the vector env give exactly the trajectories of
``step()`` (every autoreset mode, one server and several, two envs pipelined), and misuse is a
clear error."""

from __future__ import annotations

import gc
import multiprocessing
import signal
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from dinerdash import DinerDashVectorEnv, FailedPrecondition, InvalidArgument
from gymnasium.error import AlreadyPendingCallError, NoAsyncCallError
from gymnasium.vector import AutoresetMode

from .conftest import ServerProcess
from .test_deadlines import stop
from .trajectories import assert_same, async_step, trajectory

N = 7


@pytest.fixture
def two(start_server) -> list[ServerProcess]:
    return [start_server() for _ in range(2)]


def addresses(servers: list[ServerProcess], spread: bool) -> str | list[str]:
    return [s.address for s in servers] if spread else servers[0].address


@pytest.mark.parametrize("spread", [False, True], ids=["one-server", "two-servers"])
@pytest.mark.parametrize("mode", list(AutoresetMode))
def test_step_async_gives_the_trajectory_of_step(two, mode, spread) -> None:
    kwargs = {"expert": True, "autoreset_mode": mode, "config": {"lives": 2}}
    sync = DinerDashVectorEnv(N, addresses(two, spread), **kwargs)
    pipelined = DinerDashVectorEnv(N, addresses(two, spread), **kwargs)
    try:
        a, b = trajectory(sync), trajectory(pipelined, step=async_step)
        assert any(step[2].any() for step in a[1:])  # episodes ended (and were reset)
        assert_same(a, b)
    finally:
        sync.close()
        pipelined.close()


def random_actions(seed: int, steps: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 57, size=(steps, N))


def stepped(envs: DinerDashVectorEnv, seed: int, actions: np.ndarray) -> Iterator[tuple]:
    yield envs.reset(seed=seed)
    for a in actions:
        yield envs.step(a)


@pytest.mark.parametrize("spread", [False, True], ids=["one-server", "two-servers"])
@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_two_envs_pipelined_give_their_step_trajectories(two, mode, spread) -> None:
    """The trainer's pattern: env B's step is on the wire while env A's results are used, and
    the other way round. Each env's trajectory is the one step() gives it alone."""
    steps = 250
    acts_a, acts_b = random_actions(1, steps), random_actions(2, steps)
    kwargs = {"autoreset_mode": mode, "max_episode_steps": 120}
    envs = [DinerDashVectorEnv(N, addresses(two, spread), **kwargs) for _ in range(4)]
    try:
        ref_a, ref_b = list(stepped(envs[2], 10, acts_a)), list(stepped(envs[3], 20, acts_b))
        a, b = envs[0], envs[1]
        got_a, got_b = [a.reset(seed=10)], [b.reset(seed=20)]
        a.step_async(acts_a[0])
        for t in range(steps):
            b.step_async(acts_b[t])
            got_a.append(a.step_wait())
            if t + 1 < steps:
                a.step_async(acts_a[t + 1])
            got_b.append(b.step_wait())
        assert any(step[3].any() for step in ref_a[1:])  # the time limit truncated episodes
        assert_same(ref_a, got_a)
        assert_same(ref_b, got_b)
    finally:
        for e in envs:
            e.close()


def test_misuse_is_a_clear_error(address: str) -> None:
    envs = DinerDashVectorEnv(3, address)
    zeros = np.zeros(3, dtype=np.int64)
    try:
        envs.reset(seed=0)
        with pytest.raises(NoAsyncCallError, match="step_wait\\(\\) without a step_async"):
            envs.step_wait()
        envs.step_async(zeros)
        with pytest.raises(AlreadyPendingCallError, match="step_async\\(\\) while a step_async"):
            envs.step_async(zeros)
        for call in (
            lambda: envs.step(zeros),
            lambda: envs.reset(seed=1),
            envs.action_masks,
        ):
            with pytest.raises(AlreadyPendingCallError, match="call step_wait\\(\\) first"):
                call()
        _, _, _, _, info = envs.step_wait()  # the first step_async is still the pending one
        np.testing.assert_array_equal(info["tick"], [1, 1, 1])
        with pytest.raises(NoAsyncCallError):
            envs.step_wait()
        # Bad actions are refused before anything is sent, and leave nothing pending.
        with pytest.raises(InvalidArgument, match=r"actions\[1\] must be in 0\.\.=56"):
            envs.step_async(np.array([0, 57, 0]))
        with pytest.raises(ValueError, match="expected shape \\(3,\\)"):
            envs.step_async(np.zeros(4, dtype=np.int64))
        with pytest.raises(NoAsyncCallError):
            envs.step_wait()
        assert envs.step(zeros)[4]["tick"].tolist() == [2, 2, 2]
    finally:
        envs.close()


@pytest.mark.parametrize("spread", [False, True], ids=["one-server", "two-servers"])
def test_server_errors_arrive_at_step_wait_as_from_step(two, spread) -> None:
    envs = DinerDashVectorEnv(
        4, addresses(two, spread), autoreset_mode=AutoresetMode.DISABLED, max_episode_steps=2
    )
    zeros = np.zeros(4, dtype=np.int64)
    try:
        envs.reset(seed=0)
        envs.step(zeros)
        envs.step_async(zeros)
        assert envs.step_wait()[3].all()
        with pytest.raises(FailedPrecondition, match="environment 0: episode is over") as sync:
            envs.step(zeros)
        envs.step_async(zeros)
        with pytest.raises(FailedPrecondition, match="environment 0: episode is over") as pipe:
            envs.step_wait()
        assert str(pipe.value) == str(sync.value)
        assert pipe.value.env_index == sync.value.env_index == 0
        with pytest.raises(NoAsyncCallError):  # an error ends the pending step
            envs.step_wait()
        _, info = envs.reset(options={"reset_mask": np.ones(4, dtype=np.bool_)})
        assert (info["tick"] == 0).all()
    finally:
        envs.close()


def test_step_wait_timeout_or_interrupt_keeps_the_step_pending(start_server) -> None:
    server = start_server()
    envs = DinerDashVectorEnv(2, server.address)
    try:
        envs.reset(seed=0)
        stop(server)
        try:
            envs.step_async(np.zeros(2, dtype=np.int64))
            with pytest.raises(multiprocessing.TimeoutError, match="still pending"):
                envs.step_wait(timeout=0.2)
            with pytest.raises(AlreadyPendingCallError):
                envs.step_async(np.zeros(2, dtype=np.int64))
            # Ctrl-C while waiting loses nothing either: the step stays pending. Python's own
            # handler, whatever this process inherited (a job started in the background by a
            # non-interactive shell ignores SIGINT, and Python then leaves it ignored).
            main = threading.main_thread().ident
            interrupt = threading.Timer(0.2, signal.pthread_kill, (main, signal.SIGINT))
            inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
            interrupt.start()
            try:
                with pytest.raises(KeyboardInterrupt):
                    envs.step_wait()
            finally:
                interrupt.join()
                signal.signal(signal.SIGINT, inherited)
        finally:
            server.proc.send_signal(signal.SIGCONT)
        _, _, _, _, info = envs.step_wait(timeout=30)
        np.testing.assert_array_equal(info["tick"], [1, 1])
    finally:
        envs.close()


def test_close_cancels_a_pending_step_and_reset_reopens(address: str) -> None:
    envs = DinerDashVectorEnv(2, address)
    envs.reset(seed=0)
    envs.step_async(np.zeros(2, dtype=np.int64))
    envs.close()
    try:
        with pytest.raises(NoAsyncCallError):
            envs.step_wait()
        _, info = envs.reset(seed=0)  # new sessions, nothing pending
        assert (info["tick"] == 0).all()
        envs.step_async(np.zeros(2, dtype=np.int64))
        assert (envs.step_wait()[4]["tick"] == 1).all()
    finally:
        envs.close()


def step_threads() -> list[str]:
    """The names of the client's step threads alive now."""
    return [t.name for t in threading.enumerate() if t.name.startswith("dinerdash-step")]


def test_the_step_threads_end_with_the_env(address: str) -> None:
    """Over gRPC a session's Steps are made by a thread of the env, which ends with it."""
    before = len(step_threads())
    envs = DinerDashVectorEnv(2, address, transport="grpc")
    envs.reset(seed=0)
    envs.step_async(np.zeros(2, dtype=np.int64))
    envs.step_wait()
    assert len(step_threads()) == before + 1
    envs.close()
    dropped = DinerDashVectorEnv(2, address, transport="grpc")  # no close(): held weakly
    dropped.reset(seed=0)
    dropped.step_async(np.zeros(2, dtype=np.int64))
    dropped.step_wait()
    del dropped
    gc.collect()
    deadline = time.monotonic() + 10
    while len(step_threads()) > before:
        assert time.monotonic() < deadline, step_threads()
        time.sleep(0.01)


def test_over_shared_memory_step_async_rings_and_starts_no_thread(address: str) -> None:
    """Over shared memory ``step_async`` rings the doorbell itself and returns: the server steps
    while the caller works, with no thread in between. Two envs pipelined so are both stepped
    by the server before either reply is collected."""
    threads = step_threads()
    pair = [DinerDashVectorEnv(3, address, transport="shm") for _ in range(2)]
    try:
        for envs in pair:
            envs.reset(seed=0)
        for envs in pair:
            envs.step_async(np.zeros(3, dtype=np.int64))
        for envs in pair:  # both replies are in, neither yet collected
            (core,) = envs.fleet.cores
            assert core.shm_sent is not None and core.step_thread is None
            assert core.transport.ready(30.0)
        for envs in pair:
            np.testing.assert_array_equal(envs.step_wait()[4]["tick"], [1, 1, 1])
        # grpcio's own threads (its channel spin thread for a Reset's future) come and go
        assert step_threads() == threads
        assert [envs.transports for envs in pair] == [{address: "shm"}] * 2
    finally:
        for envs in pair:
            envs.close()
