"""``python -m dinerdash_agents recipe``: both stages trained into one directory, each on the
training seed given, and a second run finishing only what is missing."""

from __future__ import annotations

import json
from pathlib import Path

from dinerdash_agents import ppo
from dinerdash_agents.checkpoint import load
from dinerdash_agents.recipe import DAGGER, PPO, run_recipe

# The recipe's stages, shrunk to seconds: the expert labels (the planner is the recipe's teacher,
# and slower), one round of four episodes.
SMALL_DAGGER = {
    "teacher": "expert",
    "rounds": 1,
    "episodes_per_round": 4,
    "num_envs": 4,
    "epochs": 1,
    "validation_episodes": 2,
}


def test_the_recipe_trains_dagger_then_ppo_from_it_and_a_second_run_only_finishes_ppo(
    server_address: str, tmp_path: Path
) -> None:
    from dinerdash import ConnectOptions

    connect = ConnectOptions(address=server_address)
    per_iteration = 8 * ppo.PPOConfig().num_steps
    small = {"connect": connect, "dagger": SMALL_DAGGER, "num_envs": 8, "progress": False}
    record = run_recipe(tmp_path, seed=3, ppo_steps=per_iteration, **small)
    assert set(record["stages"]) == {DAGGER, PPO}
    assert record == json.loads((tmp_path / "recipe.json").read_text())

    dagger = json.loads((tmp_path / DAGGER / "checkpoint.json").read_text())
    assert dagger["config"]["memory"] is True and dagger["config"]["patience"] is True
    assert dagger["config"]["learner_memory"] == "own"
    assert dagger["training"]["seed"] == 3
    first = json.loads((tmp_path / PPO / "checkpoint.json").read_text())
    assert first["config"]["init"] == str(tmp_path / DAGGER)
    assert first["config"]["init_algorithm"] == "dagger"
    assert first["config"]["kick_coef"] == 0.0
    assert first["config"]["critic_memory"] is True and first["config"]["hidden"] == 256
    assert first["config"]["critic_lives"] is True and first["config"]["actor_lives"] is True
    assert first["training"]["seed"] == 3
    assert first["data"]["environment_steps"] == per_iteration
    assert (tmp_path / "tensorboard" / PPO).is_dir()

    dagger_written = (tmp_path / DAGGER / "model.eqx").stat().st_mtime_ns
    record = run_recipe(tmp_path, seed=3, ppo_steps=2 * per_iteration, **small)
    assert (tmp_path / DAGGER / "model.eqx").stat().st_mtime_ns == dagger_written
    second = json.loads((tmp_path / PPO / "checkpoint.json").read_text())
    assert second["data"]["environment_steps"] == 2 * per_iteration
    assert record["seconds"] == round(sum(record["stages"].values()), 1)
    assert load(tmp_path / PPO).algorithm == "ppo-kickstart"
