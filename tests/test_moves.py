"""Issue 47: a vector env moves its environments between servers by Snapshot and Restore, at once
and between two steps, so that a planned restart, a drain or a server added changes nothing a
trainer sees. Three real servers (``dinerdash.testing.LocalCluster``), each SIGTERMed and started
again on its port in turn, then a fourth added: every step is the undisturbed run's (observations,
rewards, flags, every info key, ``final_obs``/``final_info`` included), in both autoreset modes
and over each transport, and each drained server exits within seconds of its SIGTERM. Also: a
Snapshot of a range of a session's environments, and a Restore refused for its snapshot version
(a rolling upgrade), whose environments start new episodes with one warning."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from dinerdash import Connection, DinerDashVectorEnv, InvalidArgument, connection
from dinerdash._proto import pb
from gymnasium.vector import AutoresetMode

from .trajectories import assert_same

N = 30
SEED = 500
CONFIG = {"lives": 2, "time_limit": 40}
#: Longest a phase of the run may take (a loaded CI included); the steps are not timed.
PATIENCE_S = 90.0
#: Longest a drained server may take to exit after its SIGTERM: the env moves its sessions at
#: the first step after it, and the server exits once its last session is closed. Generous: the
#: drain's own deadline (--drain-timeout) is 60 s, far beyond it.
EXIT_AFTER_SIGTERM_S = 15.0
DNS = "replicas.test:50051"


def legal_actions(info: dict, rng: np.random.Generator) -> np.ndarray:
    """One legal action per environment, uniformly among its legal ones."""
    return np.argmax(rng.random((N, 57)) * info["action_mask"], axis=1)


def same(a: tuple, b: tuple, where: str) -> None:
    try:
        assert_same([a], [b])
    except AssertionError as e:
        raise AssertionError(f"{where}: {e}") from None


def loads(envs) -> dict[str, int]:
    out: dict[str, int] = {}
    for address, sl in envs.env_slices:
        out[address] = out.get(address, 0) + sl.stop - sl.start
    return out


def even(envs, servers: int) -> bool:
    counts = loads(envs)
    return len(counts) == servers and max(counts.values()) - min(counts.values()) <= 1


@pytest.mark.usefixtures("each_transport")
@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_rolling_restart_and_a_new_server_change_nothing(
    dinerdash_cluster_factory, start_server, monkeypatch, mode
) -> None:
    cluster = dinerdash_cluster_factory(3, drain_timeout=60)
    answer = list(cluster.addresses)  # what the DNS name resolves to
    resolve = connection.resolve_replicas
    monkeypatch.setattr(
        connection, "resolve_replicas", lambda a: list(answer) if a == DNS else resolve(a)
    )
    kwargs = {"autoreset_mode": mode, "config": CONFIG}
    reference = DinerDashVectorEnv(N, start_server().address, **kwargs)
    envs = DinerDashVectorEnv(
        N, DNS, reconnect=True, failover_after=30.0, resolve_every=0.2, **kwargs
    )
    rng = np.random.default_rng(SEED)
    steps = 0
    ended = 0

    def step_until(done, what: str) -> None:
        nonlocal b, steps, ended
        deadline = time.monotonic() + PATIENCE_S
        while not done():
            assert time.monotonic() < deadline, f"{what}: not within {PATIENCE_S:g} s"
            actions = legal_actions(b[-1], rng)
            a, b = envs.step(actions), reference.step(actions)
            same(a, b, f"step {steps} ({what})")
            ended += int((b[2] | b[3]).sum())
            steps += 1

    try:
        a, b = envs.reset(seed=SEED), reference.reset(seed=SEED)
        same(a, b, "reset")
        step_until(lambda: steps >= 20, "before the restarts")
        exits = []
        for i, address in enumerate(cluster.addresses):
            cluster.drain(i)
            signalled = time.monotonic()
            step_until(lambda: not cluster.is_running(i), f"server {i} drains")  # noqa: B023
            exits.append(time.monotonic() - signalled)
            assert cluster.wait(i, 0) == 0, f"server {i} did not exit cleanly"
            assert address not in envs.addresses
            cluster.restart(i)
            step_until(lambda: even(envs, 3), f"server {i} taken back")
        answer.append(cluster.address(cluster.add()))
        step_until(lambda: even(envs, 4), "a fourth server added")
        then = steps
        step_until(lambda: steps >= then + 20, "after")
        print(
            f"\n[moves {mode.value}] {steps} steps, {ended} episode ends, {envs.moves} moves, "
            f"drained servers exited {', '.join(f'{s:.2f}' for s in exits)} s after SIGTERM"
        )
        assert max(exits) <= EXIT_AFTER_SIGTERM_S, exits
        assert ended > 0  # autoresets (and final_obs in SAME_STEP) were compared too
        assert envs.failovers == 0 and envs.rejoins == 4 and envs.lost_addresses == []
        assert envs.moves >= N  # every environment left its first server
        for address in envs.addresses:  # one session per slice, none left behind
            with Connection(address) as conn:
                held = sum(1 for a, _ in envs.env_slices if a == address)
                assert conn.server_info().live_sessions == held
    finally:
        envs.close()
        reference.close()


def test_a_range_of_a_session_snapshots_and_restores_as_a_session_of_its_own(address) -> None:
    """``SnapshotRequest.env_start``/``env_count``: the restored session is those environments
    alone, each exactly as it was; a range outside the session is INVALID_ARGUMENT."""
    with Connection(address) as conn:
        made = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=5))
        whole = made.session_id
        conn.call("Reset", pb.ResetRequest(session_id=whole, seed=SEED))
        actions = np.arange(5, dtype="<i4")
        conn.call("Step", pb.StepRequest(session_id=whole, actions=actions.tobytes()))
        request = pb.SnapshotRequest(session_id=whole, env_start=1, env_count=3)
        part = conn.call(
            "Restore", pb.RestoreRequest(snapshot=conn.call("Snapshot", request).snapshot)
        )
        assert part.spec.num_envs == 3
        for t in range(60):
            actions = np.random.default_rng(t).integers(0, 57, 5).astype("<i4")
            a = conn.call("Step", pb.StepRequest(session_id=whole, actions=actions.tobytes()))
            b = conn.call(
                "Step", pb.StepRequest(session_id=part.session_id, actions=actions[1:4].tobytes())
            )
            assert b.observations == a.observations[40:160], f"step {t}"
            assert b.rewards == a.rewards[4:16] and b.ticks == a.ticks[4:16], f"step {t}"
        for start, count in [(5, 0), (4, 2), (0, 6)]:
            bad = pb.SnapshotRequest(session_id=whole, env_start=start, env_count=count)
            with pytest.raises(InvalidArgument, match="snapshot range"):
                conn.call("Snapshot", bad)
        tail = pb.SnapshotRequest(session_id=whole, env_start=3)  # env_count 0: to the end
        restored = conn.call(
            "Restore", pb.RestoreRequest(snapshot=conn.call("Snapshot", tail).snapshot)
        )
        assert restored.spec.num_envs == 2


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_restore_refused_for_its_version_starts_new_episodes_once_warned(
    dinerdash_cluster_factory, start_server, monkeypatch, caplog, mode
) -> None:
    """A rolling upgrade: the server left reads another snapshot version, and refuses the
    draining server's snapshots (played here by the version field of the snapshots the client
    carries, rewritten; the refusal is the real server's). The environments moved start new
    episodes there: this step ends theirs truncated (keeping its rewards), with
    ``info["reconnected"]``, and one warning says why; the other environments go on exactly."""
    cluster = dinerdash_cluster_factory(2, drain_timeout=60)
    kwargs = {"autoreset_mode": mode, "config": CONFIG}
    reference = DinerDashVectorEnv(N, start_server().address, **kwargs)
    envs = DinerDashVectorEnv(N, cluster.addresses, reconnect=True, failover_after=30.0, **kwargs)
    call = connection.Connection.call

    def other_version(self, method, request, **kw):
        reply = call(self, method, request, **kw)
        if method == "Snapshot":
            data = bytearray(reply.snapshot)
            data[4] ^= 0x40  # the little-endian u16 format version after the 4-byte kind tag
            reply = pb.SnapshotResponse(snapshot=bytes(data))
        return reply

    rng = np.random.default_rng(SEED)
    moved = np.arange(N) < N // 2  # server 0's slice
    try:
        a, b = envs.reset(seed=SEED), reference.reset(seed=SEED)
        for t in range(10):
            actions = legal_actions(b[-1], rng)
            a, b = envs.step(actions), reference.step(actions)
            same(a, b, f"step {t}")
        monkeypatch.setattr(connection.Connection, "call", other_version)
        caplog.set_level(logging.WARNING, logger="dinerdash")
        cluster.drain(0)
        deadline = time.monotonic() + PATIENCE_S
        while "reconnected" not in a[-1]:
            assert time.monotonic() < deadline, "the drained server's environments never moved"
            actions = legal_actions(b[-1], rng)
            a, b = envs.step(actions), reference.step(actions)
            if "reconnected" not in a[-1]:
                same(a, b, "before the move")
        obs, rewards, terminated, truncated, info = a
        np.testing.assert_array_equal(info["reconnected"], moved)
        np.testing.assert_array_equal(truncated[moved], ~b[2][moved])
        np.testing.assert_array_equal(rewards, b[1])  # this step's rewards are kept
        kept = ~moved
        np.testing.assert_array_equal(obs[kept], b[0][kept])
        warned = [r for r in caplog.records if "snapshot version" in r.getMessage()]
        assert len(warned) == 1, [r.getMessage() for r in caplog.records]
        assert envs.moves == 0 and envs.addresses == [cluster.address(1)]
        cluster.wait(0, EXIT_AFTER_SIGTERM_S)
        for t in range(40):  # the new episodes go on; the kept environments as before
            actions = legal_actions(b[-1], rng)
            a, b = envs.step(actions), reference.step(actions)
            assert "reconnected" not in a[-1]
            np.testing.assert_array_equal(a[0][kept], b[0][kept], err_msg=f"step {t}")
        assert len([r for r in caplog.records if "snapshot version" in r.getMessage()]) == 1
    finally:
        envs.close()
        reference.close()
