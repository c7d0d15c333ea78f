"""The best learned policy's whole recipe for one training seed, in one command: DAgger with the
look-ahead planner as teacher and memory features, exact patience among them, the learner's own
memory told its choices rather than the actions played (``dagger-planner-own-memory``), then
masked PPO on the game's reward from that learner, its critic reading the memory features and
the groups lost too, its actor counting them from the observations (``ppo-kickstart-own-memory``);
docs/agents.md gives its results and times.

::

    python -m dinerdash_agents recipe --seed K --out runs/recipe-K

A stage whose checkpoint already stands in ``OUT`` is not trained again, and a PPO stage that
stopped part way (a lost server, Ctrl-C) is resumed from its last checkpoint: running the
command again finishes the recipe. ``OUT/recipe.json`` records each stage's wall-clock seconds.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from dinerdash import ConnectOptions

from . import checkpoint
from .connect import options, served
from .dagger import DaggerConfig
from .kickstart import KickstartConfig
from .paper import DAGGER_SETTINGS, KICKSTART_SETTINGS, STEPS
from .train_dagger import train_dagger
from .train_rl import TRAINER_STATE, train_rl

__all__ = ["PPO_STEPS", "run_recipe"]

DAGGER = "dagger-planner-own-memory"
PPO = "ppo-kickstart-own-memory"
#: The PPO stage's environment steps: its row's in the paper table.
PPO_STEPS = STEPS[PPO]


def run_recipe(
    out: str | Path,
    *,
    seed: int = 0,
    ppo_steps: int = PPO_STEPS,
    connect: ConnectOptions | None = None,
    dagger: dict[str, Any] | None = None,
    num_envs: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Trains (or finishes) the recipe's two stages for training seed ``seed`` into
    ``out/dagger-planner-own-memory`` and ``out/ppo-kickstart-own-memory``, with their TensorBoard
    curves under ``out/tensorboard``; returns what it writes to ``out/recipe.json``. ``dagger``:
    settings that replace the recipe's DAgger ones (tests use fewer rounds); ``num_envs``: the PPO
    stage's environments (default its config's)."""
    # One local server, if any, for both stages, started before any JAX work.
    with served(options(connect, "run_recipe")) as (connect, _):
        return _run(Path(out), seed, ppo_steps, connect, dagger, num_envs, progress)


def _run(
    out: Path,
    seed: int,
    ppo_steps: int,
    connect: ConnectOptions,
    dagger: dict[str, Any] | None,
    num_envs: int | None,
    progress: bool,
) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    record_path = out / "recipe.json"
    record = json.loads(record_path.read_text()) if record_path.is_file() else {"stages": {}}
    record.update(seed=seed, ppo_steps=ppo_steps)

    def stage(name: str, train) -> None:
        began = time.monotonic()
        train(out / name, out / "tensorboard" / name)
        seconds = record["stages"].get(name, 0.0) + time.monotonic() - began
        record["stages"][name] = round(seconds, 1)
        record["seconds"] = round(sum(record["stages"].values()), 1)
        record_path.write_text(json.dumps(record, indent=2) + "\n")

    if not (out / DAGGER / checkpoint.DESCRIPTION).is_file():
        settings = {**DAGGER_SETTINGS[DAGGER], "teacher": "planner", **(dagger or {})}
        config = dataclasses.replace(DaggerConfig(), **settings)
        stage(
            DAGGER,
            lambda directory, curves: train_dagger(
                directory,
                config,
                connect=connect,
                seed=seed,
                progress=progress,
                tensorboard=curves,
            ),
        )
    ppo_dir = out / PPO
    resume = ppo_dir if (ppo_dir / TRAINER_STATE).is_file() else None
    if resume is None or _steps(ppo_dir) < ppo_steps:
        stage(
            PPO,
            lambda directory, curves: train_rl(
                "ppo-kickstart",
                ppo_steps,
                directory,
                num_envs=num_envs,
                connect=connect,
                seed=seed,
                resume=resume,
                init=None if resume else out / DAGGER,
                config=None if resume else KickstartConfig(**KICKSTART_SETTINGS[PPO]),
                progress=progress,
                tensorboard=curves,
            ),
        )
    return record


def _steps(directory: Path) -> int:
    """The environment steps a PPO checkpoint has trained."""
    return int(checkpoint.read_description(directory)["data"]["environment_steps"])
