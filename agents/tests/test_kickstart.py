"""Kick-started PPO: the auxiliary loss pulls the policy toward the teacher's action on a
hand-made batch, the critic warm-up leaves the actor untouched, the schedule falls as configured,
and a short run from a BC checkpoint trained here beats that BC policy, its starting point, on
unseen seeds (then resumes and loads as a checkpoint)."""

from __future__ import annotations

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from dinerdash.game import NUM_ACTIONS, OBSERVATION_HIGH, OBSERVATION_SIZE

from dinerdash_agents import bc, dagger, kickstart
from dinerdash_agents.checkpoint import load
from dinerdash_agents.cli import main as agents_main
from dinerdash_agents.errors import AgentsError
from dinerdash_agents.evaluate import evaluate_policy
from dinerdash_agents.supervised import masked_logits
from dinerdash_agents.train_imitation import train_checkpoint
from dinerdash_agents.train_rl import train_rl


def _batch(n: int, seed: int = 0, rewards: bool = True) -> dict[str, np.ndarray]:
    """A hand-made iteration of one step of ``n`` environments, time-major as the update takes
    it: random observations within bounds, about half the actions legal, the teacher's action a
    legal one; ``rewards=False``: no reward and no value, so every advantage is 0."""
    rng = np.random.default_rng(seed)
    obs = (rng.random((n, OBSERVATION_SIZE)) * OBSERVATION_HIGH).astype(np.float32)
    mask = rng.random((n, NUM_ACTIONS)) < 0.5
    mask[:, 0] = True
    teacher = np.array([rng.choice(np.flatnonzero(m)) for m in mask], np.int32)
    scale = 1.0 if rewards else 0.0
    batch = {
        "obs": obs,
        "mask": mask,
        "actions": np.zeros(n, np.int32),
        "logp": np.full(n, -np.log(NUM_ACTIONS), np.float32),
        "rewards": scale * rng.normal(size=n).astype(np.float32),
        "values": scale * rng.normal(size=n).astype(np.float32),
        "next_values": np.zeros(n, np.float32),
        "terminated": np.ones(n, np.float32),
        "done": np.ones(n, np.float32),
        "expert_actions": teacher,
    }
    return {k: v[None] for k, v in batch.items()}


def _teacher_logp(model, batch) -> float:
    logits = masked_logits(model(batch["obs"][0]), batch["mask"][0])
    logp = jax.nn.log_softmax(logits)
    teacher = batch["expert_actions"][0]
    return float(np.take_along_axis(np.asarray(logp), teacher[:, None], 1).mean())


def _trainer(**overrides) -> kickstart.KickstartTrainer:
    config = kickstart.KickstartConfig(num_envs=8, num_steps=32, bc_hidden=64, **overrides)
    return kickstart.KickstartTrainer(config, 10 * 8 * 32, seed=0, load_init=False)


def test_the_kick_loss_pulls_the_policy_toward_the_teachers_action():
    trainer = _trainer(ent_coef=0.0, learning_rate=1e-3, anneal_lr=False)
    batch = _batch(256, rewards=False)  # no advantage: only the kick-starting term moves it
    coefs = {"kick": np.array(1.0, np.float32), "policy_on": np.array(1.0, np.float32)}
    before = _teacher_logp(trainer.model, batch)
    model, opt_state = trainer.model, trainer.opt_state
    for i in range(20):
        model, opt_state, stats = trainer._update(
            model, opt_state, batch, jax.random.PRNGKey(i), coefs
        )
    after = _teacher_logp(model, batch)
    assert after > before + 0.5, (before, after)
    assert np.isfinite(stats["kick_loss"])

    # Without the kick-starting term (λ_k = 0) and without advantage, the actor stays put.
    coefs["kick"] = np.array(0.0, np.float32)
    still, _, _ = trainer._update(
        trainer.model, trainer.opt_state, batch, jax.random.PRNGKey(0), coefs
    )
    np.testing.assert_allclose(_teacher_logp(still, batch), before, atol=1e-5)


def test_the_critic_warm_up_leaves_the_actor_unchanged():
    trainer = _trainer(critic_warmup=3)
    batch = _batch(256, seed=1)
    coefs = kickstart.coefficients(trainer.config, 0, trainer.iterations)
    assert float(coefs["policy_on"]) == 0.0 and float(coefs["kick"]) > 0
    model, opt_state = trainer.model, trainer.opt_state
    for i in range(3):
        model, opt_state, _ = trainer._update(model, opt_state, batch, jax.random.PRNGKey(i), coefs)
    old, new = trainer.model.actor, model.actor
    for a, b in zip(
        jax.tree.leaves(eqx.filter(old, eqx.is_array)),
        jax.tree.leaves(eqx.filter(new, eqx.is_array)),
        strict=True,
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(
        np.asarray(trainer.model.critic[0].weight), np.asarray(model.critic[0].weight)
    )
    # After the warm-up the policy moves.
    on = kickstart.coefficients(trainer.config, 3, trainer.iterations)
    assert float(on["policy_on"]) == 1.0
    moved, _, _ = trainer._update(model, opt_state, batch, jax.random.PRNGKey(9), on)
    assert not np.array_equal(
        np.asarray(moved.actor.out.weight), np.asarray(model.actor.out.weight)
    )


def test_the_critic_reads_the_memory_features_only_when_told():
    dagger_config = dagger.DaggerConfig(memory=True, hidden=16, layers=1).to_json()
    obs = np.concatenate([_batch(4)["obs"][0], np.zeros((4, dagger.memory_size(True)))], 1)
    moved = obs.copy()
    moved[:, OBSERVATION_SIZE:] = 1.0
    for critic_memory in (False, True):
        config = kickstart.KickstartConfig(
            init_algorithm="dagger", dagger_config=dagger_config, critic_memory=critic_memory
        )
        model = kickstart.init(config)
        width = obs.shape[1] if critic_memory else OBSERVATION_SIZE
        assert model.critic[0].in_features == width
        same = np.allclose(model.value(jnp.asarray(obs)), model.value(jnp.asarray(moved)))
        assert same is not critic_memory
    # An actor without memory features leaves the critic nothing more to read: refused.
    with pytest.raises(AgentsError, match="has none"):
        _trainer(critic_memory=True)


def test_the_critic_reads_the_groups_lost_and_the_actor_does_not():
    dagger_config = dagger.DaggerConfig(memory=True, hidden=16, layers=1).to_json()
    width = OBSERVATION_SIZE + dagger.memory_size(True)
    obs = np.concatenate([_batch(5)["obs"][0], np.zeros((5, dagger.memory_size(True)))], 1)
    trainer = _trainer(init_algorithm="dagger", dagger_config=dagger_config, critic_lives=True)
    seen = trainer.with_info(obs, {"lost": np.array([0, 1, 2, 4, 7])})
    assert seen.shape == (5, width + kickstart.LOST_COLUMNS)
    np.testing.assert_array_equal(seen[:, :width], obs)
    np.testing.assert_array_equal(seen[:, width:].argmax(1), [0, 1, 2, 4, 4])  # 7: "4 or more"
    assert trainer._buffers.obs.shape[-1] == seen.shape[1]
    model = trainer.model
    assert model.critic[0].in_features == OBSERVATION_SIZE + kickstart.LOST_COLUMNS
    other = seen.copy()
    other[:, width:] = np.eye(kickstart.LOST_COLUMNS)[[3, 3, 3, 3, 0]]
    # The actor reads its own columns only: the policy that plays does not see the lives.
    np.testing.assert_array_equal(model(jnp.asarray(seen)), model(jnp.asarray(obs)))
    assert not np.allclose(model.value(jnp.asarray(seen)), model.value(jnp.asarray(other)))
    # Without the flag the model's input is what the view gives.
    plain = _trainer(init_algorithm="dagger", dagger_config=dagger_config)
    assert plain.with_info(obs, {"lost": np.zeros(5)}) is obs


def test_the_kick_coefficient_follows_its_schedule():
    linear = kickstart.KickstartConfig(kick_coef=2.0, kick_until=0.5, critic_warmup=10)
    values = [kickstart.kick_coefficient(linear, i, 110) for i in (0, 10, 35, 60, 100)]
    assert values == pytest.approx([2.0, 2.0, 1.0, 0.0, 0.0])
    geometric = kickstart.KickstartConfig(kick_schedule="geometric", kick_decay=0.5)
    assert kickstart.kick_coefficient(geometric, geometric.critic_warmup + 2, 100) == 0.25
    with pytest.raises(TypeError, match="teacher"):
        kickstart.KickstartConfig(teacher="oracle")


def test_a_short_kickstarted_run_beats_its_bc_starting_point(
    server_address: str, expert_demos: Path, tmp_path: Path
):
    from dinerdash.evaluation import evaluate_through_env

    init = tmp_path / "bc"
    train_checkpoint("bc", expert_demos, init, config=bc.BCConfig(hidden=64, epochs=3))
    out = tmp_path / "kick"
    config = kickstart.KickstartConfig(num_envs=16, num_steps=64, critic_warmup=2)
    # 12 iterations: measured, 8,964 on the seeds below against BC's 8,478 (after 6: 8,213,
    # still below BC while the critic and the pull settle).
    trainer = train_rl(
        "ppo-kickstart",
        12 * 16 * 64,
        out,
        address=server_address,
        config=config,
        init=init,
        teacher="expert",
        progress=False,
    )
    assert trainer.iteration == 12
    description = json.loads((out / "checkpoint.json").read_text())
    assert description["config"]["init"] == str(init)
    assert description["config"]["kick_schedule"] == "linear"
    # Trained on: the BC start's demonstrations (seeds 0..19) and the first resets (0..15).
    assert description["data"]["seed_ranges"] == [[0, 19]]

    seeds = {"seed": 700, "address": server_address, "num_envs": 8}
    policy = load(out)
    assert policy.algorithm == "ppo-kickstart"
    scores, _ = evaluate_policy(policy.act, 8, max_steps=3000, **seeds)
    started, _ = evaluate_policy(load(init).act, 8, max_steps=3000, **seeds)
    random, _ = evaluate_through_env("random", 8, max_steps=3000, **seeds)
    assert started.mean() > random.mean() + 5000, (started.mean(), random.mean())
    assert scores.mean() > started.mean(), (scores.mean(), started.mean())

    # Resumed from the CLI: one more iteration, the teacher and the actor kept.
    argv = ["train", "ppo-kickstart", "--steps", str(13 * 16 * 64), "--resume", str(out)]
    assert agents_main([*argv, "--out", str(out), "--address", server_address]) == 0
    again = json.loads((out / "checkpoint.json").read_text())
    assert again["training"]["iterations"] == 13
    assert again["config"]["teacher"] == "expert"


def test_kickstart_refuses_a_missing_or_foreign_init(server_address: str, tmp_path: Path):
    with pytest.raises(AgentsError, match="--init"):
        train_rl("ppo-kickstart", 100, tmp_path / "a", address=server_address, progress=False)
    with pytest.raises(AgentsError, match="ppo-kickstart's"):
        train_rl("ppo-masked", 100, tmp_path / "b", init=tmp_path, progress=False)


def test_a_run_from_a_dagger_learner_with_memory_keeps_its_memory(
    server_address: str, tmp_path: Path
):
    from dinerdash_agents import checkpoint

    # A DAgger learner with memory features and timers (untrained: what matters is its input's
    # shape; the committed ppo-kickstart-memory replays the features without timers).
    config = dagger.DaggerConfig(memory=True, timers=True, hidden=32, layers=2)
    init = tmp_path / "dagger"
    description = {"name": "d", "algorithm": "dagger", "config": config.to_json()}
    checkpoint.save(init, dagger.init(config, 3), description)
    # Two iterations, both critic warm-up: the actor must come out exactly as it went in.
    out = tmp_path / "kick"
    run = kickstart.KickstartConfig(num_envs=8, num_steps=32, critic_warmup=2)
    trainer = train_rl(
        "ppo-kickstart",
        2 * 8 * 32,
        out,
        address=server_address,
        config=run,
        init=init,
        teacher="expert",
        progress=False,
    )
    width = OBSERVATION_SIZE + dagger.MEMORY_SIZE + dagger.TIMERS_SIZE
    assert trainer._buffers.obs.shape == (32, 8, width)
    # The memory features the actor acted on: counts in [0, 1], some of them under way.
    memory = trainer._buffers.obs[..., OBSERVATION_SIZE:]
    assert memory.min() >= 0 and memory.max() <= 1 and memory.any()
    saved = json.loads((out / "checkpoint.json").read_text())["config"]
    assert saved["init_algorithm"] == "dagger" and saved["dagger_config"]["memory"] is True
    assert saved["dagger_config"]["timers"] is True
    # Played from its checkpoint, it sees its memory as the DAgger learner does: the same
    # actions, so the same scores, on the same seeds.
    seeds = {"seed": 2000, "address": server_address, "num_envs": 4, "max_steps": 400}
    kicked, _ = evaluate_policy(load(out).act, 4, **seeds)
    learner, _ = evaluate_policy(load(init).act, 4, **seeds)
    np.testing.assert_array_equal(kicked, learner)
    # Other checkpoints are refused as a start.
    with pytest.raises(AgentsError, match="'bc' or a 'dagger'"):
        train_rl("ppo-kickstart", 100, tmp_path / "x", address=server_address, init=out)


def test_the_cli_sets_the_ppo_stage_hyper_parameters(server_address: str, tmp_path: Path, capsys):
    from dinerdash_agents import checkpoint

    config = dagger.DaggerConfig(memory=True, hidden=16, layers=1)
    init = tmp_path / "dagger"
    description = {"name": "d", "algorithm": "dagger", "config": config.to_json()}
    checkpoint.save(init, dagger.init(config, 3), description)
    out = tmp_path / "kick"
    argv = ["train", "ppo-kickstart", "--init", str(init), "--kick-coef", "0", "--steps", "512"]
    argv += ["--num-envs", "8", "--address", server_address]
    flags = ["--learning-rate", "1e-4", "--gamma", "0.99", "--gae-lambda", "0.9"]
    assert agents_main([*argv, *flags, "--ent-coef", "0.01", "--out", str(out)]) == 0
    saved = json.loads((out / "checkpoint.json").read_text())["config"]
    assert (saved["learning_rate"], saved["gamma"], saved["gae_lambda"]) == (1e-4, 0.99, 0.9)
    assert saved["ent_coef"] == 0.01 and saved["kick_coef"] == 0.0
    # Out of range: refused before a run starts, naming the setting.
    for flag, value, allowed in (
        ("--gamma", "1.5", "gamma is 1.5; it must be in (0, 1]"),
        ("--gae-lambda", "-0.1", "gae_lambda is -0.1; it must be in [0, 1]"),
        ("--learning-rate", "0", "learning_rate is 0.0; it must be above 0"),
        ("--ent-coef", "-1", "ent_coef is -1.0; it must be 0 or more"),
    ):
        bad = tmp_path / f"bad{flag}"
        assert agents_main([*argv, flag, value, "--out", str(bad)]) == 1
        assert allowed in capsys.readouterr().err
        assert not bad.exists()


@pytest.mark.parametrize(("learnt", "patience"), [(False, False), (False, True), (True, False)])
def test_the_actor_counts_the_groups_lost_and_starts_as_its_init_played(
    server_address: str, tmp_path: Path, learnt: bool, patience: bool
):
    """``learnt``: the DAgger init has the exact patience features already (their block then
    follows the new groups-lost block); ``patience``: the run adds them."""
    from dinerdash_agents import checkpoint

    config = dagger.DaggerConfig(memory=True, patience=learnt, hidden=32, layers=2)
    init = tmp_path / "dagger"
    description = {"name": "d", "algorithm": "dagger", "config": config.to_json()}
    learner_model = dagger.init(config, 3)
    checkpoint.save(init, learner_model, description)
    out = tmp_path / "kick"
    run = kickstart.KickstartConfig(
        num_envs=8, num_steps=32, critic_warmup=1, actor_lives=True, actor_patience=patience
    )
    common = {"address": server_address, "teacher": "expert", "progress": False}
    trainer = train_rl("ppo-kickstart", 8 * 32, out, config=run, init=init, **common)
    # The actor's inputs: the memory features, the groups lost one-hot, then (with patience,
    # learnt or added) each group's P and B. Its first layer reads the blocks its init learnt
    # with the init's weights, the others with weights 0 (the iteration was the critic's
    # warm-up).
    width = OBSERVATION_SIZE + dagger.MEMORY_SIZE
    lives = slice(width, width + dagger.LIVES_SIZE)
    pat = dagger.PATIENCE_SIZE if learnt or patience else 0
    rows = trainer._buffers.obs
    assert rows.shape == (32, 8, width + dagger.LIVES_SIZE + pat)
    np.testing.assert_array_equal(rows[..., lives].sum(-1), 1)
    first = trainer.model.actor.layers[0].weight
    old = learner_model.layers[0].weight
    assert first.shape[1] == width + dagger.LIVES_SIZE + pat and not first[:, lives].any()
    np.testing.assert_array_equal(first[:, :width], old[:, :width])
    if learnt:
        np.testing.assert_array_equal(first[:, lives.stop :], old[:, width:])
    else:
        assert not first[:, lives.stop :].any()
    saved = json.loads((out / "checkpoint.json").read_text())["config"]
    assert saved["actor_lives"] is True and saved["dagger_config"]["lives"] is True
    assert saved["actor_patience"] is patience
    assert saved["dagger_config"]["patience"] is (learnt or patience)
    # The trainer told each environment's memory the actions it sent: the rows are those of a
    # memory told them (the run's one iteration started at the episodes' resets).
    memory = dagger.MemoryFeatures(lives=True, patience=learnt or patience)
    for t in range(32):
        np.testing.assert_array_equal(memory(rows[t, :, :OBSERVATION_SIZE]), rows[t])
        memory.acted(trainer._buffers.actions[t])
    # So it plays, from its checkpoint, as the DAgger learner it started from.
    seeds = {"seed": 2000, "address": server_address, "num_envs": 4, "max_steps": 400}
    kicked, _ = evaluate_policy(load(out).act, 4, **seeds)
    learner, _ = evaluate_policy(load(init).act, 4, **seeds)
    np.testing.assert_array_equal(kicked, learner)
    # These are memory features: an init without memory is refused.
    bare = tmp_path / "bare"
    plain = dagger.DaggerConfig(hidden=8, layers=1)
    checkpoint.save(bare, dagger.init(plain), {**description, "config": plain.to_json()})
    flag = "--actor-patience" if patience else "--actor-lives"
    run = kickstart.KickstartConfig(actor_lives=not patience, actor_patience=patience)
    with pytest.raises(AgentsError, match=flag):
        train_rl("ppo-kickstart", 100, tmp_path / "x", config=run, init=bare, **common)
