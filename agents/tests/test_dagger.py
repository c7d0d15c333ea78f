"""DAgger: the aggregation and labelling of one round on a scripted vector env (every visited
state, labelled with the teacher's action from the info, masks kept), the β mixture, the
schedules, the checkpoint, and a short run against a real local server that beats random play."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE, seat_action

from dinerdash_agents import checkpoint, dagger, load, train_dagger
from dinerdash_agents.cli import main
from dinerdash_agents.errors import AgentsError
from dinerdash_agents.evaluate import evaluate_policy


class ScriptedVectorEnv:
    """A vector env whose episode of seed ``s`` lasts ``s % 4 + 2`` steps. The observation of
    step ``t`` of seed ``s`` has ``s`` at index 0 and ``t`` at index 1; its mask allows actions
    0, ``t + 1`` and ``s % 50 + 5``, and the teacher's action is ``s % 50 + 5``. Every action
    taken is logged with the (seed, step) it was taken in."""

    def __init__(self, num_envs: int) -> None:
        self.num_envs = num_envs
        self.seed = [0] * num_envs
        self.t = [0] * num_envs
        self.taken: list[tuple[int, int, int]] = []
        self.resets: list[list[int]] = []

    @staticmethod
    def length(seed: int) -> int:
        return seed % 4 + 2

    def _state(self):
        obs = np.zeros((self.num_envs, OBSERVATION_SIZE), np.float32)
        mask = np.zeros((self.num_envs, NUM_ACTIONS), np.bool_)
        teacher = np.zeros(self.num_envs, np.int64)
        for i, (s, t) in enumerate(zip(self.seed, self.t, strict=True)):
            obs[i, :2] = (s, t)
            if t < 0:  # ended: only waiting is legal (an idle environment plays on unrecorded)
                mask[i, 0] = True
                continue
            mask[i, [0, t + 1, s % 50 + 5]] = True
            teacher[i] = s % 50 + 5
        score = np.array([100 * s + t for s, t in zip(self.seed, self.t, strict=True)])
        return obs, {"action_mask": mask, "expert_action": teacher, "score": score}

    def reset(self, *, seed, options=None):
        reset = (options or {}).get("reset_mask", np.ones(self.num_envs, np.bool_))
        self.resets.append([int(s) for s, r in zip(seed, reset, strict=True) if r])
        for i in np.flatnonzero(reset):
            self.seed[i], self.t[i] = int(seed[i]), 0
        return self._state()

    def step(self, actions):
        terminated = np.zeros(self.num_envs, np.bool_)
        for i, a in enumerate(actions):
            self.taken.append((self.seed[i], self.t[i], int(a)))
            self.t[i] += 1
            if self.t[i] == self.length(self.seed[i]):
                terminated[i] = True
        obs, info = self._state()
        for i in np.flatnonzero(terminated):  # autoreset on the next step, as NEXT_STEP does
            self.t[i] = -1 - 1000  # an unplayable state: the loop must reset or idle it
        return obs, np.zeros(self.num_envs), terminated, np.zeros(self.num_envs, np.bool_), info


class LearnerPicksTPlus1(checkpoint.BasePolicy):
    """A learner that always takes action ``t + 1`` (legal in the scripted env)."""

    def predict(self, obs, state=None, episode_start=None, deterministic=True, action_masks=None):
        return obs[:, 1].astype(np.int64) + 1, state


@pytest.mark.parametrize("beta", [1.0, 0.0])
def test_a_round_adds_every_visited_state_labelled_by_the_teacher(beta: float) -> None:
    seeds = [3, 4, 5, 6, 7, 9, 10]  # 7 episodes on 3 environments: resets with the next seed
    envs = ScriptedVectorEnv(3)
    aggregate = dagger.Aggregate()
    aggregate.add(np.ones((2, 40)), np.ones((2, 57), bool), [1, 2], round_=1)  # an earlier round
    played = dagger.play_round(envs, LearnerPicksTPlus1(), beta, seeds, np.random.default_rng(0))
    aggregate.extend(played.episodes, 2)
    lengths = [ScriptedVectorEnv.length(s) for s in seeds]
    assert played.states == sum(lengths)
    assert list(played.lengths) == lengths
    assert aggregate.steps == 2 + sum(lengths)
    data = aggregate.arrays()
    new = data["round"] == 2
    assert new.sum() == sum(lengths) and (data["round"][:2] == 1).all()
    # Exactly the visited states: each (seed, t) once, none of an idle or ended environment.
    visited = sorted(
        zip(data["obs"][new, 0].astype(int), data["obs"][new, 1].astype(int), strict=True)
    )
    assert visited == sorted((s, t) for s in seeds for t in range(ScriptedVectorEnv.length(s)))
    for obs, mask, label in zip(
        data["obs"][new], data["mask"][new], data["action"][new], strict=True
    ):
        s, t = int(obs[0]), int(obs[1])
        assert label == s % 50 + 5  # the teacher's action from the info, whoever acted
        assert np.flatnonzero(mask).tolist() == sorted({0, t + 1, s % 50 + 5})
    # The mixture: β = 1 executes the teacher's action, β = 0 the learner's.
    recorded = [(s, t, a) for s, t, a in envs.taken if s in seeds and t >= 0]
    for s, t, a in recorded:
        assert a == (s % 50 + 5 if beta == 1.0 else t + 1)
    assert played.teacher_steps == (sum(lengths) if beta == 1.0 else 0)
    # Seeds were given in order, each once; the final scores are the info's at each end.
    assert sorted(s for batch in envs.resets for s in batch if s in seeds) == seeds
    assert list(played.scores) == [100 * s + ScriptedVectorEnv.length(s) for s in seeds]


class LearnerRightOnEvenSteps(checkpoint.BasePolicy):
    """A learner that takes the teacher's action (``s % 50 + 5``) at even steps ``t``, and
    ``t + 1`` (never the teacher's in the scripted env) at odd ones."""

    def predict(self, obs, state=None, episode_start=None, deterministic=True, action_masks=None):
        s, t = obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64)
        return np.where(t % 2 == 0, s % 50 + 5, t + 1), state


@pytest.mark.parametrize("beta", [1.0, 0.5, 0.0])
def test_a_round_counts_the_learners_agreement_with_the_teacher(beta: float) -> None:
    seeds = [3, 4, 5, 6, 7, 9, 10]
    played = dagger.play_round(
        ScriptedVectorEnv(3), LearnerRightOnEvenSteps(), beta, seeds, np.random.default_rng(0)
    )
    if beta == 1.0:  # the learner is not asked
        assert played.choices == 0 and math.isnan(played.agreement)
        return
    # Every recorded state has three legal actions; the learner is asked in each, whoever acts.
    steps = [t for s in seeds for t in range(ScriptedVectorEnv.length(s))]
    assert played.choices == len(steps)
    assert played.agreed == sum(t % 2 == 0 for t in steps)
    assert played.agreement == pytest.approx(played.agreed / len(steps))


def test_the_mixture_follows_beta() -> None:
    rng = np.random.default_rng(1)
    teacher, learner = np.full(20_000, 7), np.full(20_000, 3)
    actions, from_teacher = dagger.mix_actions(teacher, learner, 0.25, rng)
    assert np.array_equal(actions == 7, from_teacher)
    assert abs(from_teacher.mean() - 0.25) < 0.02
    assert (dagger.mix_actions(teacher, learner, 1.0, rng)[0] == 7).all()
    assert (dagger.mix_actions(teacher, learner, 0.0, rng)[0] == 3).all()


def test_noise_replaces_only_the_learners_actions_and_only_by_legal_ones() -> None:
    rng = np.random.default_rng(2)
    n = 20_000
    actions = np.full(n, 3)
    learner_acted = np.arange(n) % 2 == 0
    mask = np.zeros((n, NUM_ACTIONS), bool)
    mask[:, [3, 10, 20, 30]] = True
    noised = dagger.add_noise(actions, learner_acted, mask, 0.4, rng)
    changed = noised != actions
    assert not changed[~learner_acted].any()
    assert np.isin(noised, [3, 10, 20, 30]).all()
    # Drawn uniformly over the 4 legal actions, one of which is the learner's own: 0.4 · 3/4.
    assert abs(changed[learner_acted].mean() - 0.3) < 0.02
    assert (dagger.add_noise(actions, learner_acted, mask, 0.0, rng) == 3).all()
    with pytest.raises(AgentsError, match="learner-noise"):
        dagger.DaggerConfig(learner_noise=1.5)


def test_schedules_seeds_and_refusals() -> None:
    assert dagger.betas(dagger.DaggerConfig(rounds=4, p=0.5)) == [1.0, 0.5, 0.25, 0.125]
    assert dagger.betas(dagger.DaggerConfig(rounds=3, schedule="first")) == [1.0, 0.0, 0.0]
    seeds = dagger.training_seeds(995, 10)
    assert seeds == [995, 996, 997, 998, 999, 1100, 1101, 1102, 1103, 1104]
    assert not set(dagger.training_seeds(0, 3000)) & set(range(1000, 1100))
    # Nor the 400 seeds experiments are kept or not on.
    assert dagger.training_seeds(1995, 10) == [1995, 1996, 1997, 1998, 1999, *range(2400, 2405)]
    with pytest.raises(AgentsError, match="--teacher"):
        dagger.DaggerConfig(teacher="oracle")
    aggregate = dagger.Aggregate()
    mask = np.zeros((1, 57), bool)
    mask[0, 0] = True
    with pytest.raises(AgentsError, match="illegal"):
        aggregate.add(np.zeros((1, 40)), mask, [4], round_=1)


def test_a_short_dagger_run_beats_random_on_unseen_seeds(
    server_address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "dagger"
    argv = ["train", "dagger", "--teacher", "expert", "--rounds", "2"]
    argv += ["--episodes-per-round", "8", "--num-envs", "8", "--epochs", "6"]
    argv += ["--out", str(out), "--address", server_address]
    assert main(argv) == 0
    assert "dagger (teacher expert), 2 rounds" in capsys.readouterr().out
    description = json.loads((out / "checkpoint.json").read_text())
    assert description["algorithm"] == "dagger"
    assert description["config"]["betas"] == [1.0, 0.5]
    rows = list(train_dagger.iter_rows(out))
    assert [int(r["round"]) for r in rows] == [1, 2]
    assert int(rows[-1]["dataset_steps"]) == description["data"]["steps"]
    policy = load(out)
    episodes = 4
    random_scores, _ = evaluate_policy(
        lambda obs, mask: np.random.default_rng(0).integers(0, 57, size=len(obs)),
        episodes,
        seed=1000,
        address=server_address,
    )
    scores, _ = evaluate_policy(policy.act, episodes, seed=1000, address=server_address)
    # Random play loses its five groups fast (about -1,300); the expert scores about 9,000.
    assert scores.mean() > max(random_scores.mean(), 0) + 3000, scores


def test_seat_weights_scale_the_masked_loss_of_seat_states() -> None:
    import jax.numpy as jnp

    from dinerdash_agents.supervised import cross_entropy

    rng = np.random.default_rng(2)
    logits = jnp.asarray(rng.normal(size=(6, 57)), jnp.float32)
    mask = np.zeros((6, 57), bool)
    mask[:, [0, 3, 15, 20]] = True
    actions = np.array([0, 3, 15, 20, 0, 15])
    ones = dagger.seat_weights(actions, 1.0)
    assert np.array_equal(ones, np.ones(6, np.float32))
    plain = cross_entropy(logits, jnp.asarray(actions), jnp.asarray(mask))
    same = dagger.weighted_cross_entropy(logits, jnp.asarray(actions), mask, ones)
    assert float(same) == pytest.approx(float(plain), rel=1e-6)
    weights = dagger.seat_weights(actions, 10.0)  # 3 seat states of 6: 10 / 5.5 and 1 / 5.5
    np.testing.assert_allclose(weights, np.array([1, 1, 10, 10, 1, 10]) / 5.5, rtol=1e-6)


def _restaurant(tables=(), queue=(), hands=(0, 0)) -> np.ndarray:
    """An observation: ``tables`` of (table, state, seats, level), ``queue`` of (level, size)."""
    obs = np.zeros(OBSERVATION_SIZE, np.float32)
    obs[2:18:3] = -1
    for t, state, seats, level in tables:
        obs[3 * (t - 1) : 3 * t] = (state, seats, level)
    for g, (level, size) in enumerate(queue):
        obs[24 + 2 * g : 26 + 2 * g] = (level, size)
    obs[38:40] = hands
    return obs


def _slot(features: np.ndarray, slot: int) -> tuple[float, float, float]:
    """(steps since the level changed, type 2, changed) of memory slot ``slot`` (tables 0..5,
    queue places 6..12) of an augmented observation."""
    count, type2, changed = features[OBSERVATION_SIZE + 3 * slot : OBSERVATION_SIZE + 3 * slot + 3]
    return round(count * dagger.MEMORY_CAP), type2, changed


def test_memory_follows_each_groups_patience_through_the_queue_and_to_its_table() -> None:
    memory = dagger.MemoryFeatures()
    start = _restaurant(queue=[(3, 2)])
    assert dagger.is_episode_start(start)
    # Environment 1 stays at the start; environment 0 plays the story below.
    story = [
        start,
        start,
        start,
        _restaurant(queue=[(2, 2)]),  # the grace buffer is gone: level 3 -> 2
        _restaurant(queue=[(2, 2), (4, 5)]),  # a type-2 group of 5 arrives
        _restaurant(queue=[(2, 2), (4, 5)]),
        # group 1 (2 people) sits at table 3 (2 seats); the group of 5 moves up to place 1
        _restaurant(tables=[(3, 1, 2, 2)], queue=[(4, 5)]),
        _restaurant(tables=[(3, 1, 2, 2)], queue=[(3, 5)]),
    ]
    rows = [memory.augment(np.stack([obs, start])) for obs in story]
    assert all(r.shape == (2, OBSERVATION_SIZE + dagger.MEMORY_SIZE) for r in rows)
    np.testing.assert_array_equal(rows[-1][:, :OBSERVATION_SIZE], np.stack([story[-1], start]))
    first = 6
    assert [_slot(r[0], first) for r in rows[:4]] == [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 0, 1)]
    assert _slot(rows[5][0], first) == (2, 0, 1)
    assert _slot(rows[5][0], first + 1) == (1, 1, 0)
    # Seated: table 3 carries the group's memory on, the queue's place 1 is the group of 5.
    assert _slot(rows[6][0], 2) == (3, 0, 1)
    assert _slot(rows[6][0], first) == (2, 1, 0)
    assert _slot(rows[7][0], first) == (0, 1, 1)
    assert _slot(rows[7][0], 2) == (4, 0, 1)
    assert all(_slot(rows[7][0], t) == (0, 0, 0) for t in (0, 1, 3, 4, 5))
    # The other environment's unchanged start goes on counting (its first group waits alone).
    assert [_slot(r[1], first)[0] for r in rows] == list(range(len(rows)))
    # A new episode starts the memory afresh; the counter is capped.
    again = memory.augment(np.stack([start, start]))
    assert _slot(again[0], first) == (0, 0, 0) and _slot(again[0], 2) == (0, 0, 0)
    assert _slot(again[1], first)[0] == len(rows)
    busy = _restaurant(tables=[(1, 4, 4, 2)], queue=[(3, 2)])
    for _ in range(dagger.MEMORY_CAP + 5):
        last = memory.augment(np.stack([busy, busy]))
    assert _slot(last[0], 0)[0] == dagger.MEMORY_CAP


@pytest.mark.parametrize("timers", [False, True])
def test_a_checkpoint_with_memory_plays_through_its_own_memory(
    tmp_path: Path, timers: bool
) -> None:
    from dinerdash_agents import checkpoint

    config = dagger.DaggerConfig(memory=True, timers=timers, hidden=8, layers=1)
    model = dagger.init(config, 0)
    description = {"name": "m", "algorithm": "dagger", "config": config.to_json()}
    checkpoint.save(tmp_path / "m", model, description)
    policy = load(tmp_path / "m")
    start = _restaurant(queue=[(3, 2)])
    obs = np.stack([start, _restaurant(queue=[(2, 2)])])
    mask = np.zeros((2, NUM_ACTIONS), np.bool_)
    mask[:, :2] = True
    expected = dagger.greedy_actions(model, dagger.MemoryFeatures(timers).augment(obs), mask)
    np.testing.assert_array_equal(policy.act(obs, mask), expected)
    timer_size = dagger.TIMERS_SIZE if timers else 0
    assert dagger.input_size(config) == OBSERVATION_SIZE + dagger.MEMORY_SIZE + timer_size
    with pytest.raises(AgentsError, match="need memory"):
        dagger.DaggerConfig(timers=True)


def test_told_the_actions_the_memory_keeps_each_groups_exact_patience() -> None:
    """With ``patience``, the features end with each slot's P / 800 and B / 400, which are the
    rules' own (the plain-Python simulator's groups, matched step for step against the recorded
    reference in tests/test_reference.py) at every step of four games played by a mixture of
    the expert and random legal actions, across episode ends. Without the actions, the memory
    cannot tell which of two like groups side by side was seated, and goes wrong."""
    from dinerdash_bench.reference import Game

    width = OBSERVATION_SIZE + dagger.memory_size(True, lives=True, patience=True)
    assert width == OBSERVATION_SIZE + dagger.MEMORY_SIZE + dagger.LIVES_SIZE + 26
    rng = np.random.default_rng(1)
    games = [Game() for _ in range(4)]
    seeds = iter(range(7000, 8000))
    obs = np.array([g.reset(seed=next(seeds)) for g in games], np.float32)
    told, blind = (
        dagger.MemoryFeatures(lives=True, patience=True),
        dagger.MemoryFeatures(patience=True),
    )
    exact = wrong_blind = ends = 0
    for _ in range(1500):
        rows, blind_rows = told(obs), blind(obs)
        assert rows.shape == (4, width)
        for k, game in enumerate(games):
            r = game.restaurant
            groups = [t.group for t in r.tables] + list(r.queue)
            truth = [(g.patience / 800, g.buffer / 400) if g else (0, 0) for g in groups]
            truth = np.array(truth + [(0, 0)] * (13 - len(truth)), np.float32).ravel()
            np.testing.assert_allclose(rows[k, -26:], truth, atol=1e-6)
            exact += 1
            wrong_blind += not np.allclose(blind_rows[k, -26:], truth, atol=1e-6)
        actions = []
        for game in games:
            legal = np.flatnonzero(game.action_mask())
            expert = rng.random() < 0.6
            actions.append(game.expert_action() if expert else int(rng.choice(legal)))
        told.acted(np.array(actions))
        for k, (game, a) in enumerate(zip(games, actions, strict=True)):
            o, _, done = game.step(a)
            if done:
                o, ends = game.reset(seed=next(seeds)), ends + 1
            obs[k] = o
    assert exact == 6000 and ends > 0 and wrong_blind > 0


def test_told_the_seat_the_memory_follows_the_group_seated_of_two_alike() -> None:
    """Two groups of 2 at level 2 wait side by side, the second for longer in its level; the
    first is seated at table 3. Told the action, the memory carries the second group's count on
    in the queue and the first's to the table; from the observations alone it takes the first
    group's count to stay."""
    start = _restaurant(queue=[(3, 2)])
    story = [start] + [_restaurant(queue=[(2, 2), (2, 2)])] * 4
    # The memory's groups, as if the second had been at level 2 longer: set up by hand.
    seated = _restaurant(tables=[(3, 1, 2, 2)], queue=[(2, 2)])
    counts = {}
    for told in (True, False):
        memory = dagger.MemoryFeatures(patience=True)
        for obs in story:
            memory(obs[None])
        first, second = memory._memories[0].queue
        first.count, second.count = 1, 9
        if told:
            memory.acted(np.array([seat_action(1, 3)]))
        row = memory(seated[None])[0]
        counts[told] = (_slot(row, 2)[0], _slot(row, 6)[0])
    assert counts == {True: (2, 10), False: (10, 2)}


class _Recording(dagger.MemoryFeatures):
    """Patience memory features that keep every batch they compute."""

    def __init__(self) -> None:
        super().__init__(patience=True)
        self.rows: list[np.ndarray] = []

    def augment(self, obs: np.ndarray) -> np.ndarray:
        self.rows.append(super().augment(obs))
        return self.rows[-1]

    __call__ = augment


class _RandomWithMemory(checkpoint.BasePolicy):
    """A learner with a patience memory as its state (told its own choices, as
    :class:`~dinerdash_agents.checkpoint.Policy` does) that picks a random legal action."""

    def __init__(self) -> None:
        super().__init__()
        self.rng = np.random.default_rng(0)
        self.memory = _Recording()
        #: The observations it was shown and its choices, step by step.
        self.seen: list[np.ndarray] = []
        self.choices: list[np.ndarray] = []

    def predict(self, obs, state=None, episode_start=None, deterministic=True, action_masks=None):
        self.seen.append(obs)
        self.memory(obs)
        actions = np.array([self.rng.choice(np.flatnonzero(m)) for m in action_masks])
        self.choices.append(actions)
        self.memory.acted(actions)
        return actions, self.memory


@pytest.mark.parametrize("learner_memory", ["played", "own"])
def test_a_round_tells_the_memories_the_actions_it_played(
    server_address: str, learner_memory: str
) -> None:
    """A round of the mixture on a real server, recorded with ``--patience``'s memory (``train
    dagger --memory --patience``): each episode's recorded features are those of a memory told,
    step by step, the actions played, and so are the learner's own, though half the actions
    played were the teacher's; with ``--learner-memory own``, the learner's are those of a memory
    told its own choices, and differ from the recorded ones."""
    import gymnasium

    config = dagger.DaggerConfig(
        memory=True, patience=True, teacher="expert", learner_memory=learner_memory
    )
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0", num_envs=2, address=server_address, expert=True
    )
    memory, learner = _Recording(), _RandomWithMemory()
    rng = np.random.default_rng(0)
    try:
        played = dagger.play_round(envs, learner, 0.5, [5, 6, 7], rng, memory, learner_memory)
    finally:
        envs.close()
    assert [len(e.obs) > 20 for e in played.episodes] == [True] * 3
    assert 0 < played.teacher_steps < played.states
    for episode in played.episodes:
        assert episode.obs.shape[1] == dagger.input_size(config)
    learners, recorded = np.stack(learner.memory.rows), np.stack(memory.rows)
    if learner_memory == "played":
        np.testing.assert_array_equal(learners, recorded)
        return
    assert not np.array_equal(learners, recorded)
    own = dagger.MemoryFeatures(patience=True)
    rows = []
    for obs, choices in zip(learner.seen, learner.choices, strict=True):
        rows.append(own.augment(obs))
        own.acted(choices)
    np.testing.assert_array_equal(learners, np.stack(rows))
    with pytest.raises(AgentsError, match="only the patience memory"):
        dagger.DaggerConfig(memory=True, learner_memory="own")


def test_the_groups_lost_counted_from_the_observations_are_infos(server_address: str) -> None:
    """The count of groups lost that the memory keeps from the observations alone is the
    server's ``info["lost"]`` at every step: under the expert (groups run away from tables),
    a random legal policy and one that only waits (the queue fills, groups walk out of it, a
    full queue takes in the next)."""
    from dinerdash import DinerDashEnv

    rng = np.random.default_rng(0)
    policies = {
        "expert": lambda info: info["expert_action"],
        "random": lambda info: rng.choice(np.flatnonzero(info["action_mask"])),
        "wait": lambda info: 0,
    }
    lost = {name: 0 for name in policies}
    with DinerDashEnv(address=server_address, expert=True) as env:
        for name, policy in policies.items():
            for seed in (3, 4):
                memory = dagger.MemoryFeatures(lives=True)
                obs, info = env.reset(seed=seed)
                row = memory.augment(obs[None])[0]
                assert row.shape == (OBSERVATION_SIZE + dagger.MEMORY_SIZE + dagger.LIVES_SIZE,)
                for _ in range(3000):
                    obs, _, terminated, truncated, info = env.step(policy(info))
                    counted = memory.augment(obs[None])[0][-dagger.LIVES_SIZE :]
                    assert counted.sum() == 1 and counted.argmax() == min(info["lost"], 4), name
                    if terminated or truncated:
                        break
                lost[name] += info["lost"]
    assert lost == {"expert": 10, "random": 10, "wait": 10}
    with pytest.raises(AgentsError, match="need memory"):
        dagger.DaggerConfig(lives=True)


def test_the_timers_follow_reading_eating_cooking_and_arrivals(server_address: str) -> None:
    """An expert episode's timers against the rules' fixed durations: reading and eating last 10
    steps, an order handed to the kitchen is food on a counter 10 steps later, and a group
    arrives every 9 steps while the queue has room."""
    from dinerdash import DinerDashEnv

    memory = dagger.MemoryFeatures(timers=True)
    timers = OBSERVATION_SIZE + dagger.MEMORY_SIZE
    with DinerDashEnv(address=server_address, expert=True) as env:
        obs, info = env.reset(seed=7)
        last, rows = obs, [memory.augment(obs[None])[0]]
        assert rows[0].shape == (timers + dagger.TIMERS_SIZE,)
        seen = {"reading": 0, "eating": 0, "cooking": 0, "arrival": 0}
        for _ in range(600):
            obs, _, terminated, truncated, info = env.step(info["expert_action"])
            row = memory.augment(obs[None])[0]
            before = np.rint(rows[-1][timers:] * dagger.TIMER_CAP).astype(int)
            for t in range(6):
                was, now = int(last[3 * t]), int(obs[3 * t])
                if (was, now) in ((1, 2), (4, 6)):
                    assert before[t] == 9, (t, was, now)
                    seen["reading" if was == 1 else "eating"] += 1
                if last[18 + t] == 0 and obs[18 + t] == 1:
                    assert before[6 + t] == 10, t
                    seen["cooking"] += 1
            if len(dagger._queue(obs)) > len(dagger._queue(last)):
                assert round(row[-1] * dagger.TIMER_CAP) == 0
                seen["arrival"] += 1
            last = obs
            rows.append(row)
            if terminated or truncated:
                break
    assert min(seen.values()) >= 5, seen
