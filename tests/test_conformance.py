"""Trajectories recorded from the reference simulator (tests/data/conformance) replay exactly
through the client: observations, rewards, terminations, score, lost and the expert's choices."""

from __future__ import annotations

import json

import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv


def load(files):
    episodes = []
    for path in files:
        for n, line in enumerate(path.read_text().splitlines()):
            if line.strip():
                episodes.append((f"{path.name}:{n + 1}", json.loads(line)))
    assert episodes
    return episodes


@pytest.mark.parametrize("transport", ["grpc", "shm"])
def test_every_recorded_episode_replays_through_the_env(
    address: str, conformance_files, transport: str
) -> None:
    env = DinerDashEnv(address, expert=True, transport=transport)
    replayed = 0
    try:
        for where, ep in load(conformance_files):
            obs, info = env.reset(seed=ep["seed"])
            assert obs.tolist() == ep["reset_obs"], f"{where}: reset observation"
            assert info["seed"] == ep["seed"]
            for i, step in enumerate(ep["steps"]):
                # The record's expert_action is the choice in the state before the step, i.e.
                # the one the client reported with the previous observation.
                assert info["expert_action"] == step["expert_action"], f"{where} step {i}: expert"
                obs, reward, terminated, truncated, info = env.step(step["action"])
                at = f"{where} step {i} (action {step['action']})"
                assert obs.tolist() == step["obs"], f"{at}: observation"
                assert reward == step["reward"], f"{at}: reward"
                assert terminated == step["terminated"], f"{at}: terminated"
                assert not truncated, at
                assert info["score"] == step["score"], f"{at}: score"
                assert info["lost"] == step["lost"], f"{at}: lost"
                assert info["tick"] == i + 1
                replayed += 1
    finally:
        env.close()
    assert replayed > 1000


@pytest.mark.parametrize("transport", ["grpc", "shm"])
def test_every_recorded_episode_replays_through_one_vector_env(
    address: str, conformance_files, transport: str
) -> None:
    episodes = [ep for _, ep in load(conformance_files)]
    n = len(episodes)
    envs = DinerDashVectorEnv(n, address, expert=True, transport=transport)
    try:
        obs, info = envs.reset(seed=[ep["seed"] for ep in episodes])
        np.testing.assert_array_equal(obs, [ep["reset_obs"] for ep in episodes])
        longest = max(len(ep["steps"]) for ep in episodes)
        for t in range(longest):
            live = [i for i, ep in enumerate(episodes) if t < len(ep["steps"])]
            want = [episodes[i]["steps"][t] for i in live]
            np.testing.assert_array_equal(
                info["expert_action"][live], [s["expert_action"] for s in want]
            )
            actions = np.zeros(n, dtype=np.int64)
            actions[live] = [s["action"] for s in want]
            obs, reward, terminated, _, info = envs.step(actions)
            np.testing.assert_array_equal(obs[live], [s["obs"] for s in want], err_msg=f"step {t}")
            np.testing.assert_array_equal(reward[live], [s["reward"] for s in want])
            np.testing.assert_array_equal(terminated[live], [s["terminated"] for s in want])
            np.testing.assert_array_equal(info["score"][live], [s["score"] for s in want])
            np.testing.assert_array_equal(info["lost"][live], [s["lost"] for s in want])
    finally:
        envs.close()
