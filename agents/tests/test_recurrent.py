"""Sequence DAgger's learners (:mod:`dinerdash_agents.recurrent`): the episode-start rule, the
state's reset at an episode's start (across autoreset), the policy's step-by-step actions
against one scan over the same sequences, truncated BPTT's chunk states, the checkpoint round
trip, a round's recording on a scripted vector env, and a short run against a real server that
``python -m dinerdash_agents evaluate`` then plays."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE
from test_dagger import ScriptedVectorEnv

from dinerdash_agents import checkpoint, dagger, load
from dinerdash_agents import recurrent as rec
from dinerdash_agents.cli import main
from dinerdash_agents.dagger import play_round

KINDS = ["gru", "stack"]


def start_obs(level: int = 4, size: int = 2) -> np.ndarray:
    """An episode's first observation: six free clean tables (capacities 2, 2, 4, 4, 4, 6, no
    group), no food, empty hands, one group waiting."""
    obs = np.zeros(OBSERVATION_SIZE, np.float32)
    obs[: 3 * 6] = np.array([[0, c, -1] for c in (2, 2, 4, 4, 4, 6)]).reshape(-1)
    obs[24:26] = (level, size)
    return obs


def busy_obs(rng: np.random.Generator) -> np.ndarray:
    """A mid-episode observation: table 0 occupied (status 2), the rest random but plausible."""
    obs = start_obs()
    obs[0:3] = (2, 2, rng.integers(0, 4))
    obs[24:30] = (rng.integers(0, 5), 3, rng.integers(0, 5), 2, rng.integers(0, 5), 4)
    obs[38] = rng.integers(0, 3)
    return obs


def sequences(rng: np.random.Generator, steps: int, envs: int) -> np.ndarray:
    """(T, B, 40) observations: busy ones, with an episode start at a few random steps."""
    obs = np.stack([[busy_obs(rng) for _ in range(envs)] for _ in range(steps)])
    for b in range(envs):
        for t in rng.choice(np.arange(1, steps), size=2, replace=False):
            obs[t, b] = start_obs(level=3 + int(rng.integers(0, 2)))
    return obs


def config(kind: str, **kw) -> rec.RecurrentConfig:
    return rec.RecurrentConfig(kind=kind, hidden=16, stack=3, **kw)


def test_episode_starts_marks_first_observations_that_changed() -> None:
    rng = np.random.default_rng(0)
    s, busy = start_obs(), busy_obs(rng)
    batch = np.stack([s, s, busy, start_obs(level=2)])
    last = np.stack([busy, s, s, busy])
    # A start after a busy state: yes; the same start again (the agent waited): no; a busy
    # state: no; a lone group below its starting level: no.
    assert dagger.episode_starts(batch, last).tolist() == [True, False, False, False]
    assert dagger.episode_starts(batch, None).all()
    assert dagger.sequence_starts(np.stack([s, s, busy, s])).tolist() == [True, False, False, True]


@pytest.mark.parametrize("kind", KINDS)
def test_state_resets_at_an_episode_start(kind: str) -> None:
    rng = np.random.default_rng(1)
    model = rec.init(config(kind), 0)
    policy = rec.RecurrentPolicy(model, {"algorithm": rec.ALGORITHM})
    for _ in range(12):  # a busy history, then a new episode (as an autoreset brings it)
        policy.act(np.stack([busy_obs(rng), busy_obs(rng)]))
    assert not np.allclose(policy.state.model, 0)
    policy.act(np.stack([start_obs(), busy_obs(rng)]))
    fresh = rec.RecurrentPolicy(model, {"algorithm": rec.ALGORITHM})
    fresh.act(start_obs()[None])
    np.testing.assert_allclose(policy.state.model[0], fresh.state.model[0], rtol=1e-6, atol=1e-6)
    # Environment 1 went on: its state is not the fresh one.
    assert not np.allclose(policy.state.model[1], fresh.state.model[0])
    # A batch of another size starts every environment afresh; so does episode_start.
    policy.act(np.stack([start_obs()] * 3))
    repeated = np.repeat(fresh.state.model, 3, axis=0)
    np.testing.assert_allclose(policy.state.model, repeated, atol=1e-6)
    policy.act(np.stack([busy_obs(rng)] * 3), episode_start=[False, True, False])
    fresh.reset()
    b = busy_obs(rng)
    policy.act(np.stack([b] * 3), episode_start=[False, True, False])
    fresh.act(b[None])
    np.testing.assert_allclose(policy.state.model[1], fresh.state.model[0], atol=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_policy_actions_equal_a_replay_of_the_scan(kind: str) -> None:
    rng = np.random.default_rng(2)
    model = rec.init(config(kind), 3)
    steps, envs = 40, 4
    obs = sequences(rng, steps, envs)
    masks = rng.random((steps, envs, NUM_ACTIONS)) < 0.5
    masks[..., 0] = True
    policy = rec.RecurrentPolicy(model, {"algorithm": rec.ALGORITHM})
    stepped = np.stack([policy.act(obs[t], masks[t]) for t in range(steps)])
    first = np.stack([dagger.sequence_starts(obs[:, b]) for b in range(envs)], axis=1)
    logits, last = model.unroll(model.initial_state(envs), jnp.asarray(obs), jnp.asarray(first))
    scanned = np.argmax(np.where(masks, np.asarray(logits), -np.inf), axis=-1)
    np.testing.assert_array_equal(stepped, scanned)
    np.testing.assert_allclose(policy.state.model, last, rtol=1e-5, atol=1e-5)
    assert first.sum() >= 2 * envs  # the sequences did hold episode starts


@pytest.mark.parametrize("kind", KINDS)
def test_chunks_start_from_the_lane_state_of_one_forward_pass(kind: str) -> None:
    rng = np.random.default_rng(4)
    model = rec.init(config(kind), 5)
    episodes = []
    for length in (50, 23, 77, 31):
        o = np.stack([busy_obs(rng) for _ in range(length)])
        o[0] = start_obs()
        m = np.ones((length, NUM_ACTIONS), np.bool_)
        a = rng.integers(0, NUM_ACTIONS, length).astype(np.int32)
        episodes.append(rec.Episode(o, m, a, dagger.sequence_starts(o)))
    data = rec.sequence_batches(episodes, chunk=8, seat_weight=4.0, lanes=3)
    lanes, per_lane, chunk = data["action"].shape
    assert (lanes, chunk) == (3, 8) and lanes * per_lane * chunk >= 181
    # Padding weighs nothing; a seat action weighs 4 (every action is legal here).
    assert data["weight"].sum() == pytest.approx(
        sum(float(np.where(e.action >= 15, 4.0, 1.0).sum()) for e in episodes)
    )
    starts = rec.chunk_starts(model, jnp.asarray(data["obs"]), jnp.asarray(data["first"]))
    # Chunk j of a lane unrolled from its start gives the logits of the lane's full unroll.
    for lane in range(lanes):
        o = jnp.asarray(data["obs"][lane].reshape(-1, 1, OBSERVATION_SIZE))
        f = jnp.asarray(data["first"][lane].reshape(-1, 1))
        full, _ = model.unroll(model.initial_state(1), o, f)
        for j in range(per_lane):
            part, _ = model.unroll(
                starts[lane, j][None],
                jnp.asarray(data["obs"][lane, j][:, None]),
                jnp.asarray(data["first"][lane, j][:, None]),
            )
            np.testing.assert_allclose(
                part[:, 0], full[j * chunk : (j + 1) * chunk, 0], rtol=1e-4, atol=1e-4
            )


@pytest.mark.parametrize(("kind", "memory"), [("gru", False), ("stack", False), ("gru", True)])
def test_checkpoint_round_trip(kind: str, memory: bool, tmp_path: Path) -> None:
    cfg = config(kind, memory=memory)
    model = rec.init(cfg, 7)
    description = {"name": "r", "algorithm": rec.ALGORITHM, "config": cfg.to_json()}
    checkpoint.save(tmp_path / "r", model, description)
    loaded = load(tmp_path / "r")
    assert isinstance(loaded, rec.RecurrentPolicy)
    rng = np.random.default_rng(8)
    obs = sequences(rng, 20, 3)
    original = rec.RecurrentPolicy(model, description)
    for t in range(len(obs)):
        np.testing.assert_array_equal(loaded.act(obs[t]), original.act(obs[t]))


def test_a_round_records_each_episode_in_seed_order() -> None:
    seeds = [3, 4, 5, 6, 7, 9]
    envs = ScriptedVectorEnv(3)
    model = rec.init(config("gru"), 0)
    learner = rec.RecurrentPolicy(model, {"algorithm": rec.ALGORITHM})
    played = play_round(envs, learner, 0.5, seeds, np.random.default_rng(0))
    episodes, scores = played.episodes, played.scores
    assert [len(e) for e in episodes] == [ScriptedVectorEnv.length(s) for s in seeds]
    for seed, e in zip(seeds, episodes, strict=True):
        assert (e.obs[:, 0] == seed).all() and e.obs[:, 1].tolist() == list(range(len(e)))
        assert (e.action == seed % 50 + 5).all()  # the teacher's label at every step
        assert e.first[0] and e.mask[np.arange(len(e)), e.action].all()
    assert len(scores) == len(seeds)


def test_train_then_evaluate_plays_the_checkpoint(
    server_address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "gru"
    code = main(
        [
            "train",
            "dagger-recurrent",
            "--kind",
            "gru",
            "--rounds",
            "2",
            "--episodes-per-round",
            "4",
            "--num-envs",
            "4",
            "--hidden",
            "16",
            "--out",
            str(out),
            "--address",
            server_address,
        ]
    )
    assert code == 0
    description = json.loads((out / checkpoint.DESCRIPTION).read_text())
    assert description["algorithm"] == "dagger-recurrent"
    assert description["config"]["kind"] == "gru"
    assert (out / "curve.csv").read_text().count("\n") == 3  # header and two rounds
    capsys.readouterr()
    argv = ["evaluate", str(out), "--episodes", "3", "--seed", "1000", "--json"]
    assert main([*argv, "--address", server_address]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(result["scores"]) == 3
