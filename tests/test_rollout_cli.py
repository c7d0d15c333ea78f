"""Server-side rollouts, the expert's numbers through the client, and ``python -m dinerdash``."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import dinerdash
import numpy as np
import pytest
from dinerdash import DinerDashEnv
from dinerdash.evaluation import evaluate_through_env

from .conftest import server_binary, server_env

EPISODES = 100  # seeds 0..99, the published reference's evaluation


def test_rollout_equals_stepping_the_env(address: str) -> None:
    env = DinerDashEnv(address, expert=True)
    try:
        episodes = list(
            dinerdash.rollout("expert", seeds=[3, 4, 5], address=address, action_masks=True)
        )
        assert [ep.seed for ep in episodes] == [3, 4, 5]
        for ep in episodes:
            obs, info = env.reset(seed=ep.seed)
            np.testing.assert_array_equal(ep.observations[0], obs)
            np.testing.assert_array_equal(ep.action_masks[0], info["action_mask"])
            for t in range(ep.steps):
                assert ep.actions[t] == ep.expert_actions[t] == info["expert_action"]
                obs, reward, terminated, truncated, info = env.step(ep.actions[t])
                np.testing.assert_array_equal(ep.observations[t + 1], obs)
                np.testing.assert_array_equal(ep.action_masks[t + 1], info["action_mask"])
                assert ep.rewards[t] == reward
            assert (
                terminated == ep.terminated
                and ep.score == info["score"]
                and ep.lost == info["lost"]
            )
    finally:
        env.close()


def test_random_rollouts_replay(address: str) -> None:
    a = list(dinerdash.rollout("random", episodes=3, seed=10, address=address))
    b = list(dinerdash.rollout("random", episodes=3, seed=10, address=address))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.actions, y.actions)
        assert x.score == y.score and x.terminated


def test_expert_through_the_client_reproduces_the_simulator(address: str) -> None:
    out = subprocess.run(
        [
            str(server_binary()),
            "eval",
            "--policy",
            "expert",
            "--episodes",
            str(EPISODES),
            "--seed",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
        env=server_env(),
    ).stdout
    mean, sd = map(float, re.search(r"score\s+(-?[\d.]+) ± ([\d.]+)", out).groups())
    assert (mean, sd) == (9151.6, 4489.5)  # the published reference, via the simulator
    scores, lengths = evaluate_through_env("expert", EPISODES, seed=0, address=address, num_envs=50)
    assert (round(scores.mean(), 1), round(scores.std(), 1)) == (mean, sd)
    served = list(dinerdash.rollout("expert", episodes=EPISODES, seed=0, address=address))
    np.testing.assert_array_equal(scores, [ep.score for ep in served])  # episode by episode
    np.testing.assert_array_equal(lengths, [ep.steps for ep in served])


def run_cli(*args: str) -> str:
    return run_cli_both(*args)[0]


def run_cli_both(*args: str) -> tuple[str, str]:
    """The command's stdout and stderr; it must succeed."""
    result = subprocess.run(
        [sys.executable, "-m", "dinerdash", *args], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    return result.stdout, result.stderr


def test_cli_evaluate(address: str) -> None:
    for via in ("env", "rollout"):
        out = run_cli(
            "evaluate", "--policy", "expert", "--episodes", "4", "--via", via, "--address", address
        )
        assert re.search(r"score\s+-?[\d.]+ ± [\d.]+", out), out
    out = run_cli("evaluate", "--policy", "random", "--episodes", "4", "--address", address)
    assert "policy random: 4 episodes" in out


def test_cli_collect(address: str, tmp_path: Path) -> None:
    out = run_cli("collect", "--episodes", "3", "--out", str(tmp_path), "--address", address)
    assert "3 episodes" in out
    data = np.load(tmp_path / "dinerdash_expert.npz")
    total = int(data["episode_lengths"].sum())
    assert data["observations"].shape == (total, 40) and data["actions"].shape == (total,)
    assert data["action_masks"].shape == (total, 57) and data["action_masks"].dtype == np.bool_
    assert data["terminations"].sum() == 3 and data["rewards"].shape == (total,)
    assert data["action_masks"][np.arange(total), data["actions"]].all()  # the expert acts validly
    np.testing.assert_array_equal(data["seeds"], [0, 1, 2])
    starts, ends = data["episode_starts"], np.cumsum(data["episode_lengths"])
    np.testing.assert_array_equal(
        [data["rewards"][s:e].sum() for s, e in zip(starts, ends, strict=True)],
        data["scores"],
    )


def test_cli_collect_writes_a_minari_dataset_when_minari_is_installed(
    address, tmp_path, monkeypatch
):
    pytest.importorskip("minari", reason="minari is an optional extra (make test installs it)")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    argv = ("collect", "--episodes", "2", "--out", str(tmp_path), "--address", address)
    out, err = run_cli_both(*argv)
    assert "wrote Minari dataset dinerdash/expert-v0" in out
    assert "Warning" not in err, err  # Minari's advice to dataset authors is not the user's
    import minari

    dataset = minari.load_dataset("dinerdash/expert-v0")
    data = np.load(tmp_path / "dinerdash_expert.npz")
    assert dataset.total_episodes == 2 and dataset.total_steps == data["episode_lengths"].sum()
    episode = next(dataset.iterate_episodes())
    np.testing.assert_array_equal(episode.actions, data["actions"][: data["episode_lengths"][0]])
    assert episode.infos["action_mask"].shape == (episode.observations.shape[0], 57)


def test_cli_bench_runs(address: str) -> None:
    args = "bench --steps 200 --vec-steps 20 --num-envs 8 --sb3-envs 4 --sb3-steps 20 --pipeline"
    args += " --rounds 1 --ceiling-seconds 0.2"
    out = run_cli(*args.split(), "--reference-steps", "2000", "--address", address)
    for line in ("loopback TCP floor", "reference", "gRPC round trip", "single env"):
        assert line in out
    assert "make_vec N=8" in out and "decode N=8" in out and "pipelined 2 x N=8" in out
    assert "x the reference" in out
    # The transports table, down to the share of the in-process rate no Python client can pass.
    assert "shm N=256 step" in out and "% of in process at most" in out
    # The SB3 comparison runs when the sb3 extra is installed, and says so when it is not.
    assert "SB3 DummyVecEnv N=4" in out or "skipped (pip install 'dinerdash[sb3]')" in out


def test_cli_bench_without_the_bench_package_names_the_pip_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``bench`` is dinerdash-bench's: without it the client's command says how to install it."""
    from dinerdash.cli import main

    monkeypatch.setitem(sys.modules, "dinerdash_bench", None)  # as if not installed
    monkeypatch.delitem(sys.modules, "dinerdash_bench.cli", raising=False)
    assert main(["bench", "--steps", "0"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "pip install dinerdash-bench" in err, err


def test_cli_reports_errors_readably(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "dinerdash", "evaluate", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**server_env(), "DINERDASH_SERVER": str(tmp_path / "missing")},
    )
    assert result.returncode == 1 and "cargo build --release" in result.stderr


def test_cli_reports_an_unreadable_tls_ca_readably(address: str, tmp_path: Path) -> None:
    missing = tmp_path / "missing-ca.pem"
    cmd = [sys.executable, "-m", "dinerdash", "evaluate", "--episodes", "1", "--address", address]
    result = subprocess.run(
        [*cmd, "--tls-ca", str(missing)],
        capture_output=True,
        text=True,
        timeout=60,
        env=server_env(),
    )
    assert result.returncode == 1, result.stderr
    assert result.stderr.startswith("error: tls_ca: cannot read")
    assert "Traceback" not in result.stderr
