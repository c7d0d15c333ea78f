"""The live curves: short training runs (PPO, DAgger, BC) against a real local server write
TensorBoard event files that TensorBoard's own reader reads back with the expected tags and
values, and the agents with their writer import no torch."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from dinerdash_agents import ppo
from dinerdash_agents.cli import main
from dinerdash_agents.curves import LiveCurves, read_curve
from dinerdash_agents.dagger import DaggerConfig
from dinerdash_agents.train_dagger import train_dagger
from dinerdash_agents.train_rl import train_rl


def _scalars(directory: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the event files in ``directory``: tag -> [(step, value)]."""
    events = EventAccumulator(str(directory), size_guidance={"scalars": 0})
    events.Reload()
    return {
        tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]
    }


def test_a_short_ppo_run_writes_its_curves_as_it_goes(server_address: str, tmp_path: Path):
    # Episodes capped at 40 steps, so that some end within the run's two iterations.
    config = ppo.PPOConfig(masked=True).for_num_envs(8)
    config = dataclasses.replace(config, max_episode_steps=40)
    out, board = tmp_path / "run", tmp_path / "board"
    trainer = train_rl(
        "ppo-masked",
        1024,
        out,
        address=server_address,
        config=config,
        progress=False,
        tensorboard=board,
    )
    scalars = _scalars(board)
    losses = {f"train/{k}" for k in ("policy_loss", "value_loss", "entropy", "approx_kl")}
    rollout = {"rollout/score", "rollout/episode_length", "time/env_steps_per_s"}
    assert losses | rollout <= set(scalars), sorted(scalars)
    per_iteration = 8 * config.num_steps
    for tag in losses | rollout:
        assert [step for step, _ in scalars[tag]] == [per_iteration, 2 * per_iteration], tag
    # The same score as the curve.csv beside the checkpoint; lengths within the cap.
    rows = read_curve(out)
    for (_, live), row in zip(scalars["rollout/score"], rows, strict=True):
        assert live == pytest.approx(float(row["mean_score_last_100_episodes"]), rel=1e-6)
    assert all(0 < length <= 40 for _, length in scalars["rollout/episode_length"])
    assert scalars["rollout/episode_length"][-1][1] == pytest.approx(trainer.mean_recent_length)
    assert all(value > 0 for _, value in scalars["time/env_steps_per_s"])
    assert all(value > 0 for _, value in scalars["train/entropy"])


def test_a_resumed_run_drops_what_its_interrupted_process_wrote_after_the_checkpoint(
    tmp_path: Path,
):
    with LiveCurves(tmp_path) as live:  # checkpointed at step 10, then lost after step 30
        for step in (10, 20, 30):
            live.add(step, {"rollout/score": step})
    with LiveCurves(tmp_path, resumed=True, step=10) as live:
        live.add(20, {"rollout/score": -20})
    assert _scalars(tmp_path)["rollout/score"] == [(10, 10.0), (20, -20.0)]
    # A new run of the same name starts the curves afresh.
    with LiveCurves(tmp_path) as live:
        live.add(5, {"rollout/score": 5, "rollout/episode_length": float("nan")})
    assert _scalars(tmp_path) == {"rollout/score": [(5, 5.0)]}


def test_a_resumed_ppo_run_continues_its_curves(server_address: str, tmp_path: Path):
    out = tmp_path / "runs" / "p"
    small = ["--num-envs", "8", "--address", server_address, "--out", str(out)]
    assert main(["train", "ppo-masked", "--steps", "512", *small]) == 0
    assert main(["train", "ppo-masked", "--steps", "1024", "--resume", str(out), *small]) == 0
    # The default: tensorboard/<name> beside the checkpoint.
    scalars = _scalars(tmp_path / "runs" / "tensorboard" / "p")
    per_iteration = 8 * ppo.PPOConfig().num_steps
    assert [step for step, _ in scalars["train/policy_loss"]] == [per_iteration, 2 * per_iteration]
    # The seeds trained on: each process's first resets, seed * 8 + steps done + i.
    described = json.loads((out / "checkpoint.json").read_text())
    assert described["data"]["seed_ranges"] == [[0, 7], [per_iteration, per_iteration + 7]]


def test_a_short_dagger_run_writes_its_rounds_and_the_agreement(
    server_address: str, tmp_path: Path
):
    config = DaggerConfig(
        teacher="expert",
        rounds=2,
        episodes_per_round=4,
        num_envs=4,
        max_episode_steps=150,
        hidden=32,
        epochs=1,
        validation_episodes=2,
    )
    board = tmp_path / "board"
    train_dagger(
        tmp_path / "dagger", config, address=server_address, progress=False, tensorboard=board
    )
    scalars = _scalars(board)
    expected = {
        "rollout/score",
        "rollout/episode_length",
        "validation/score",
        "train/loss",
        "dagger/beta",
        "dagger/teacher_share",
        "dagger/dataset_steps",
        "time/env_steps_per_s",
    }
    assert expected <= set(scalars), sorted(scalars)
    for tag in expected:
        assert [step for step, _ in scalars[tag]] == [1, 2], tag
    assert [beta for _, beta in scalars["dagger/beta"]] == [1.0, 0.5]
    # Round 1 is the teacher's alone (β = 1): the learner is first asked in round 2.
    assert [step for step, _ in scalars["dagger/agreement"]] == [2]
    assert 0.0 <= scalars["dagger/agreement"][0][1] <= 1.0
    assert all(0 < length <= 150 for _, length in scalars["rollout/episode_length"])


def test_bc_writes_each_epochs_loss_beside_its_checkpoint(expert_demos: Path, tmp_path: Path):
    out = tmp_path / "runs" / "bc"
    argv = ["train", "bc", "--demos", str(expert_demos), "--epochs", "3", "--out", str(out)]
    assert main(argv) == 0
    loss = _scalars(tmp_path / "runs" / "tensorboard" / "bc")["train/loss/bc"]
    assert [step for step, _ in loss] == [1, 2, 3]
    assert all(math.isfinite(value) and value > 0 for _, value in loss)


def test_the_agents_and_their_curves_writer_import_no_torch(tmp_path: Path):
    # The development venv has torch (for other tests): what counts is what gets imported.
    script = f"""
import sys
import dinerdash_agents, dinerdash_agents.cli, dinerdash_agents.train_rl
import dinerdash_agents.train_dagger, dinerdash_agents.train_imitation
from dinerdash_agents.curves import LiveCurves
with LiveCurves({str(tmp_path)!r}) as live:
    live.add(1, {{"rollout/score": 1.0}})
assert "tensorboard" in sys.modules
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "tensorflow", "tensorboardX"))
print(heavy)
"""
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]", run.stdout
    assert list(tmp_path.glob("events.out.tfevents.*"))
