"""Every call has a deadline: a stopped (SIGSTOP) server gives a typed ServiceTimeout within the
``timeout=`` keyword or ``DINERDASH_TIMEOUT``, and the env works again once the server resumes."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv, ServiceTimeout
from dinerdash.connection import DEFAULT_TIMEOUT, Connection, call_timeout
from dinerdash.testing import wait_stopped

from .conftest import ServerProcess
from .trajectories import async_step, plain_step


@pytest.fixture
def stoppable(start_server) -> Iterator[ServerProcess]:
    """A server of this test alone, resumed (SIGCONT) before it is stopped."""
    server = start_server()
    yield server
    if server.proc.poll() is None:
        server.proc.send_signal(signal.SIGCONT)


def stop(server: ServerProcess) -> None:
    """SIGSTOP, then wait (bounded) until the kernel reports every thread of the process
    stopped: the signal is asynchronous, and a server still running for a moment would answer
    the next call."""
    server.proc.send_signal(signal.SIGSTOP)
    wait_stopped(server.proc.pid, timeout=10)
    state = Path(f"/proc/{server.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    assert state in ("T", "t"), "the server did not stop within 10 s"


def test_a_stopped_server_times_out_a_step(stoppable: ServerProcess) -> None:
    env = DinerDashEnv(stoppable.address, timeout=1.0)
    try:
        env.reset(seed=0)
        stop(stoppable)
        with pytest.raises(ServiceTimeout) as e:
            env.step(0)
        assert isinstance(e.value, TimeoutError)
        assert "within 1 s" in str(e.value) and e.value.address == stoppable.address
        stoppable.proc.send_signal(signal.SIGCONT)
        # The session goes on. The timed-out Step was already sent: the resumed server may still
        # apply it, before or after this reset (gRPC cannot recall a request), so the next step
        # reports tick 1, or 2 when the old Step landed after the reset.
        _, info = env.reset(seed=0)
        assert info["tick"] == 0
        assert env.step(0)[4]["tick"] in (1, 2)
    finally:
        stoppable.proc.send_signal(signal.SIGCONT)
        env.close()


@pytest.mark.usefixtures("each_transport")
@pytest.mark.parametrize("step", [plain_step, async_step], ids=["step", "step_async"])
def test_dinerdash_timeout_bounds_a_vector_env(
    stoppable: ServerProcess, monkeypatch: pytest.MonkeyPatch, step
) -> None:
    """Over shared memory too, and with ``step_async`` / ``step_wait``, whose wait for the reply
    of a Step rung without a thread must still end at the Step's deadline."""
    monkeypatch.setenv("DINERDASH_TIMEOUT", "1.5")
    envs = DinerDashVectorEnv(4, stoppable.address)
    try:
        envs.reset(seed=0)
        stop(stoppable)
        with pytest.raises(ServiceTimeout, match=r"within 1\.5 s"):
            step(envs, np.zeros(4, dtype=np.int64))
        with pytest.raises(ServiceTimeout):
            envs.reset(seed=1)
    finally:
        stoppable.proc.send_signal(signal.SIGCONT)
        envs.close()


def test_the_deadline_is_always_finite(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DINERDASH_TIMEOUT", raising=False)
    assert call_timeout(None) == DEFAULT_TIMEOUT and 0 < DEFAULT_TIMEOUT < 600
    assert call_timeout(2) == 2.0
    monkeypatch.setenv("DINERDASH_TIMEOUT", "7")
    assert call_timeout(None) == 7.0
    for bad in ("0", "-1", "inf", "soon"):
        monkeypatch.setenv("DINERDASH_TIMEOUT", bad)
        with pytest.raises(ValueError, match=r"DINERDASH_TIMEOUT|timeout"):
            call_timeout(None)


def test_connections_carry_the_deadline(address: str) -> None:
    with Connection(address, timeout=3) as conn:
        assert conn.timeout == 3.0
        assert conn.server_info().ruleset
