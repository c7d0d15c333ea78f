"""``dinerdash.ray.rllib``'s masking wrappers on a real server: the single env's and the vector
env's observation becomes RLlib's ``{"observations", "action_mask"}`` ``Dict`` (the mask as
float32 0/1, equal to the state's ``action_masks()``), and the info no longer carries the mask
(nor the vector env's ``_action_mask``), at a reset and at a step. Skipped when RLlib (the
``dinerdash[ray]`` extra) is not installed (and CI fails on that skip: tests/conftest.py)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ray.rllib")

from dinerdash import DinerDashEnv, DinerDashVectorEnv
from dinerdash.ray.rllib import MaskedObservation, VectorMaskedObservation


def test_the_single_env_wrapper_puts_the_mask_in_the_observation(server) -> None:
    env = MaskedObservation(DinerDashEnv(server.address))
    try:
        for result in (env.reset(seed=1), env.step(0)):
            obs, info = result[0], result[-1]
            assert env.observation_space.contains(obs)
            mask = env.unwrapped.action_masks()
            np.testing.assert_array_equal(obs["action_mask"], mask.astype(np.float32))
            assert "action_mask" not in info and "tick" in info
    finally:
        env.close()


def test_the_vector_env_wrapper_puts_the_masks_in_the_observations(server) -> None:
    envs = VectorMaskedObservation(DinerDashVectorEnv(3, server.address))
    try:
        for result in (envs.reset(seed=1), envs.step(np.zeros(3, dtype=np.int64))):
            obs, info = result[0], result[-1]
            assert envs.observation_space.contains(obs)
            assert obs["observations"].shape == (3, 40)
            masks = envs.unwrapped.action_masks()
            np.testing.assert_array_equal(obs["action_mask"], masks.astype(np.float32))
            assert "action_mask" not in info and "_action_mask" not in info and "tick" in info
    finally:
        envs.close()
