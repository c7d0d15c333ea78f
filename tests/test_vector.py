"""The vector env against a real server: make_vec, Gymnasium's vector format, and equality with
Gymnasium's own SyncVectorEnv over single environments (the reference vector semantics)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from dinerdash import DinerDashEnv, DinerDashVectorEnv, FailedPrecondition
from gymnasium.vector import AutoresetMode, SyncVectorEnv

STEPS = 400
# One life: episodes end often, so the autoreset paths are exercised within a few hundred steps.
SHORT = {"lives": 1}


def compare_info(mine: dict, ref: dict, where: str) -> None:
    assert mine.keys() == ref.keys(), where
    for key in ref:
        if isinstance(ref[key], dict):
            compare_info(mine[key], ref[key], f"{where} {key}")
        elif ref[key].dtype == object:  # final_obs: arrays or None
            for a, b in zip(mine[key], ref[key], strict=True):
                assert (a is None) == (b is None), where
                if a is not None:
                    np.testing.assert_array_equal(a, b, err_msg=f"{where} {key}")
        else:
            np.testing.assert_array_equal(
                mine[key].astype(ref[key].dtype), ref[key], err_msg=f"{where} {key}"
            )
            assert mine[key].dtype == ref[key].dtype, f"{where} {key}"


def compare_partial_reset(mine: tuple, ref: tuple, done: np.ndarray, where: str) -> None:
    """After ``reset(options={"reset_mask": done})``: the same observations; Gymnasium's infos
    cover the environments reset, ours every environment (the others' current values)."""
    np.testing.assert_array_equal(mine[0], ref[0], err_msg=where)
    info_m, info_r = mine[1], ref[1]
    assert info_m.keys() == info_r.keys(), where
    np.testing.assert_array_equal(info_m["_seed"], done, err_msg=where)
    for key in info_r:
        if not key.startswith("_"):
            reset = info_r[f"_{key}"]
            np.testing.assert_array_equal(reset, done, err_msg=f"{where} {key}")
            assert info_m[f"_{key}"][reset].all(), f"{where} {key}"
            np.testing.assert_array_equal(
                info_m[key][reset].astype(info_r[key].dtype), info_r[key][reset], err_msg=where
            )


def run_pair(
    address: str, mode: AutoresetMode, n: int = 4, transport: str = "grpc", steps: int = STEPS
) -> int:
    mine = DinerDashVectorEnv(
        n, address, expert=True, config=SHORT, autoreset_mode=mode, transport=transport
    )
    ref = SyncVectorEnv(
        [
            lambda: DinerDashEnv(address, expert=True, config=SHORT, transport="grpc")
            for _ in range(n)
        ],
        autoreset_mode=mode,
    )
    ends = 0
    try:
        obs_m, info_m = mine.reset(seed=100)
        obs_r, info_r = ref.reset(seed=100)
        np.testing.assert_array_equal(obs_m, obs_r)
        compare_info(info_m, info_r, "reset")
        rng = np.random.default_rng(0)
        for t in range(steps):
            # Half expert, half random: long enough episodes, and invalid actions too.
            actions = np.where(rng.random(n) < 0.5, info_m["expert_action"], rng.integers(0, 57, n))
            out_m, out_r = mine.step(actions), ref.step(actions)
            names = ("obs", "reward", "terminated", "truncated")
            for name, a, b in zip(names, out_m[:4], out_r[:4], strict=True):
                np.testing.assert_array_equal(a, b, err_msg=f"step {t}: {name}")
                assert a.dtype == b.dtype, name
            info_m, info_r = out_m[4], out_r[4]
            compare_info(info_m, info_r, f"step {t}")
            done = out_m[2] | out_m[3]
            ends += int(np.sum(done))
            if mode == AutoresetMode.DISABLED and done.any():
                # No autoreset: the caller resets the finished environments alone.
                options = {"reset_mask": done}
                seed = int(rng.integers(0, 1000))
                mine_reset = mine.reset(seed=seed, options=dict(options))
                ref_reset = ref.reset(seed=seed, options=dict(options))
                compare_partial_reset(mine_reset, ref_reset, done, f"reset after step {t}")
                info_m = mine_reset[1]
    finally:
        mine.close()
        ref.close()
    return ends


@pytest.mark.parametrize("transport", ["grpc", "shm"])
@pytest.mark.parametrize("n", [1, 4])
@pytest.mark.parametrize("mode", list(AutoresetMode))
def test_same_as_gymnasium_sync_vector_env(
    address: str, mode: AutoresetMode, n: int, transport: str
) -> None:
    """Over either transport, step for step the same as single envs stepped over gRPC."""
    assert run_pair(address, mode, n, transport) >= 2  # the (auto)reset path was taken


def test_many_environments_decode_as_single_envs(address: str) -> None:
    """Above 32 environments a gRPC reply's repeated fields (the seeds) are read through
    protobuf's container rather than a list: the same values as single envs report."""
    assert run_pair(address, AutoresetMode.NEXT_STEP, n=40, steps=200) >= 2


def test_make_vec_uses_the_batched_session(address: str) -> None:
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=8, address=address, expert=True)
    try:
        assert isinstance(envs, DinerDashVectorEnv)
        assert len(envs.session_ids) == 1  # ONE server session for the 8 environments
        assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        assert envs.single_action_space == gymnasium.spaces.Discrete(57)
        assert envs.action_space.shape == (8,) and envs.observation_space.shape == (8, 40)
        obs, info = envs.reset(seed=0)
        assert obs.shape == (8, 40) and obs.dtype == np.float32 and obs in envs.observation_space
        assert info["action_mask"].shape == (8, 57) and info["action_mask"].dtype == np.bool_
        assert info["expert_action"].shape == (8,)
        np.testing.assert_array_equal(info["seed"], np.arange(8))
        for key in ("action_mask", "score", "lost", "tick", "expert_action", "seed"):
            np.testing.assert_array_equal(info[f"_{key}"], np.ones(8, dtype=bool))
        obs, reward, terminated, truncated, info = envs.step(info["expert_action"])
        assert reward.dtype == np.float64 and terminated.dtype == np.bool_
        # The same keys as at reset (TorchRL reads them once): each episode's seed kept.
        np.testing.assert_array_equal(info["seed"], np.arange(8))
        assert info["_seed"].all()
    finally:
        envs.close()


def test_make_vec_same_step_mode_and_time_limit(address: str) -> None:
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=3,
        address=address,
        autoreset_mode=AutoresetMode.SAME_STEP,
        max_episode_steps=5,
    )
    try:
        assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        obs0, _ = envs.reset(seed=1)
        for _ in range(4):
            _, _, _, truncated, info = envs.step(np.zeros(3, dtype=np.int64))
            assert not truncated.any()
        obs, reward, terminated, truncated, info = envs.step(np.zeros(3, dtype=np.int64))
        assert truncated.all() and not terminated.any()
        np.testing.assert_array_equal(info["_final_obs"], [True] * 3)
        np.testing.assert_array_equal(info["final_info"]["tick"], [5, 5, 5])
        np.testing.assert_array_equal(info["tick"], [0, 0, 0])  # the new episodes' first state
        assert info["_seed"].all()
    finally:
        envs.close()


def test_seed_list_and_per_env_arrivals(address: str) -> None:
    envs = DinerDashVectorEnv(3, address)
    try:
        _, info = envs.reset(seed=[7, 70, 700])
        np.testing.assert_array_equal(info["seed"], [7, 70, 700])
        obs, _ = envs.reset(options={"arrivals": [[(1, 1)], [(1, 2)], [(2, 6)]]})
        np.testing.assert_array_equal(obs[:, 25], [1, 2, 6])
        obs, _ = envs.reset(options={"arrivals": [(1, 4)]})
        np.testing.assert_array_equal(obs[:, 25], [4, 4, 4])
        with pytest.raises(ValueError):
            envs.step(np.zeros(2, dtype=np.int64))
    finally:
        envs.close()


def test_render_one_frame_per_env(address: str) -> None:
    for mode in ("ansi", "rgb_array"):
        envs = DinerDashVectorEnv(2, address, render_mode=mode)
        try:
            envs.reset(seed=0)
            frames = envs.render()
            assert len(frames) == 2
        finally:
            envs.close()


def test_reset_mask_is_checked(address: str) -> None:
    envs = DinerDashVectorEnv(3, address, autoreset_mode=AutoresetMode.DISABLED)
    try:
        first = np.array([True, False, False])
        with pytest.raises(ValueError, match="environment 1 has never been reset"):
            envs.reset(options={"reset_mask": first})
        envs.reset(seed=0)
        with pytest.raises(TypeError, match="must be a numpy array"):
            envs.reset(options={"reset_mask": [True, False, False]})
        with pytest.raises(ValueError, match=r"bool array of shape \(3,\)"):
            envs.reset(options={"reset_mask": np.ones(2, dtype=bool)})
        with pytest.raises(ValueError, match="selects no environment"):
            envs.reset(options={"reset_mask": np.zeros(3, dtype=bool)})
        with pytest.raises(ValueError, match="give it with a full reset"):
            envs.reset(options={"reset_mask": first, "config": {"lives": 1}})
        obs, info = envs.step(np.zeros(3, dtype=np.int64))[::4]
        again, info = envs.reset(seed=0, options={"reset_mask": first})
        np.testing.assert_array_equal(info["tick"], [0, 1, 1])
        np.testing.assert_array_equal(again[1:], obs[1:])
        np.testing.assert_array_equal(info["_seed"], first)
    finally:
        envs.close()


def test_disabled_mode_refuses_finished_environments(address: str) -> None:
    envs = DinerDashVectorEnv(
        2, address, autoreset_mode=AutoresetMode.DISABLED, max_episode_steps=2
    )
    try:
        envs.reset(seed=0)
        envs.step(np.zeros(2, dtype=np.int64))
        truncated = envs.step(np.zeros(2, dtype=np.int64))[3]
        assert truncated.all()
        with pytest.raises(FailedPrecondition, match="environment 0: episode is over"):
            envs.step(np.zeros(2, dtype=np.int64))
        _, info = envs.reset(options={"reset_mask": np.array([False, True])})
        np.testing.assert_array_equal(info["tick"], [2, 0])
    finally:
        envs.close()
