"""The plain-Python simulator (``dinerdash_bench.reference``, the baseline of ``bench``) replays
every trajectory recorded from the reference (tests/data/conformance) exactly, expert included.
No server is needed."""

from __future__ import annotations

import pytest
from dinerdash.game import NUM_ACTIONS, WAIT
from dinerdash_bench.reference import Config, Game, random_steps_per_second

from .test_conformance import load


def test_every_recorded_episode_replays_through_the_reference(conformance_files) -> None:
    replayed = 0
    for where, ep in load(conformance_files):
        game = Game()
        assert game.reset(seed=ep["seed"]) == ep["reset_obs"], f"{where}: reset observation"
        assert (game.score, game.lost, game.tick) == (0, 0, 0)
        for i, step in enumerate(ep["steps"]):
            at = f"{where} step {i} (action {step['action']})"
            # The record's expert_action is the choice in the state before the step.
            expert = game.expert_action()
            assert expert == step["expert_action"], f"{at}: expert"
            mask = game.action_mask()
            assert mask[WAIT] and mask[expert], f"{at}: mask refuses the expert's action"
            # An action the mask refuses only lets time pass, exactly like waiting.
            waited = None if mask[step["action"]] else game.restaurant.copy()
            obs, reward, done = game.step(step["action"])
            assert obs == step["obs"], f"{at}: observation"
            assert reward == step["reward"], f"{at}: reward"
            assert done == step["terminated"], f"{at}: done"
            assert game.score == step["score"], f"{at}: score"
            assert game.lost == step["lost"], f"{at}: lost"
            assert game.tick == i + 1, at
            if waited is not None:
                assert waited.step(WAIT) == reward, f"{at}: refused action's reward"
                assert waited.observation() == obs, f"{at}: refused action's observation"
            replayed += 1
    assert replayed > 1000


def test_a_reset_without_a_seed_continues_the_stream() -> None:
    seeded = Game(seed=7)
    first, second = seeded.reset(), seeded.reset()
    again = Game()
    assert again.reset(seed=7) == first
    assert again.reset() == second
    assert again.restaurant.arrivals == seeded.restaurant.arrivals
    # Without any seed the game picks one from entropy and reports it, so the episode replays.
    fresh = Game()
    obs = fresh.reset()
    assert fresh.seed is not None
    replay = Game()
    assert replay.reset(seed=fresh.seed) == obs
    assert replay.restaurant.arrivals == fresh.restaurant.arrivals


def test_bad_input_is_refused() -> None:
    game = Game()
    with pytest.raises(RuntimeError, match="never reset"):
        game.step(0)
    with pytest.raises(ValueError, match="non-negative"):
        game.reset(seed=-1)
    game.reset(seed=0)
    for action in (-1, NUM_ACTIONS):
        with pytest.raises(ValueError, match=r"0\.\.=56"):
            game.step(action)
    with pytest.raises(ValueError, match="positive"):
        random_steps_per_second(0)


def test_a_time_limit_ends_the_episode() -> None:
    game = Game(config=Config(time_limit=3))
    game.reset(seed=0)
    assert [game.step(WAIT)[2] for _ in range(3)] == [False, False, True]


def test_random_steps_per_second_measures_a_rate() -> None:
    # Only that it runs (episodes end and reset within 3,000 random steps) and reports a rate:
    # the rate itself depends on the machine.
    rate = random_steps_per_second(2_000, seed=3)
    assert rate > 0
