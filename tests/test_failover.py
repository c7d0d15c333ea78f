"""Issue 18, part 2: failover across servers. A vector env spread over three real servers
(``reconnect=True``) loses one to ``SIGKILL`` for good: after ``failover_after`` its environments
move to the two servers left and all N step on, while the environments of the servers that
stayed up keep the trajectories of a run without the failure; with no server left it raises
``NoServerLeft``.

The servers are a ``dinerdash.testing.LocalCluster`` of three, from the package's pytest plugin.

Time bounds: the wait the client's design allows (``failover_after``, ``reconnect_timeout``) +
:data:`SLACK` for the work itself + the time this process and the servers waited for a CPU over
the same interval (:class:`tests.cpu_wait.CpuWait`): what a loaded machine adds is measured, not
guessed, and a wait for the wrong timeout (the call's 60 s, the reconnect's 30 s) still fails."""

from __future__ import annotations

import time

import gymnasium
import numpy as np
import pytest
from dinerdash import (
    Connection,
    DinerDashVectorEnv,
    NoServerLeft,
    ServiceTransportError,
)
from gymnasium.vector import AutoresetMode

from .cpu_wait import CpuWait
from .trajectories import async_step, plain_step

N = 7  # slices of 3, 2 and 2: the middle server's environments 3..4 move
FAILOVER_AFTER = 1.0
#: The fixed part of every time bound beyond the design's waits, for the work on a quiet machine;
#: what load adds is measured (:class:`tests.cpu_wait.CpuWait`).
SLACK = 5.0
KILL_AT = 30
STEPS = 120
MOVED = np.array([False] * 3 + [True] * 2 + [False] * 2)
KEPT = np.flatnonzero(~MOVED)
# Episodes end every 40 ticks (and at the second group lost), so that the kept environments'
# autoresets (and SAME_STEP's final_obs) are compared too.
CONFIG = {"lives": 2, "time_limit": 40}


#: dinerdash_cluster: three servers (dinerdash.testing's pytest plugin).
pytestmark = [pytest.mark.dinerdash_cluster(3), pytest.mark.usefixtures("each_transport")]


def record(result: tuple, i: int) -> dict:
    """Everything a reset or step result says about environment ``i``: its value in every
    array, and every info key (nested ``final_info`` included) that its ``_key`` mask gives it.
    ``reconnected`` is left out: only the failover run has it."""
    *arrays, info = result
    out = {f"[{j}]": np.asarray(a)[i] for j, a in enumerate(arrays)}

    def flatten(info: dict, prefix: str) -> None:
        for key, value in info.items():
            mask = info.get(f"_{key}")
            if key.startswith("_") or key == "reconnected" or (mask is not None and not mask[i]):
                continue
            if isinstance(value, dict):
                flatten(value, f"{prefix}{key}.")
            else:
                out[prefix + key] = value[i]

    flatten(info, "")
    return out


def assert_same_envs(a: tuple, b: tuple, envs, where: str) -> None:
    for i in envs:
        x, y = record(a, i), record(b, i)
        assert x.keys() == y.keys(), f"{where}, environment {i}"
        for key in x:
            u, v = np.asarray(x[key]), np.asarray(y[key])
            assert u.dtype == v.dtype, f"{where}, environment {i}, {key}"
            np.testing.assert_array_equal(u, v, err_msg=f"{where}, environment {i}, {key}")


def live_sessions(address: str) -> int:
    with Connection(address) as conn:
        return conn.server_info().live_sessions


@pytest.mark.parametrize("step", [plain_step, async_step], ids=["step", "step_async"])
@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_killed_server_moves_its_environments(dinerdash_cluster, mode, step) -> None:
    kwargs = {"expert": True, "autoreset_mode": mode, "config": CONFIG}
    s0, s1, s2 = dinerdash_cluster.addresses
    # The run without a failure, on the server that stays up.
    reference = DinerDashVectorEnv(N, s0, **kwargs)
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=N,
        address=[s0, s1, s2],
        reconnect=True,
        reconnect_timeout=30,
        failover_after=FAILOVER_AFTER,
        **kwargs,
    )
    rng = np.random.default_rng(11)
    try:
        assert envs.unwrapped.failover_after == FAILOVER_AFTER
        a, b = envs.reset(seed=50), reference.reset(seed=50)
        assert_same_envs(a, b, range(N), "reset")
        kept_ended = 0
        for t in range(STEPS):
            info = b[-1]
            actions = np.where(rng.random(N) < 0.6, info["expert_action"], rng.integers(0, 57, N))
            before = a
            if t == KILL_AT:
                dinerdash_cluster.kill(1)  # SIGKILL, never restarted
                killed = time.monotonic()
                cpu_wait = CpuWait.of(dinerdash_cluster)
            a, b = step(envs, actions), reference.step(actions)
            assert_same_envs(a, b, KEPT, f"step {t}")
            obs, reward, terminated, truncated, info = a
            assert obs.shape == (N, 40) and info["action_mask"].shape == (N, 57)
            assert info["expert_action"].shape == (N,)
            np.testing.assert_array_equal(envs.unwrapped.action_masks(), info["action_mask"])
            kept_ended += int((terminated | truncated)[KEPT].sum())
            if t < KILL_AT:
                assert "reconnected" not in info
            elif t == KILL_AT:
                failover = time.monotonic() - killed
                failover_load = cpu_wait.seconds()
                # The moved episodes end truncated, as after a reconnect.
                np.testing.assert_array_equal(info["reconnected"], MOVED)
                np.testing.assert_array_equal(info["_reconnected"], MOVED)
                assert truncated[MOVED].all() and not terminated[MOVED].any()
                assert (reward[MOVED] == 0).all()
                if mode == AutoresetMode.NEXT_STEP:
                    # Their last state; the next step is the autoreset.
                    np.testing.assert_array_equal(info["tick"][MOVED], before[4]["tick"][MOVED])
                else:
                    # SAME_STEP: the new episodes start now; the old ones' last state is final_*.
                    assert info["_seed"][MOVED].all() and (info["tick"][MOVED] == 0).all()
                    for i in np.flatnonzero(MOVED):
                        np.testing.assert_array_equal(info["final_obs"][i], before[0][i])
                    np.testing.assert_array_equal(
                        info["final_info"]["tick"][MOVED], before[4]["tick"][MOVED]
                    )
                # Environment i keeps index i; the moved pieces went to the least loaded
                # server first (s2 held 2, s0 held 3).
                assert envs.unwrapped.env_slices == [
                    (s0, slice(0, 3)),
                    (s2, slice(3, 4)),
                    (s0, slice(4, 5)),
                    (s2, slice(5, 7)),
                ]
                assert envs.unwrapped.addresses == [s0, s2]
                assert envs.unwrapped.lost_addresses == [s1]
                # s0: its first session, the moved one and the reference's.
                assert live_sessions(s0) == 3 and live_sessions(s2) == 2
            else:
                assert "reconnected" not in info
                new_episode = t == KILL_AT + 1 and mode == AutoresetMode.NEXT_STEP
                if new_episode:  # the autoreset into the new sessions' episodes
                    assert info["_seed"][MOVED].all() and (info["tick"][MOVED] == 0).all()
                    assert (info["seed"][MOVED] != 0).all()  # drawn by their new servers
                first_step = KILL_AT + (2 if mode == AutoresetMode.NEXT_STEP else 1)
                if t == first_step:
                    # Every one of the N environments has stepped again.
                    all_stepping = time.monotonic() - killed
                    all_stepping_load = cpu_wait.seconds()
                    assert (info["tick"][MOVED] == 1).all()
        assert kept_ended >= 2 * len(KEPT)  # the kept environments' autoresets were compared
        print(
            f"\n[failover {mode.value} {step.__name__}] failover_after={FAILOVER_AFTER:g} s: "
            f"SIGKILL -> failover step returned {failover:.3f} s, -> all {N} environments "
            f"stepping on their servers {all_stepping:.3f} s (waited for a CPU: "
            f"{failover_load:.3f} s, {all_stepping_load:.3f} s)"
        )
        assert FAILOVER_AFTER <= failover < FAILOVER_AFTER + SLACK + failover_load
        assert all_stepping < FAILOVER_AFTER + SLACK + all_stepping_load

        # A seeded reset gives environment i the seed 50 + i wherever it lives now: all N
        # environments, the moved ones included, replay the reference's trajectories.
        a, b = envs.reset(seed=50), reference.reset(seed=50)
        assert_same_envs(a, b, range(N), "reset after the failover")
        for t in range(60):
            actions = np.where(rng.random(N) < 0.6, b[-1]["expert_action"], 0)
            a, b = step(envs, actions), reference.step(actions)
            assert_same_envs(a, b, range(N), f"step {t} after the reset")
        closing, cpu_wait = time.monotonic(), CpuWait.of(dinerdash_cluster)
        envs.close()
        assert time.monotonic() - closing < SLACK + cpu_wait.seconds()
    finally:
        envs.close()
        reference.close()


def test_a_server_lost_at_a_reset_moves_and_resets_its_environments(dinerdash_cluster) -> None:
    addresses = dinerdash_cluster.addresses
    reference = DinerDashVectorEnv(N, addresses[2], expert=True)
    envs = DinerDashVectorEnv(
        N, addresses, expert=True, reconnect=True, failover_after=FAILOVER_AFTER
    )
    try:
        envs.reset(seed=0)
        envs.step(np.zeros(N, dtype=np.int64))
        dinerdash_cluster.kill(0)  # environments 0..2 move to the other two
        a, b = envs.reset(seed=7), reference.reset(seed=7)
        np.testing.assert_array_equal(a[1]["seed"], 7 + np.arange(N))
        assert a[1]["_seed"].all()
        assert_same_envs(a, b, range(N), "reset")
        assert envs.lost_addresses == [addresses[0]]
        assert [sl for _, sl in envs.env_slices] == [
            slice(0, 2),  # 2 of 0..2 to the second server (both held 2)
            slice(2, 3),
            slice(3, 5),
            slice(5, 7),
        ]
        assert envs.addresses == [addresses[1], addresses[2]]
        for t in range(30):
            actions = b[-1]["expert_action"]
            a, b = envs.step(actions), reference.step(actions)
            assert_same_envs(a, b, range(N), f"step {t}")
        # A lost server that comes back is taken back: tests/test_membership.py.
    finally:
        envs.close()
        reference.close()


@pytest.mark.parametrize("step", [plain_step, async_step], ids=["step", "step_async"])
def test_two_lost_together_then_the_last_raises(dinerdash_cluster, step) -> None:
    addresses = dinerdash_cluster.addresses
    envs = DinerDashVectorEnv(
        6, addresses, reconnect=True, reconnect_timeout=1.0, failover_after=0.5
    )
    try:
        envs.reset(seed=0)
        step(envs, np.zeros(6, dtype=np.int64))
        dinerdash_cluster.kill(1)
        dinerdash_cluster.kill(2)
        _, _, _, truncated, info = step(envs, np.zeros(6, dtype=np.int64))
        lost = np.arange(6) >= 2
        np.testing.assert_array_equal(truncated, lost)
        np.testing.assert_array_equal(info["reconnected"], lost)
        assert envs.addresses == [addresses[0]]
        assert envs.lost_addresses == addresses[1:]
        for _ in range(3):
            _, _, _, truncated, info = step(envs, np.zeros(6, dtype=np.int64))
            assert "reconnected" not in info and not truncated.any()
        assert live_sessions(addresses[0]) == 3  # its own and one for each lost server

        dinerdash_cluster.kill(0)  # the last one: waited for reconnect_timeout, then NoServerLeft
        began, cpu_wait = time.monotonic(), CpuWait.of(dinerdash_cluster)
        with pytest.raises(NoServerLeft) as e:
            step(envs, np.zeros(6, dtype=np.int64))
        waited, load = time.monotonic() - began, cpu_wait.seconds()
        assert isinstance(e.value, ServiceTransportError)
        message = str(e.value)
        assert "no server left" in message and all(a in message for a in addresses)
        assert 1.0 <= waited < 1.0 + SLACK + load
        closing, cpu_wait = time.monotonic(), CpuWait.of(dinerdash_cluster)
        envs.close()
        assert time.monotonic() - closing < SLACK + cpu_wait.seconds()
    finally:
        envs.close()


def test_without_failover_a_lost_server_is_waited_for_and_raises(dinerdash_cluster) -> None:
    envs = DinerDashVectorEnv(
        N, dinerdash_cluster.addresses, reconnect=True, reconnect_timeout=1.0, failover_after=None
    )
    try:
        envs.reset(seed=0)
        dinerdash_cluster.kill(1)
        with pytest.raises(ServiceTransportError, match="could not reconnect") as e:
            envs.step(np.zeros(N, dtype=np.int64))
        assert not isinstance(e.value, NoServerLeft)
        assert envs.lost_addresses == []
    finally:
        envs.close()


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf")])
def test_failover_after_must_be_positive_seconds(dinerdash_server, bad) -> None:
    address = dinerdash_server
    with pytest.raises(ValueError, match="failover_after: expected a positive, finite number"):
        DinerDashVectorEnv(2, address, reconnect=True, failover_after=bad)
    with pytest.raises(ValueError, match="failover_after"):
        gymnasium.make_vec(
            "dinerdash:DinerDash-v0", num_envs=2, address=address, failover_after=bad
        )


@pytest.mark.parametrize("bad", ["10", True, [1.0]])
def test_failover_after_must_be_a_number(dinerdash_server, bad) -> None:
    with pytest.raises(TypeError, match="failover_after: expected a number of seconds or None"):
        DinerDashVectorEnv(2, dinerdash_server, reconnect=True, failover_after=bad)
