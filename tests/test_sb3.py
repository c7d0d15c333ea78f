"""stable-baselines3 as researchers use it: ``action_masks()`` on both envs, SB3's ``check_env``
with its render checks, :func:`dinerdash.sb3.make_vec_env` (terminal observations, truncation
flags, masks, seeding) and short MaskablePPO runs, on a plain ``gymnasium.make`` env (no wrapper)
and on the adapter. Needs the ``dinerdash[sb3]`` extra (``make venv`` installs it)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv

pytest.importorskip("stable_baselines3", reason="pip install 'dinerdash[sb3]'")
pytest.importorskip("sb3_contrib", reason="pip install 'dinerdash[sb3]'")

from dinerdash.sb3 import DinerDashSB3VecEnv, make_vec_env
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.utils import get_action_masks, is_masking_supported
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

N = 4


def test_action_masks_of_both_envs_are_the_info_masks(address: str) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address)
    envs = DinerDashVectorEnv(N, address)
    try:
        with pytest.raises(gymnasium.error.ResetNeeded):
            env.unwrapped.action_masks()
        _, info = env.reset(seed=1)
        _, vinfo = envs.reset(seed=1)
        for _ in range(30):
            mask = env.unwrapped.action_masks()
            assert mask.dtype == np.bool_ and mask.shape == (57,) and mask[0]
            np.testing.assert_array_equal(mask, info["action_mask"])
            masks = envs.action_masks()
            np.testing.assert_array_equal(masks, vinfo["action_mask"])
            np.testing.assert_array_equal(masks[0], mask)  # same seed, same legal moves
            action = int(np.flatnonzero(mask)[-1])
            _, _, _, _, info = env.step(action)
            _, _, _, _, vinfo = envs.step(np.full(N, action))
    finally:
        env.close()
        envs.close()


@pytest.mark.parametrize("render_mode", ["ansi", "rgb_array"])
def test_check_env_passes_with_its_render_checks(address: str, render_mode: str) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address, render_mode=render_mode)
    try:
        check_env(env.unwrapped, warn=True, skip_render_check=False)
        # check_env closed the env at the end of its render check; it is still usable.
        _, info = env.reset(seed=0)
        assert info["tick"] == 0
    finally:
        env.close()


def test_the_adapter_reports_terminal_observations_and_truncation(address: str) -> None:
    env = make_vec_env(N, address=address, max_episode_steps=7, monitor=False)
    # The same episodes, played through the Gymnasium vector env, say what the adapter must show.
    reference = DinerDashVectorEnv(N, address, max_episode_steps=7)
    try:
        assert isinstance(env, DinerDashSB3VecEnv) and isinstance(env, VecEnv)
        assert env.num_envs == N and env.action_space.n == 57
        env.seed(100)
        obs = env.reset()
        expected, _ = reference.reset(seed=100)
        np.testing.assert_array_equal(obs, expected)
        assert obs.shape == (N, 40) and obs.dtype == np.float32
        assert [int(i["seed"]) for i in env.reset_infos] == [100, 101, 102, 103]
        for step in range(1, 8):
            masks = get_action_masks(env)
            assert masks.shape == (N, 57) and masks[:, 0].all()
            obs, rewards, dones, infos = env.step(np.zeros(N, dtype=np.int64))
            expected, _, _, truncated, _ = reference.step(np.zeros(N, dtype=np.int64))
            assert rewards.dtype == np.float32 and dones.shape == (N,)
            if step < 7:
                assert not dones.any() and infos == [{}] * N
                np.testing.assert_array_equal(obs, expected)
        # Step 7 reaches the time limit: every episode is truncated, and already reset.
        assert dones.all() and truncated.all()
        for i, info in enumerate(infos):
            assert info["TimeLimit.truncated"] is True
            np.testing.assert_array_equal(info["terminal_observation"], expected[i])
        assert len(env.env_method("action_masks")) == N
        assert env.env_method("action_masks", indices=[1])[0].shape == (57,)
        assert env.get_attr("render_mode") == [None] * N
        assert env.env_is_wrapped(gymnasium.Wrapper) == [False] * N
        with pytest.raises(AttributeError, match="action_masks"):
            env.env_method("fork")
    finally:
        env.close()
        reference.close()


def test_the_adapter_is_seeded_like_the_vector_env(address: str) -> None:
    sb3 = make_vec_env(N, address=address)
    gym_envs = DinerDashVectorEnv(N, address)
    try:
        assert isinstance(sb3, VecMonitor) and is_masking_supported(sb3)
        sb3.seed(7)
        obs = sb3.reset()
        expected, _ = gym_envs.reset(seed=7)
        np.testing.assert_array_equal(obs, expected)
        rng = np.random.default_rng(0)
        for _ in range(50):
            masks = get_action_masks(sb3)
            actions = np.argmax(rng.random(masks.shape) * masks, axis=1)
            obs, rewards, dones, _ = sb3.step(actions)
            expected, exp_rewards, term, trunc, _ = gym_envs.step(actions)
            np.testing.assert_array_equal(obs, expected)
            np.testing.assert_array_equal(rewards, exp_rewards)
            assert not dones.any() and not (term | trunc).any()
    finally:
        sb3.close()
        gym_envs.close()


def test_maskable_ppo_trains_on_a_plain_gymnasium_env(address: str) -> None:
    """No wrapper: MaskablePPO finds ``action_masks`` on the env itself."""
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address, max_episode_steps=200)
    try:
        model = MaskablePPO("MlpPolicy", env, n_steps=256, batch_size=64, n_epochs=1, seed=0)
        model.learn(total_timesteps=512)
        assert model.num_timesteps >= 512
    finally:
        env.close()


def test_maskable_ppo_trains_on_the_adapter(address: str) -> None:
    env = make_vec_env(8, address=address, max_episode_steps=200)
    try:
        model = MaskablePPO("MlpPolicy", env, n_steps=128, batch_size=256, n_epochs=1, seed=0)
        model.learn(total_timesteps=2048)
        assert model.num_timesteps >= 2048
        # Episodes of 200 steps ended (8 of them by step 1600): VecMonitor logged their returns.
        assert len(model.ep_info_buffer) > 0
        obs = env.reset()
        actions, _ = model.predict(obs, action_masks=get_action_masks(env), deterministic=True)
        assert get_action_masks(env)[np.arange(8), actions].all()  # only legal actions
    finally:
        env.close()


def test_make_vec_env_refuses_another_autoreset_mode(address: str) -> None:
    with pytest.raises(TypeError, match="SAME_STEP"):
        make_vec_env(2, address=address, autoreset_mode="next_step")
    envs = DinerDashVectorEnv(1, address)
    try:
        with pytest.raises(ValueError, match="SAME_STEP"):
            DinerDashSB3VecEnv(envs)
    finally:
        envs.close()


def test_single_env_reuse_after_close_with_sb3_helpers(address: str) -> None:
    env = DinerDashEnv(address)
    env.close()
    _, info = env.reset(seed=0)
    assert env.action_masks()[0] and info["tick"] == 0
    env.close()
