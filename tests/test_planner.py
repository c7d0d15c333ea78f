"""The look-ahead planner through the client: ``expert="planner"`` in ``gymnasium.make`` and
``make_vec``, ``rollout("planner")``, and ``python -m dinerdash evaluate|collect --policy
planner``."""

from __future__ import annotations

from pathlib import Path

import dinerdash
import gymnasium
import numpy as np
import pytest

from .test_rollout_cli import run_cli

STEPS = 120  # planner episodes last hundreds of steps: these never end early


def test_env_with_planner_expert_plays_the_planner_rollout(address: str) -> None:
    (episode,) = dinerdash.rollout("planner", seeds=[7], address=address, max_steps=STEPS)
    assert episode.steps == STEPS
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address, expert="planner")
    try:
        _, info = env.reset(seed=7)
        actions = []
        for _ in range(STEPS):
            action = int(info["expert_action"])
            assert info["action_mask"][action]
            actions.append(action)
            _, _, terminated, truncated, info = env.step(action)
            assert not (terminated or truncated)
        np.testing.assert_array_equal(actions, episode.actions)
        assert info["score"] == episode.score
    finally:
        env.close()


def test_make_vec_with_planner_expert(address: str) -> None:
    episodes = list(dinerdash.rollout("planner", seeds=[3, 4], address=address, max_steps=STEPS))
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0", num_envs=2, address=address, expert="planner"
    )
    try:
        _, infos = envs.reset(seed=3)
        actions = []
        for _ in range(STEPS):
            actions.append(infos["expert_action"].copy())
            _, _, terminated, truncated, infos = envs.step(infos["expert_action"])
            assert not (terminated | truncated).any()
        actions = np.stack(actions, axis=1)
        for i, ep in enumerate(episodes):
            np.testing.assert_array_equal(actions[i], ep.actions)
    finally:
        envs.close()


def test_expert_must_be_a_bool_or_an_expert_name(address: str) -> None:
    with pytest.raises(ValueError, match="expert must be a bool or one of"):
        dinerdash.DinerDashEnv(address, expert="random")


def test_cli_evaluate_and_collect_with_the_planner(address: str, tmp_path: Path) -> None:
    for via in ("env", "rollout"):
        out = run_cli(
            "evaluate",
            "--policy",
            "planner",
            "--episodes",
            "2",
            "--max-steps",
            "150",
            "--via",
            via,
            "--address",
            address,
        )
        assert "policy planner: 2 episodes" in out, out
    out = run_cli(
        "collect",
        "--policy",
        "planner",
        "--episodes",
        "2",
        "--max-steps",
        "100",
        "--out",
        str(tmp_path),
        "--address",
        address,
    )
    assert "2 episodes" in out
    data = np.load(tmp_path / "dinerdash_planner.npz")
    assert data["actions"].shape == (200,)
    assert data["action_masks"][np.arange(200), data["actions"]].all()
    (episode,) = dinerdash.rollout("planner", seeds=[0], address=address, max_steps=100)
    np.testing.assert_array_equal(data["actions"][:100], episode.actions)
