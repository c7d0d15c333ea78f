"""The single environment against a real server: Gymnasium's checker, spaces, infos,
determinism, reset options, rendering and the server extras (fork, snapshot, restore)."""

from __future__ import annotations

import warnings

import dinerdash
import gymnasium
import numpy as np
import pytest
from dinerdash import DinerDashEnv
from dinerdash.render import HEIGHT, STATUS_COLORS, WIDTH
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.env_match import check_environments_match

from .conftest import ServerProcess

MAX_STEPS = 3000  # bound on every loop below


def rollout_random(env, seed: int, steps: int, action_seed: int = 7):
    """(obs, reward, terminated, truncated, info) of ``steps`` random steps, resetting at ends."""
    rng = np.random.default_rng(action_seed)
    out = [env.reset(seed=seed)]
    for _ in range(steps):
        step = env.step(int(rng.integers(0, 57)))
        out.append(step)
        if step[2] or step[3]:
            out.append(env.reset())
    return out


def assert_same(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert len(x) == len(y)
        for u, v in zip(x, y, strict=True):
            if isinstance(u, dict):
                assert u.keys() == v.keys()
                for k in u:
                    np.testing.assert_array_equal(u[k], v[k], err_msg=k)
            else:
                np.testing.assert_array_equal(u, v)


@pytest.mark.parametrize("render_mode", [None, "ansi", "rgb_array"])
def test_check_env_passes(address: str, render_mode) -> None:
    # Made through gymnasium.make so that the checker can also try the other render modes.
    made = gymnasium.make(
        "dinerdash:DinerDash-v0", address=address, expert=True, render_mode=render_mode
    )
    env = made.unwrapped
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any checker warning fails the test
            check_env(env, skip_render_check=render_mode is None)
    finally:
        env.close()


def test_check_env_on_the_made_env_including_close_twice(address: str) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address)
    try:
        assert isinstance(env.unwrapped, DinerDashEnv)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env(env.unwrapped)  # with a spec: also makes a second env and closes it twice
    finally:
        env.close()
        env.close()


def test_spaces_are_those_of_the_rules(address: str) -> None:
    env = DinerDashEnv(address)
    try:
        assert env.action_space == gymnasium.spaces.Discrete(57)
        box = env.observation_space
        assert box.shape == (40,) and box.dtype == np.float32
        low = [0, 0, -1] * 6 + [0] * 6 + [0, 0] * 7 + [0, 0]
        high = [6, 6, 4] * 6 + [1] * 6 + [4, 6] * 7 + [18, 18]
        np.testing.assert_array_equal(box.low, low)
        np.testing.assert_array_equal(box.high, high)
    finally:
        env.close()


def test_infos_hold_the_documented_keys(address: str) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address, expert=True)
    try:
        obs, info = env.reset(seed=3)
        assert set(info) == {"action_mask", "score", "lost", "tick", "expert_action", "seed"}
        assert info["seed"] == 3 and info["score"] == 0 and info["lost"] == 0 and info["tick"] == 0
        assert info["action_mask"].dtype == np.bool_ and info["action_mask"].shape == (57,)
        assert info["action_mask"][0]
        assert info["action_mask"][info["expert_action"]]
        total = 0.0
        for _ in range(50):
            obs, reward, terminated, truncated, info = env.step(info["expert_action"])
            total += reward
            # Every step's info has reset's keys (TorchRL reads them once), the seed kept.
            assert set(info) == {"action_mask", "score", "lost", "tick", "expert_action", "seed"}
            assert info["seed"] == 3
            assert obs.dtype == np.float32 and obs in env.observation_space
        assert info["tick"] == 50
        assert total == info["score"]  # reward is the change of the score
    finally:
        env.close()
    plain = DinerDashEnv(address)
    try:
        _, info = plain.reset(seed=3)
        assert "expert_action" not in info
    finally:
        plain.close()


def test_same_seed_same_trajectory_across_two_sessions(address: str) -> None:
    a, b = DinerDashEnv(address, expert=True), DinerDashEnv(address, expert=True)
    try:
        assert a.session_id != b.session_id
        assert_same(rollout_random(a, 11, 400), rollout_random(b, 11, 400))
    finally:
        a.close()
        b.close()


def test_same_seed_same_trajectory_across_two_server_processes(start_server) -> None:
    s1, s2 = start_server(), start_server()
    assert s1.pid != s2.pid
    a, b = DinerDashEnv(s1.address, expert=True), DinerDashEnv(s2.address, expert=True)
    try:
        assert_same(rollout_random(a, 12, 400), rollout_random(b, 12, 400))
    finally:
        a.close()
        b.close()
    # Gymnasium's own comparison, renders included (rgb_array: gymnasium 1.2, which Ray pins,
    # compares renders with ``(a == b).all()``, which a str render fails).
    a = DinerDashEnv(s1.address, expert=True, render_mode="rgb_array")
    b = DinerDashEnv(s2.address, expert=True, render_mode="rgb_array")
    try:
        check_environments_match(a, b, num_steps=300, seed=13)
    finally:
        a.close()
        b.close()


def test_different_seeds_differ(address: str) -> None:
    env = DinerDashEnv(address)
    try:
        firsts = {tuple(env.reset(seed=s)[0][24:26]) for s in range(20)}
        assert len(firsts) > 1
    finally:
        env.close()


def test_unseeded_reset_reports_a_seed_that_replays(address: str) -> None:
    a, b = DinerDashEnv(address), DinerDashEnv(address)
    try:
        obs, info = a.reset()
        seed = info["seed"]
        obs_b, info_b = b.reset(seed=seed)
        np.testing.assert_array_equal(obs, obs_b)
        assert info_b["seed"] == seed
        for action in [15, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 7]:
            sa, sb = a.step(action), b.step(action)
            np.testing.assert_array_equal(sa[0], sb[0])
    finally:
        a.close()
        b.close()


def test_reset_with_an_explicit_arrival_list(address: str) -> None:
    env = DinerDashEnv(address)
    try:
        obs, _ = env.reset(options={"arrivals": [(2, 3), (1, 5)]})
        assert obs[24] == 800 // 200 and obs[25] == 3  # group 1: type 2, size 3
        for _ in range(10):  # groups arrive at ticks 0, 9, ...: the 10th step brings group 2
            obs, *_ = env.step(0)
        assert obs[26] == 600 // 200 and obs[27] == 5  # group 2: type 1, size 5
        obs2, _ = env.reset(options={"arrivals": [{"customer_type": 1, "size": 6}]})
        assert obs2[24] == 600 // 200 and obs2[25] == 6
    finally:
        env.close()


def test_configuration_at_make_and_at_reset(address: str) -> None:
    env = gymnasium.make("dinerdash:DinerDash-v0", address=address, config={"time_limit": 25})
    try:
        assert env.unwrapped.game_config["time_limit"] == 25
        env.reset(seed=0)
        for t in range(1, 26):
            _, _, terminated, truncated, info = env.step(0)
            assert truncated == (t == 25) and not terminated
        assert info["tick"] == 25
        env.reset(seed=0, options={"config": {"lives": 1, "time_limit": 0}})
        for _ in range(MAX_STEPS):
            _, _, terminated, truncated, info = env.step(0)  # waiting loses groups
            if terminated or truncated:
                break
        assert terminated and not truncated and info["lost"] == 1
    finally:
        env.close()


def test_render_modes(address: str) -> None:
    ansi = DinerDashEnv(address, render_mode="ansi")
    rgb = DinerDashEnv(address, render_mode="rgb_array")
    try:
        for env in (ansi, rgb):
            env.reset(options={"arrivals": [(1, 4)]})
            env.step(15)  # seat group 1 at table 1: status 1, reading the menu
        text = ansi.render()
        assert isinstance(text, str) and "score" in text.lower() and "\x1b[" not in text
        img = rgb.render()
        assert img.shape == (HEIGHT, WIDTH, 3) and img.dtype == np.uint8
        # Table 1's cell is drawn in the "reading" colour; table 2 is free.
        np.testing.assert_array_equal(img[36 + 40, 88 + 40], STATUS_COLORS[1])
        np.testing.assert_array_equal(img[36 + 40, 180 + 40], STATUS_COLORS[0])
    finally:
        ansi.close()
        rgb.close()


def test_fork_continues_identically(address: str) -> None:
    env = DinerDashEnv(address, expert=True)
    try:
        _, info = env.reset(seed=5)
        for _ in range(40):
            _, _, _, _, info = env.step(info["expert_action"])
        child = env.fork()
        try:
            assert child.session_id != env.session_id
            actions = np.random.default_rng(1).integers(0, 57, size=200)
            for a in actions:
                x, y = env.step(int(a)), child.step(int(a))
                assert_same([x], [y])  # the whole step: observation, flags and every info key
                if x[2]:
                    break
        finally:
            child.close()
        env.reset(seed=5)  # the child's close() closed its own session, not this env's
    finally:
        env.close()


def test_snapshot_restore_rewinds(address: str) -> None:
    env = DinerDashEnv(address)
    try:
        env.reset(seed=9)
        for _ in range(30):
            env.step(0)
        snap = env.snapshot()
        assert isinstance(snap.data, bytes) and snap.data
        actions = [15, 16, 0, 0, 1, 0, 7, 0, 0, 0, 0, 0, 0, 0, 0, 8, 1]
        first = [env.step(a) for a in actions]
        obs, info = env.restore(snap)
        np.testing.assert_array_equal(obs, snap.observation)
        assert info["tick"] == 30
        second = [env.step(a) for a in actions]
        assert_same(first, second)
    finally:
        env.close()


def test_snapshot_restores_on_another_server(address: str, start_server) -> None:
    other: ServerProcess = start_server()
    a, b = DinerDashEnv(address), DinerDashEnv(other.address)
    try:
        a.reset(seed=4)
        for _ in range(20):
            a.step(0)
        b.restore(a.snapshot())
        for action in [15, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]:
            x, y = a.step(action), b.step(action)
            np.testing.assert_array_equal(x[0], y[0])
            assert x[4]["tick"] == y[4]["tick"]
    finally:
        a.close()
        b.close()


def test_package_exports() -> None:
    assert issubclass(dinerdash.ServiceTransportError, OSError)
    assert issubclass(dinerdash.SessionNotFound, dinerdash.ServiceError)
    assert (
        gymnasium.spec("DinerDash-v0").vector_entry_point == "dinerdash.vector:DinerDashVectorEnv"
    )
