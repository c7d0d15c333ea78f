"""PPO and GAIL: advantages on a hand-made trajectory, masked sampling, a short learning run
against a real local server, the GAIL discriminator, and resuming a checkpointed run."""

from __future__ import annotations

import json
from pathlib import Path

import equinox as eqx
import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from dinerdash.game import NUM_ACTIONS
from gymnasium.vector import AutoresetMode

from dinerdash_agents import gail, ppo
from dinerdash_agents.checkpoint import Policy, load
from dinerdash_agents.cli import main as agents_main
from dinerdash_agents.demos import load_demos
from dinerdash_agents.evaluate import evaluate_policy
from dinerdash_agents.supervised import ILLEGAL_LOGIT


def test_gae_bootstraps_a_truncation_but_not_a_termination():
    # One environment, four steps: step 1 terminates, step 3 is truncated.
    g, lam = 0.9, 0.5
    rewards = jnp.array([[1.0], [2.0], [3.0], [4.0]])
    values = jnp.array([[10.0], [20.0], [30.0], [40.0]])
    # What follows each step: V(obs 1); anything (terminated); V(obs 3); V(step 3's final obs).
    next_values = jnp.array([[20.0], [999.0], [40.0], [7.0]])
    terminated = jnp.array([[0.0], [1.0], [0.0], [0.0]])
    done = jnp.array([[0.0], [1.0], [0.0], [1.0]])
    adv, returns = ppo.gae(rewards, values, next_values, terminated, done, g, lam)
    d3 = 4 + g * 7 - 40  # truncated: bootstraps from the last observation's value
    d2 = 3 + g * 40 - 30
    d1 = 2 - 20  # terminated: nothing follows
    d0 = 1 + g * 20 - 10
    expected = [d0 + g * lam * d1, d1, d2 + g * lam * d3, d3]  # no advantage crosses an end
    np.testing.assert_allclose(np.asarray(adv)[:, 0], expected, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(returns), np.asarray(adv) + np.asarray(values))


def test_sampling_follows_the_probabilities():
    logits = jnp.log(jnp.array([[0.1, 0.0, 0.6, 0.3]] * 20_000))
    u = np.random.default_rng(1).random(20_000, dtype=np.float32)
    actions, logp = ppo.sample_actions(logits, jnp.asarray(u))
    counts = np.bincount(np.asarray(actions), minlength=4) / 20_000
    np.testing.assert_allclose(counts, [0.1, 0.0, 0.6, 0.3], atol=0.02)
    np.testing.assert_allclose(np.exp(np.asarray(logp)), np.array([0.1, 0.0, 0.6, 0.3])[actions])


def test_masked_sampling_never_picks_an_illegal_action():
    rng = np.random.default_rng(0)
    for _ in range(50):
        mask = rng.random((64, NUM_ACTIONS)) < rng.uniform(0.02, 0.5)
        mask[:, 0] = True  # waiting is always legal
        logits = jnp.asarray(rng.normal(0, 30, (64, NUM_ACTIONS)), jnp.float32)
        u = rng.random(64, dtype=np.float32)
        u[:4] = [0.0, 0.999999, np.nextafter(np.float32(1), np.float32(0)), 0.5]  # the edges
        actions, logp = ppo.sample_actions(jnp.where(mask, logits, ILLEGAL_LOGIT), jnp.asarray(u))
        assert mask[np.arange(64), np.asarray(actions)].all()
        assert np.isfinite(np.asarray(logp)).all()


def test_a_short_masked_ppo_run_learns(server_address: str):
    """About 20,000 steps lift the greedy policy far above its untrained self on unseen seeds."""
    config = ppo.PPOConfig(num_envs=32, num_steps=64)
    trainer = ppo.Trainer(config, 20_000, seed=0)

    def greedy_score() -> float:
        policy = Policy(trainer.model, {"algorithm": "ppo-masked"})
        scores, _ = evaluate_policy(
            policy.act, 16, seed=500, address=server_address, num_envs=16, max_steps=3000
        )
        return float(scores.mean())

    before = greedy_score()
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=config.num_envs,
        address=server_address,
        autoreset_mode=AutoresetMode.SAME_STEP,
        max_episode_steps=config.max_episode_steps,
    )
    try:
        trainer.attach(envs)
        while trainer.iteration < trainer.iterations:
            stats = trainer.step()
            assert all(np.isfinite(v) for v in stats.values())
    finally:
        envs.close()
    assert trainer.steps >= 20_000
    after = greedy_score()
    assert after > before + 2000, (before, after)


def test_the_gail_discriminator_separates_expert_pairs_from_random_ones(expert_demos: Path):
    demos = load_demos(expert_demos, 10)
    rng = np.random.default_rng(0)
    expert = {"obs": demos.observations, "actions": demos.actions.astype(np.int32)}
    random = {
        "obs": demos.observations,
        "actions": rng.integers(0, NUM_ACTIONS, len(demos.actions)).astype(np.int32),
    }
    d = gail.Discriminator(jax.random.PRNGKey(0))
    before = float(gail.discriminator_loss(d, expert, random))
    d, _ = gail.fit_discriminator(d, expert, random, steps=300)
    after = float(gail.discriminator_loss(d, expert, random))
    assert after < before
    e = np.asarray(d(expert["obs"], expert["actions"]))
    r = np.asarray(d(random["obs"], random["actions"]))
    accuracy = ((e > 0).mean() + (r < 0).mean()) / 2
    assert accuracy > 0.8, accuracy


def test_resume_continues_from_the_saved_step_count(server_address: str, tmp_path: Path, capsys):
    out = tmp_path / "run"
    small = ["--num-envs", "8", "--address", server_address, "--out", str(out)]
    assert agents_main(["train", "ppo-masked", "--steps", "1500", *small]) == 0
    first = json.loads((out / "checkpoint.json").read_text())
    # Whole iterations of 8 environments x the default num_steps, enough to reach --steps.
    per_iteration = 8 * ppo.PPOConfig().num_steps
    assert first["data"]["environment_steps"] == 3 * per_iteration
    assert len((out / "curve.csv").read_text().splitlines()) == 1 + 3

    resume = ["train", "ppo-masked", "--steps", "2500", "--resume", str(out), *small]
    capsys.readouterr()
    assert agents_main(resume) == 0
    # The resumed process's bar counts only its own steps, so that its rate is not inflated by
    # the earlier process's (it once showed 10^15 env-steps/s).
    bar = capsys.readouterr().err
    assert f" {2 * per_iteration}/{2 * per_iteration} " in bar
    assert f"/{5 * per_iteration} " not in bar
    second = json.loads((out / "checkpoint.json").read_text())
    assert second["data"]["environment_steps"] == 5 * per_iteration
    assert second["training"]["iterations"] == 5
    rows = (out / "curve.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == [per_iteration * i for i in range(1, 6)]
    assert (out / "curve.png").is_file()
    assert load(out).algorithm == "ppo-masked"


def test_rl_bad_input_is_refused_with_a_clear_error(tmp_path: Path, capsys):
    assert agents_main(["train", "gail", "--steps", "100", "--out", str(tmp_path / "g")]) == 1
    assert "gail needs --demos" in capsys.readouterr().err
    assert not (tmp_path / "g").exists()
    bc_dir = tmp_path / "not-rl"
    bc_dir.mkdir()
    (bc_dir / "checkpoint.json").write_text("{}")
    argv = ["train", "ppo", "--resume", str(bc_dir), "--out", str(tmp_path / "p")]
    assert agents_main(argv) == 1
    assert "checkpoint.json" in capsys.readouterr().err
    # A new ppo-kickstart run's settings, asked of another algorithm.
    for flags in (
        ["--critic-memory"],
        ["--critic-lives"],
        ["--actor-lives"],
        ["--actor-patience"],
        ["--kick-coef", "0"],
        ["--hidden", "64"],
        ["--epochs", "4"],
        ["--learning-rate", "1e-4"],
        ["--gamma", "0.99"],
        ["--gae-lambda", "0.9"],
        ["--ent-coef", "0.01"],
    ):
        argv = ["train", "ppo-masked", "--steps", "100", *flags, "--out", str(tmp_path / "k")]
        assert agents_main(argv) == 1
        assert "are a new ppo-kickstart run's" in capsys.readouterr().err


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(eqx.filter(tree, eqx.is_array))]


def _moved(before, after) -> bool:
    return any(
        not np.array_equal(a, b) for a, b in zip(_leaves(before), _leaves(after), strict=True)
    )


@pytest.mark.parametrize("algorithm", ["ppo", "gail"])
def test_every_rl_algorithm_trains_and_loads(
    algorithm: str, server_address: str, expert_demos: Path, tmp_path: Path
):
    out = tmp_path / algorithm
    argv = ["train", algorithm, "--steps", "1024", "--num-envs", "8", "--out", str(out)]
    argv += ["--address", server_address, "--demos", str(expert_demos)]
    assert agents_main(argv) == 0
    policy = load(out)
    described = json.loads((out / "checkpoint.json").read_text())
    assert described["training"]["iterations"] == 2
    assert described["module"] == f"dinerdash_agents.{algorithm}"
    # The update moved the actor: the parameters and the policy's logits are not the initial
    # ones (the run's seed 0, the config it wrote).
    config = ppo.config_from_json(described["config"])
    initial = ppo.init(config, 0)
    assert _moved(initial.actor, policy.model.actor) and _moved(initial.critic, policy.model.critic)
    demos = load_demos(expert_demos, 5)
    obs = demos.observations[:256]
    assert not np.allclose(np.asarray(initial(obs)), np.asarray(policy.model(obs)), atol=1e-4)
    actions = policy.act(obs, demos.action_masks[:256])
    assert actions.shape == (256,) and demos.action_masks[np.arange(256), actions].all()
    if algorithm == "gail":
        # The discriminator learned: its saved state is not its initial one, and it tells the
        # expert's pairs from a policy's that picks legal actions at random (as the young policy
        # nearly does) better than at the start (measured: loss 1.388 -> 1.379).
        fresh = gail.GAILTrainer(config, 1024, seed=0, demos=load_demos(expert_demos, None))
        state = eqx.tree_deserialise_leaves(out / "trainer.eqx", fresh.state())
        trained = state["discriminator"]
        assert _moved(fresh.discriminator, trained)
        rng = np.random.default_rng(0)
        expert = {"obs": demos.observations, "actions": demos.actions.astype(np.int32)}
        legal = [rng.choice(np.flatnonzero(m)) for m in demos.action_masks]
        other = {"obs": demos.observations, "actions": np.array(legal, np.int32)}
        before = float(gail.discriminator_loss(fresh.discriminator, expert, other))
        after = float(gail.discriminator_loss(trained, expert, other))
        assert after < before, (before, after)


def test_losing_the_server_leaves_a_resumable_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
):
    from dinerdash.server import LocalServer

    server = LocalServer()
    step = ppo.Trainer.step

    def step_then_lose_the_server(self: ppo.Trainer) -> dict:
        stats = step(self)
        if self.iteration == 2:
            server.stop()
        return stats

    monkeypatch.setattr(ppo.Trainer, "step", step_then_lose_the_server)
    out = tmp_path / "run"
    argv = ["train", "ppo-masked", "--steps", "2500", "--num-envs", "8", "--out", str(out)]
    try:
        assert agents_main([*argv, "--address", server.address]) == 1
    finally:
        server.stop()
    err = capsys.readouterr().err
    assert "lost the server" in err and f"--resume {out}" in err
    per_iteration = 8 * ppo.PPOConfig().num_steps
    saved = json.loads((out / "checkpoint.json").read_text())
    assert saved["data"]["environment_steps"] == 2 * per_iteration

    monkeypatch.setattr(ppo.Trainer, "step", step)
    with LocalServer() as again:
        assert agents_main([*argv, "--resume", str(out), "--address", again.address]) == 0
    assert json.loads((out / "checkpoint.json").read_text())["training"]["iterations"] == 5


class _Recording:
    """A vector env that keeps every step's observations and ``final_obs`` (for a test's own
    bootstrap)."""

    def __init__(self, envs) -> None:
        self.envs, self.num_envs, self.steps = envs, envs.num_envs, []

    def reset(self, **kwargs):
        return self.envs.reset(**kwargs)

    def step(self, actions):
        result = self.envs.step(actions)
        obs, _, terminated, truncated, info = result
        self.steps.append((obs.copy(), terminated.copy(), truncated.copy(), info.get("final_obs")))
        return result


def test_pipelined_halves_play_the_samples_of_one_vector_env(server_address: str):
    """Two vector envs of 4 stepped in turn give the rollout one of 8 gives (same seeds, same
    actions), and the next values are the critic's of what follows each step: the next
    observation, a truncated episode's last one, 0 after a termination."""
    config = ppo.PPOConfig(num_envs=8, num_steps=64, max_episode_steps=40)

    def make(n: int):
        return gymnasium.make_vec(
            "dinerdash:DinerDash-v0",
            num_envs=n,
            address=server_address,
            autoreset_mode=AutoresetMode.SAME_STEP,
            max_episode_steps=config.max_episode_steps,
        )

    one = ppo.Trainer(config, 3 * 8 * 64, seed=3)
    halves = ppo.Trainer(config, 3 * 8 * 64, seed=3)
    whole, parts = _Recording(make(8)), [make(4), make(4)]
    try:
        one.attach(whole)
        halves.attach(parts)
        for iteration in range(3):
            a, b = one.collect(), halves.collect()
            for name in ("obs", "mask", "actions", "rewards", "terminated", "done"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
            for name in ("logp", "values", "next_values"):
                np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-5)
            # The next values, recomputed from what the environments returned.
            steps = whole.steps[-config.num_steps :]
            expected = np.zeros_like(a.next_values)
            for t, (obs, terminated, truncated, final_obs) in enumerate(steps):
                following = obs.copy()
                for i in np.flatnonzero(truncated & ~terminated):
                    following[i] = final_obs[i]
                values = np.asarray(one.model.value(jnp.asarray(following)))
                expected[t] = np.where(terminated, 0.0, values)
            np.testing.assert_allclose(a.next_values, expected, atol=1e-5)
            if iteration == 0:
                assert a.done.sum() >= 8 and (a.done > a.terminated).any()  # truncations
            for trainer in (one, halves):  # the update, as step() does it after collecting
                batch = trainer._buffers.batch(trainer.rewards_of(trainer._buffers))
                trainer.model, trainer.opt_state, _ = trainer._update(
                    trainer.model, trainer.opt_state, batch, trainer._next_key()
                )
                trainer.iteration += 1
        assert one.recent_scores == halves.recent_scores and one.episodes == halves.episodes
    finally:
        whole.envs.close()
        for e in parts:
            e.close()


def test_bench_ppo_reports_the_rate_and_where_the_time_goes(server_address: str, capsys):
    argv = ["bench-ppo", "--num-envs", "8", "--iterations", "2", "--address", server_address]
    assert agents_main([*argv, "--pipeline", "2", "--json"]) == 0
    out = capsys.readouterr().out
    result = json.loads(out.strip().splitlines()[-1])
    assert result["pipeline"] == 2 and result["samples_per_iteration"] == 8 * 64
    assert result["env_steps_per_s"] > 0 and "env-steps/s end to end" in out
    parts = result["ms_per_iteration"]
    assert parts["act"] > 0 and parts["env"] > 0 and parts["update"] > 0
    assert agents_main([*argv, "--pipeline", "0"]) == 1
    assert "--pipeline must be at least 1" in capsys.readouterr().err


def test_bench_ppo_runs_the_recipes_ppo_stage_from_its_init(server_address: str, capsys):
    """``--algorithm ppo-kickstart`` benchmarks the recipe's PPO stage (memory features and the
    groups lost counted on the client, the critic reading ``info["lost"]``) from the committed
    DAgger learner; ``--init`` goes with it alone."""
    init = Path(__file__).resolve().parents[2] / "docs/results/checkpoints/dagger-planner-memory"
    argv = ["bench-ppo", "--num-envs", "8", "--iterations", "2", "--address", server_address]
    assert agents_main([*argv, "--algorithm", "ppo-kickstart", "--init", str(init), "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["algorithm"] == "ppo-kickstart" and result["samples_per_iteration"] == 8 * 64
    assert result["env_steps_per_s"] > 0 and result["ms_per_iteration"]["update"] > 0
    assert agents_main([*argv, "--init", str(init)]) == 1
    assert "--init DIR (a dagger checkpoint) goes with ppo-kickstart" in capsys.readouterr().err
    assert agents_main([*argv, "--algorithm", "ppo-kickstart"]) == 1
    assert "goes with ppo-kickstart" in capsys.readouterr().err


@pytest.mark.parametrize("split", [1, 2])
def test_an_iteration_crosses_host_and_device_only_where_it_says(server_address: str, split: int):
    """Under ``jax.transfer_guard_device_to_host("disallow")`` an implicit copy from the device
    to the host (a hidden sync) raises: a whole iteration (acting, bootstrap, update; one vector
    env or two pipelined) brings results back only by its explicit ``jax.device_get``s (per
    step the sampled actions, drawn on the device, once). The update's observations, masks,
    actions, log-probabilities and values are the device's copies made when acting, equal to
    the host's buffers."""
    config = ppo.PPOConfig(num_envs=8, num_steps=16, max_episode_steps=40)
    envs = [
        gymnasium.make_vec(
            "dinerdash:DinerDash-v0",
            num_envs=8 // split,
            address=server_address,
            autoreset_mode=AutoresetMode.SAME_STEP,
            max_episode_steps=config.max_episode_steps,
        )
        for _ in range(split)
    ]
    trainer = ppo.Trainer(config, 3 * 8 * 16, seed=5)
    try:
        trainer.attach(envs if split > 1 else envs[0])
        trainer.step()  # compiles (a first compilation copies constants)
        with jax.transfer_guard_device_to_host("disallow"):
            trainer.step()
            rollout = trainer.collect()
        assert rollout.device is not None
        for name in ("obs", "mask", "actions", "logp", "values"):
            np.testing.assert_array_equal(
                np.asarray(rollout.device[name]), getattr(rollout, name), err_msg=name
            )
    finally:
        for e in envs:
            e.close()


def test_more_environments_keep_the_minibatch_and_the_updates_per_sample():
    base = ppo.PPOConfig()
    assert base.for_num_envs(8) == ppo.PPOConfig(num_envs=8)  # at or below 256: only N
    for n, steps, minibatches in [(512, 32, 4), (1024, 32, 8), (4096, 32, 32), (16384, 32, 128)]:
        c = base.for_num_envs(n)
        assert (c.num_envs, c.num_steps, c.num_minibatches) == (n, steps, minibatches)
        samples = c.num_envs * c.num_steps
        assert samples // c.num_minibatches == 4096  # the base's minibatch: 256 * 64 / 4
        # gradient steps per sample and the learning rate: the base's
        assert c.update_epochs * c.num_minibatches / samples == 2 * 4 / (256 * 64)
        assert c.learning_rate == base.learning_rate


def test_an_rl_runs_environments_never_start_on_the_evaluation_or_validation_seeds(
    server_address: str, tmp_path: Path
):
    # Training seed 125 of 8 environments would start them on seeds 1000..1007, the evaluation
    # seeds; they take the next 8 that are neither evaluation nor validation seeds.
    out = tmp_path / "run"
    argv = ["train", "ppo-masked", "--steps", "512", "--num-envs", "8", "--seed", "125"]
    assert agents_main([*argv, "--address", server_address, "--out", str(out)]) == 0
    described = json.loads((out / "checkpoint.json").read_text())
    assert described["data"]["seed_ranges"] == [[1100, 1107]]
