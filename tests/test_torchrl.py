"""TorchRL as a client (``pip install 'dinerdash[torchrl]'``): its ``check_env_specs`` and a
rollout across episode ends, for ``GymEnv("dinerdash:DinerDash-v0")`` and for ``GymWrapper``
over ``gymnasium.make_vec(..., autoreset_mode=SAME_STEP)`` (TorchRL refuses NEXT_STEP vector
envs by design). TorchRL reads the info keys once, so every step's info must have reset's keys
(``seed`` included) in dtypes torch handles."""

from __future__ import annotations

import dinerdash  # noqa: F401  (registers DinerDash-v0)
import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

torch = pytest.importorskip("torch")
torchrl_envs = pytest.importorskip("torchrl.envs")
check_env_specs = pytest.importorskip("torchrl.envs.utils").check_env_specs

#: Short episodes (truncated), so that a rollout of STEPS crosses several ends.
EPISODE = 40
STEPS = 3 * EPISODE + 10


def test_gym_env_passes_check_env_specs_and_rolls_across_episode_ends(address: str) -> None:
    env = torchrl_envs.GymEnv("dinerdash:DinerDash-v0", address=address, max_episode_steps=EPISODE)
    try:
        check_env_specs(env)
        env.set_seed(5)
        td = env.rollout(STEPS, break_when_any_done=False)
        assert td.batch_size == torch.Size([STEPS])
        ends = td["next", "done"].squeeze(-1)
        # Every EPISODE-th step truncates, and the next step starts a new episode.
        assert ends.nonzero().squeeze(-1).tolist() == [
            EPISODE - 1,
            2 * EPISODE - 1,
            3 * EPISODE - 1,
        ]
        assert td["next", "truncated"].squeeze(-1)[ends].all()
        assert not td["next", "terminated"].any()
        obs = td["observation"]
        assert obs.shape == (STEPS, 40) and obs.dtype == torch.float32
        # A new episode after each end: a fresh start, not the ended episode's next state.
        for end in ends.nonzero().squeeze(-1).tolist():
            assert not torch.equal(obs[end + 1], td["next", "observation"][end])
    finally:
        env.close()


def test_gym_wrapper_over_a_same_step_vector_env(address: str) -> None:
    n = 3
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=n,
        address=address,
        autoreset_mode=AutoresetMode.SAME_STEP,
        max_episode_steps=EPISODE,
    )
    env = torchrl_envs.GymWrapper(envs)
    try:
        check_env_specs(env)
        env.set_seed(100)
        td = env.rollout(STEPS, break_when_any_done=False)
        assert td.batch_size == torch.Size([n, STEPS])
        done = td["next", "done"].squeeze(-1)
        assert (done.sum(dim=1) == 3).all(), done.sum(dim=1)
        # The info keys, read every step: the tick counts each episode's steps and starts again
        # at 0 after each end (SAME_STEP: the end's own "next" holds the ended episode's last
        # state); the seed stays that of each environment's episode until it ends.
        ticks, next_ticks = td["tick"], td["next", "tick"]
        for i in range(n):
            for end in done[i].nonzero().squeeze(-1).tolist():
                assert next_ticks[i, end] == EPISODE
                if end + 1 < STEPS:
                    assert ticks[i, end + 1] == 0
        seeds = td["seed"]
        assert seeds.dtype == torch.int64
        np.testing.assert_array_equal(seeds[:, 0].numpy(), [100, 101, 102])
        np.testing.assert_array_equal(
            seeds[:, EPISODE - 1].numpy(), seeds[:, 0].numpy()
        )  # the first episode's seed throughout it
    finally:
        env.close()


def test_gym_wrapper_refuses_a_next_step_vector_env(address: str) -> None:
    """TorchRL's own rule, kept here so that a TorchRL that starts accepting NEXT_STEP is noticed
    (and tested)."""
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=2, address=address)
    try:
        with pytest.raises(Exception, match=r"(?i)autoreset|next.step|same.step"):
            torchrl_envs.GymWrapper(envs)
    finally:
        envs.close()
