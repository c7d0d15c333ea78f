"""Issue 26: training that outlives its servers. A vector env over three real servers
(``reconnect=True``, ``failover_after``) gives up a server that hangs (SIGSTOP) within
``failover_after`` + 2 s, with the other environments' trajectories those of an undisturbed run;
takes back a lost server that returns and a DNS name's new replica, moving environments onto them
(by Snapshot and Restore, no episode cut) until the loads are even; and the single-server env
keeps its typed errors. Over each transport. (A black-holed network and a slow one, through a
TCP proxy: ``test_membership_proxy.py``.)

Time bounds: the wait the design allows (``failover_after``, the health checks' period) +
:data:`SLACK` (the issue's 2 s) + the time this process and the servers waited for a CPU over the
same interval (:class:`tests.cpu_wait.CpuWait`): on a quiet machine the issue's bound, on a
loaded one that bound plus what the load measurably took; a wait for the wrong timeout (the
call's 60 s, the reconnect's 30 s) still fails."""

from __future__ import annotations

import functools
import itertools
import subprocess
import time
from collections import Counter

import numpy as np
import pytest
from dinerdash import DinerDashVectorEnv, ServiceTimeout, ServiceTransportError
from dinerdash._fleet import PROBE_EVERY
from gymnasium.vector import AutoresetMode

from .cpu_wait import CpuWait
from .test_failover import assert_same_envs, live_sessions
from .trajectories import async_step, plain_step

N = 7  # slices of 3, 2 and 2: the middle server's environments 3..4 move
FAILOVER_AFTER = 1.5
#: The fixed part of the bounds beyond the design's waits (the issue's: failover_after + 2 s);
#: what load adds is measured (:class:`tests.cpu_wait.CpuWait`).
SLACK = 2.0
MOVED = np.array([False] * 3 + [True] * 2 + [False] * 2)
KEPT = np.flatnonzero(~MOVED)
CONFIG = {"lives": 2, "time_limit": 40}


#: dinerdash_cluster: three servers (dinerdash.testing's pytest plugin).
pytestmark = [pytest.mark.dinerdash_cluster(3), pytest.mark.usefixtures("each_transport")]


def make(addresses, **kwargs):
    kwargs = {"reconnect_timeout": 30, "failover_after": FAILOVER_AFTER, **kwargs}
    return DinerDashVectorEnv(N, addresses, expert=True, config=CONFIG, reconnect=True, **kwargs)


def actions_for(info: dict, rng: np.random.Generator) -> np.ndarray:
    return np.where(rng.random(N) < 0.6, info["expert_action"], rng.integers(0, 57, N))


def run_loss(
    envs, reference, lose, step, cluster, steps: int = 40, lose_at: int = 10
) -> tuple[float, float]:
    """Steps ``envs`` beside ``reference`` (the kept environments compared at every step), calls
    ``lose()`` before step ``lose_at`` and returns the seconds that step took, and the seconds
    this process and ``cluster``'s servers waited for a CPU meanwhile
    (:class:`~tests.cpu_wait.CpuWait`)."""
    rng = np.random.default_rng(5)
    a, b = envs.reset(seed=50), reference.reset(seed=50)
    assert_same_envs(a, b, range(N), "reset")
    took = None
    for t in range(steps):
        actions = actions_for(b[-1], rng)
        if t == lose_at:
            lose()
            began, cpu_wait = time.monotonic(), CpuWait.of(cluster)
        a, b = step(envs, actions), reference.step(actions)
        if t == lose_at:
            took, load = time.monotonic() - began, cpu_wait.seconds()
            np.testing.assert_array_equal(a[-1]["reconnected"], MOVED)
            assert a[3][MOVED].all()
        assert_same_envs(a, b, KEPT, f"step {t}")
    return took, load


@pytest.mark.parametrize("step", [plain_step, async_step], ids=["step", "step_async"])
def test_a_hung_server_is_given_up(dinerdash_cluster, step) -> None:
    s0, s1, s2 = dinerdash_cluster.addresses
    reference = DinerDashVectorEnv(N, s0, expert=True, config=CONFIG)
    envs = make([s0, s1, s2], timeout=60)
    try:
        hang = functools.partial(dinerdash_cluster.hang, 1)
        took, load = run_loss(envs, reference, hang, step, dinerdash_cluster)
        print(
            f"\n[hung server] failover_after={FAILOVER_AFTER:g} s: given up in {took:.3f} s "
            f"(waited for a CPU: {load:.3f} s)"
        )
        assert FAILOVER_AFTER <= took < FAILOVER_AFTER + SLACK + load
        assert envs.lost_addresses == [s1] and envs.addresses == [s0, s2]
        assert envs.failovers == 1
    finally:
        envs.close()
        reference.close()


def loads(envs) -> Counter:
    out: Counter = Counter()
    for address, sl in envs.env_slices:
        out[address] += sl.stop - sl.start
    return out


def check_uncut(before: tuple, after: tuple, mode: AutoresetMode, where: str, ignore=()) -> None:
    """No episode was cut between two steps (``before`` may be a reset's result): each
    environment's tick went on by one, or its episode ended (terminated, or truncated at the time
    limit) and the next one began."""
    info0, info1 = before[-1], after[-1]
    done0 = before[2] | before[3] if len(before) == 5 else np.zeros(N, np.bool_)  # a reset
    for i in range(N):
        if i in ignore:
            continue
        if mode == AutoresetMode.NEXT_STEP:
            if done0[i]:
                assert info1["_seed"][i] and info1["tick"][i] == 0, f"{where}, env {i}"
                continue
            started = info0["tick"][i]
        else:
            started = info0["tick"][i]
            if after[2][i] or after[3][i]:
                assert info1["final_info"]["tick"][i] == started + 1, f"{where}, env {i}"
                assert info1["tick"][i] == 0, f"{where}, env {i}"
                continue
        assert info1["tick"][i] == started + 1, f"{where}, env {i}"
    truncated = after[3]
    if not truncated.any():
        return
    ticks = info1["final_info"]["tick"] if mode == AutoresetMode.SAME_STEP else info1["tick"]
    for i in np.flatnonzero(truncated):
        if i not in ignore:
            assert ticks[i] == CONFIG["time_limit"], f"{where}, env {i} truncated early"


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_lost_server_that_returns_is_taken_back(dinerdash_cluster, mode) -> None:
    addresses = dinerdash_cluster.addresses
    envs = make(addresses, autoreset_mode=mode, failover_after=1.0)
    try:
        rng = np.random.default_rng(9)
        before = envs.reset(seed=0)
        dinerdash_cluster.kill(1)
        rejoined = balanced = None
        deadline = time.monotonic() + 60
        # Bounded by time, not steps: over shared memory 10,000 steps take under a second, less
        # than the first health check of the given-up server waits.
        for t in itertools.count():
            assert time.monotonic() < deadline, f"not even again after {t} steps: {loads(envs)}"
            after = envs.step(actions_for(before[-1], rng))
            if t == 0:
                assert after[-1]["reconnected"][MOVED].all() and envs.failovers == 1
                dinerdash_cluster.restart(1)
                restarted, cpu_wait = time.monotonic(), CpuWait.of(dinerdash_cluster)
            else:
                assert "reconnected" not in after[-1], f"step {t}: an episode was cut"
                check_uncut(before, after, mode, f"step {t}")
            if rejoined is None and envs.rejoins:
                rejoined, took, load = t, time.monotonic() - restarted, cpu_wait.seconds()
                assert envs.lost_addresses == []
            if (
                rejoined is not None
                and max(loads(envs).values()) - min(loads(envs).values()) <= 1
                and len(loads(envs)) == 3
            ):
                balanced = t
                break
            before = after
        print(
            f"\n[rejoin {mode.value}] taken back at step {rejoined}, {took:.3f} s after the "
            f"restart (waited for a CPU: {load:.3f} s); loads even at step {balanced} after "
            f"{envs.moves} moves: {dict(loads(envs))}"
        )
        # At the next round of health checks (one a second): each waits for the returning
        # server's channel to reconnect, which it drives while it waits.
        assert took < PROBE_EVERY + SLACK + load
        assert envs.rejoins == 1 and envs.moves >= 2
        assert sorted(loads(envs).values()) == [2, 2, 3]
        # The sessions the failover opened moved back whole: no session keeps an unused slot.
        assert sum(live_sessions(a) for a in envs.addresses) == len(envs.env_slices)
    finally:
        envs.close()


def test_a_dns_name_that_grows_is_followed(dinerdash_cluster, monkeypatch) -> None:
    """``replicas.test`` first answers two servers, then three: the third is taken in."""
    from dinerdash import connection

    s0, s1, s2 = dinerdash_cluster.addresses
    answer = [s0, s1]
    resolve = connection.resolve_replicas

    def resolver(address):
        if address == "replicas.test:50051":
            return list(answer)
        return resolve(address)

    monkeypatch.setattr(connection, "resolve_replicas", resolver)
    envs = DinerDashVectorEnv(
        6, "replicas.test:50051", reconnect=True, failover_after=1.0, resolve_every=0.2
    )
    try:
        assert envs.addresses == answer
        envs.reset(seed=0)
        answer.append(s2)
        deadline = time.monotonic() + 60
        while sorted(loads(envs).values()) != [2, 2, 2]:
            assert time.monotonic() < deadline, f"not even: {loads(envs)}"
            _, _, _, _, info = envs.step(np.zeros(6, dtype=np.int64))
            assert "reconnected" not in info
        assert envs.rejoins == 1 and envs.failovers == 0 and envs.lost_addresses == []
    finally:
        envs.close()


@pytest.mark.dinerdash_cluster(2)
def test_one_server_keeps_its_typed_errors(dinerdash_cluster) -> None:
    """A single server lost: waited for ``reconnect_timeout``, then an error naming it and the
    time waited; a single hung server: the call's deadline, naming it."""
    lost, hung = dinerdash_cluster.addresses
    envs = DinerDashVectorEnv(3, lost, reconnect=True, reconnect_timeout=1.0)
    try:
        envs.reset(seed=0)
        dinerdash_cluster.kill(0)
        with pytest.raises(ServiceTransportError, match="within 1 s") as e:
            envs.step(np.zeros(3, dtype=np.int64))
        assert lost in str(e.value)
    finally:
        envs.close()
    envs = DinerDashVectorEnv(3, hung, reconnect=True, timeout=1.0)
    try:
        envs.reset(seed=0)
        dinerdash_cluster.hang(1)
        with pytest.raises(ServiceTimeout, match="within 1 s") as e:
            envs.step(np.zeros(3, dtype=np.int64))
        assert hung in str(e.value)
    finally:
        dinerdash_cluster.resume(1)
        envs.close()


def _drains() -> bool:
    """The server binary drains on SIGTERM (``--drain-timeout``, issue 26 part 3)."""
    from dinerdash.server import find_server_binary

    out = subprocess.run(
        [str(find_server_binary(None)), "--help"], capture_output=True, text=True, timeout=30
    )
    return "--drain-timeout" in out.stdout


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_rolling_restart_cuts_no_episode(dinerdash_cluster_factory, mode) -> None:
    """Each server in turn drains (SIGTERM), exits once the env has moved every environment off
    it (at once, by Snapshot and Restore), and is started again on its port; the env takes it
    back and moves environments onto it. No episode is cut, none is lost (that every step is the
    undisturbed run's: ``test_moves.py``)."""
    if not _drains():
        pytest.skip("this dinerdash-server does not drain on SIGTERM (no --drain-timeout)")
    cluster = dinerdash_cluster_factory(3, drain_timeout=20)
    addresses = cluster.addresses
    envs = make(addresses, autoreset_mode=mode, failover_after=2.0)
    rng = np.random.default_rng(4)
    steps = 0

    def step_until(done, what: str) -> None:
        nonlocal before, steps
        deadline = time.monotonic() + 60
        while not done():
            assert time.monotonic() < deadline, f"{what}: not within 60 s ({envs.env_slices})"
            after = envs.step(actions_for(before[-1], rng))
            assert "reconnected" not in after[-1], f"step {steps}: an episode was cut"
            check_uncut(before, after, mode, f"step {steps}")
            before, steps = after, steps + 1

    try:
        before = envs.reset(seed=0)
        for i, address in enumerate(addresses):
            cluster.drain(i)
            step_until(lambda: not cluster.is_running(i), f"server {i} drained")  # noqa: B023
            assert address not in envs.addresses and address in envs.lost_addresses
            cluster.restart(i)

            def even() -> bool:
                counts = loads(envs)
                return len(counts) == 3 and max(counts.values()) - min(counts.values()) <= 1

            step_until(even, f"server {i} taken back")
        print(
            f"\n[rolling restart {mode.value}] {steps} steps, {envs.moves} moves, "
            f"{envs.rejoins} rejoins, {envs.failovers} failovers, no episode cut"
        )
        assert envs.failovers == 0 and envs.rejoins == 3 and envs.lost_addresses == []
        assert envs.moves >= N  # every environment left its first server when it drained
    finally:
        envs.close()


def test_a_drain_moves_episodes_longer_than_it_whole(dinerdash_cluster_factory) -> None:
    """Episodes far longer than the drain (3 s): the draining server's environments move at the
    first step after its SIGTERM, by Snapshot and Restore, none cut (no ``reconnected``, no
    truncation), and the server exits with no session left, well before its deadline."""
    if not _drains():
        pytest.skip("this dinerdash-server does not drain on SIGTERM (no --drain-timeout)")
    cluster = dinerdash_cluster_factory(2, drain_timeout=3)
    envs = DinerDashVectorEnv(
        4, cluster.addresses, config={"time_limit": 5000}, reconnect=True, failover_after=2.0
    )
    try:
        envs.reset(seed=0)
        cluster.drain(0)
        deadline = time.monotonic() + 30
        while cluster.is_running(0):
            assert time.monotonic() < deadline, f"server 0 still runs: {envs.env_slices}"
            _, _, terminated, truncated, info = envs.step(np.zeros(4, dtype=np.int64))
            assert "reconnected" not in info and not truncated.any()
            time.sleep(0.01)
        assert cluster.wait(0, 0) == 0
        _, _, _, truncated, info = envs.step(np.zeros(4, dtype=np.int64))
        assert "reconnected" not in info and not truncated.any()
        assert envs.failovers == 0 and envs.moves == 2  # server 0 held environments 0 and 1
        assert envs.addresses == [cluster.address(1)]
    finally:
        envs.close()
