"""``dinerdash.ray`` on a two-node Ray cluster simulated on this machine (``ray.cluster_utils``,
one CPU per node, no dashboard, every address 127.0.0.1): servers placed on both nodes, RLlib's
EnvRunners each stepping one batched session, masked PPO that learns, and a dead server that
comes back on its port.

One cluster and one pool of servers serve the whole module (starting them costs about 20 s of
the module's wall time); the training runs once, in :func:`trained`. Skipped when Ray (the
``dinerdash[ray]`` extra) is not installed.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest

# Before Ray is imported: Ray then takes 127.0.0.1 as every node's address (by default it takes
# the machine's outward address), so the servers listen on loopback only.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

ray = pytest.importorskip("ray")
torch = pytest.importorskip("torch")
pytest.importorskip("ray.rllib")

from dinerdash import DinerDashVectorEnv  # noqa: E402
from dinerdash.connection import Connection  # noqa: E402
from dinerdash.evaluation import evaluate_through_env, play_seeded  # noqa: E402
from dinerdash.ray import masked_ppo, start_servers  # noqa: E402
from dinerdash.testing import wait_stopped  # noqa: E402
from ray.cluster_utils import Cluster  # noqa: E402

from .conftest import server_binary  # noqa: E402

#: PPO iterations of the short run (4096 environment steps each with masked_ppo's defaults).
TRAIN_ITERATIONS = 5
#: Unseen evaluation seeds (the agents' EVAL_SEED), episodes played greedily.
EVAL_SEED = 1000
EVAL_EPISODES = 32


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    # The raylets and their workers inherit this process's environment: the binary, and no
    # developer's token or address.
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DINERDASH_SERVER", str(server_binary()))
        for key in ("DINERDASH_ADDRESS", "DINERDASH_AUTH_TOKEN", "DINERDASH_TIMEOUT"):
            mp.delenv(key, raising=False)
        cluster = Cluster(
            initialize_head=True,
            head_node_args={
                "num_cpus": 1,
                "include_dashboard": False,
                "node_ip_address": "127.0.0.1",
            },
        )
        try:
            cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
            ray.init(address=cluster.address, log_to_driver=False)
            yield cluster
        finally:
            ray.shutdown()
            cluster.shutdown()


@pytest.fixture(scope="module")
def pool(cluster: Cluster):
    with start_servers() as servers:
        yield servers


def _live_sessions(address: str) -> int:
    with Connection(address) as conn:
        return conn.server_info().live_sessions


@pytest.fixture(scope="module")
def trained(pool) -> SimpleNamespace:
    """``masked_ppo(pool.addresses)`` built, its sessions counted, trained for
    :data:`TRAIN_ITERATIONS` iterations; the EnvRunners' servers and steps, the results and
    the trained module. The algorithm is stopped before the tests look at it."""
    sessions_before = [_live_sessions(a) for a in pool.addresses]
    algo = masked_ppo(pool.addresses).debugging(seed=0).build_algo()
    try:
        sessions = [_live_sessions(a) for a in pool.addresses]
        results = [algo.train() for _ in range(TRAIN_ITERATIONS)]
        runners = algo.env_runner_group.foreach_env_runner(
            lambda r: (
                r.worker_index,
                r.env.unwrapped.addresses if r.env is not None else [],
                r.num_env_steps_sampled_lifetime,
            ),
            local_env_runner=False,
        )
        module = algo.get_module()
    finally:
        algo.stop()
    return SimpleNamespace(
        sessions_before=sessions_before,
        sessions=sessions,
        results=results,
        runners=sorted(runners),
        module=module,
    )


def test_two_servers_land_on_the_two_nodes(pool, cluster: Cluster) -> None:
    nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"]}
    assert len(nodes) == 2
    assert len(pool.addresses) == 2
    assert set(pool.node_ids) == nodes
    assert ray.get([a.node_id.remote() for a in pool.actors]) == pool.node_ids
    for address in pool.addresses:
        host, port = address.rsplit(":", 1)
        assert host == "127.0.0.1" and int(port) > 0
        with Connection(address) as conn:
            assert conn.server_info().ruleset == "v0"


def test_each_env_runner_steps_one_batched_session_on_its_own_server(
    trained: SimpleNamespace, pool
) -> None:
    # One session per EnvRunner, on its server: nothing before the build, one each after.
    assert trained.sessions_before == [0, 0]
    assert trained.sessions == [1, 1]
    # EnvRunner 1 holds the first server, EnvRunner 2 the second; both sampled.
    assert [(w, addrs) for w, addrs, _ in trained.runners] == [
        (1, [pool.addresses[0]]),
        (2, [pool.addresses[1]]),
    ]
    for _, _, steps in trained.runners:
        assert steps >= TRAIN_ITERATIONS * 64 * 32


def test_train_iterations_run(trained: SimpleNamespace) -> None:
    sampled = [r["env_runners"]["num_env_steps_sampled_lifetime"] for r in trained.results]
    # 2 EnvRunners x 64 environments x 32 steps per iteration (the last fragment may run over).
    assert all(b - a >= 4096 for a, b in zip([0, *sampled], sampled, strict=False))
    for result in trained.results[:3]:
        learner = result["learners"]["default_policy"]
        assert np.isfinite(learner["total_loss"]) and np.isfinite(learner["vf_loss"])
        assert learner["entropy"] > 0


def _greedy(module):
    def act(obs: np.ndarray, info: dict) -> np.ndarray:
        batch = {
            "obs": {
                "observations": torch.as_tensor(obs),
                "action_mask": torch.as_tensor(info["action_mask"], dtype=torch.float32),
            }
        }
        with torch.no_grad():
            logits = module.forward_inference(batch)["action_dist_inputs"]
        return logits.argmax(-1).numpy()

    return act


def test_masked_ppo_beats_random_play_on_unseen_seeds(trained: SimpleNamespace, pool) -> None:
    envs = DinerDashVectorEnv(EVAL_EPISODES, pool.addresses)
    rng = np.random.default_rng(0)

    def random_legal(obs: np.ndarray, info: dict) -> np.ndarray:
        return np.array([rng.choice(np.flatnonzero(m)) for m in info["action_mask"]])

    try:
        play = dict(episodes=EVAL_EPISODES, seed=EVAL_SEED, max_steps=20_000)
        trained_scores, _ = play_seeded(envs, _greedy(trained.module), **play)
        legal_scores, _ = play_seeded(envs, random_legal, **play)
    finally:
        envs.close()
    random_scores, _ = evaluate_through_env(
        "random", EVAL_EPISODES, seed=EVAL_SEED, address=pool.addresses
    )
    # Random play over all 57 actions loses its groups fast (about -1,200); random legal play
    # (what the untrained masked policy samples) about 4,000; after 20,000 steps the greedy
    # policy scores about 7,000.
    means = (trained_scores.mean(), legal_scores.mean(), random_scores.mean())
    print(f"greedy masked PPO {means[0]:.0f}, random legal {means[1]:.0f}, random {means[2]:.0f}")
    assert trained_scores.mean() > max(random_scores.mean(), 0) + 3000, means
    assert trained_scores.mean() > legal_scores.mean() + 1000, means


def _gone(pid: int) -> bool:
    """The process has exited (a zombie counts: its parent may be gone, with nobody to reap
    it)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] == "Z"
    except (FileNotFoundError, ProcessLookupError):
        # Reaped before the open, or between the open and the read (ESRCH).
        return True


def test_a_dead_server_comes_back_on_its_port(pool) -> None:
    """Killing a server's process, then another server's actor: Ray restarts the actor, which
    starts the server on the same port, and a ``reconnect=True`` env steps on."""
    for i, kill in enumerate(("process", "actor")):
        address = pool.addresses[i]
        envs = DinerDashVectorEnv(4, address, reconnect=True, reconnect_timeout=60)
        try:
            envs.reset(seed=0)
            envs.step(np.zeros(4, dtype=np.int64))
            pid = pool.pids()[i]
            if kill == "process":
                os.kill(pid, signal.SIGKILL)
            else:
                ray.kill(pool.actors[i], no_restart=False)  # asynchronous
            deadline = time.monotonic() + 30
            while not _gone(pid):
                assert time.monotonic() < deadline, f"server {i} still runs after its {kill} died"
                time.sleep(0.05)
            # The next step waits for the server, then reports the episodes as lost.
            _, _, _, truncated, info = envs.step(np.zeros(4, dtype=np.int64))
            assert info["reconnected"].all() and truncated.all()
            assert envs.addresses == [address]
            envs.step(np.zeros(4, dtype=np.int64))
        finally:
            envs.close()
        deadline = time.monotonic() + 30
        while pool.pids()[i] == pid:  # the restarted actor reports its new server
            assert time.monotonic() < deadline, f"server {i} not restarted after its {kill} died"
            time.sleep(0.2)
        assert pool.addresses[i] == address
        assert _live_sessions(address) == 0


def test_a_server_ray_restarts_is_taken_back(pool) -> None:
    """An EnvRunner's env over both servers (what ``make_env`` builds for a runner whose share
    is both): the first server's process stops answering, its environments move to the second
    after ``failover_after``; the process is then killed, Ray restarts the server on its port, and
    the env takes it back and moves environments onto it (Snapshot, Restore) until each server
    holds two. (The process is stopped before it is killed because Ray can restart a killed
    server in less than ``failover_after``: the env would then just reconnect, losing nothing.)"""
    from dinerdash.ray.rllib import make_env

    envs = make_env(
        {
            "address": pool.addresses,
            "num_envs": 4,
            "reconnect": True,
            "failover_after": 1.0,
            "mask_observation": False,
        }
    )
    try:
        envs.reset(seed=0)
        pid = pool.pids()[0]
        os.kill(pid, signal.SIGSTOP)
        wait_stopped(pid)  # else its shared-memory thread may still answer the Step
        _, _, _, _, info = envs.step(np.zeros(4, dtype=np.int64))
        assert info["reconnected"][:2].all() and envs.lost_addresses == [pool.addresses[0]]
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 60
        while envs.rejoins == 0 or len(envs.addresses) < 2:
            assert time.monotonic() < deadline, f"not taken back: {envs.env_slices}"
            _, _, _, _, info = envs.step(np.zeros(4, dtype=np.int64))
            assert "reconnected" not in info
        assert envs.lost_addresses == [] and envs.failovers == 1
        assert sorted(envs.addresses) == sorted(pool.addresses)
    finally:
        envs.close()
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)  # still stopped if an assertion above failed
