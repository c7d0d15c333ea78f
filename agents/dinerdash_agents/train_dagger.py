"""One DAgger run (``train dagger --teacher planner|expert``): the sessions on the server with
the teacher labelling every state, :data:`~dinerdash_agents.dagger.DaggerConfig`'s rounds of
play and retraining (:mod:`~dinerdash_agents.dagger`, the algorithm), validation of each round's
learner on seeds 2000.., the curve (``curve.csv``, ``curve.png``: one row per round) and the
checkpoint of the best round."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

from . import checkpoint, dagger
from ._version import __version__
from .connect import ConnectOptions, options, served
from .curves import read_curve, write_curve
from .dagger import (
    TEACHERS,
    VALIDATION_SEED,
    Aggregate,
    DaggerConfig,
    DaggerNet,
    MemoryFeatures,
    betas,
    greedy_actions,
    init,
    input_size,
    play_round,
    training_seeds,
)
from .evaluate import evaluate_policy

__all__ = ["CURVE_COLUMNS", "iter_rows", "save_run", "train_dagger"]

#: The columns of a DAgger run's ``curve.csv``.
CURVE_COLUMNS = (
    "round",
    "beta",
    "episodes",
    "seeds",
    "dataset_steps",
    "teacher_share",
    "rollout_mean_score",
    "rollout_mean_length",
    "validation_mean_score",
    "validation_sd",
    "final_loss",
    "round_seconds",
)


def train_dagger(
    out: str | Path,
    config: DaggerConfig,
    *,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    seed: int = 0,
    name: str | None = None,
    progress: bool = True,
    **connection: Any,
) -> tuple[checkpoint.Policy, dict]:
    """Runs ``config.rounds`` DAgger rounds against the server(s) of ``connect`` (with
    ``address`` and the connection keywords put in; none named: ``DINERDASH_ADDRESS``, else a
    local server started here) and writes the best round's learner to ``out``; returns its
    :class:`~dinerdash_agents.checkpoint.Policy` and description."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    connect = options(connect, "train_dagger", address, **connection)
    # A local server, if any, starts before any JAX work.
    with served(connect) as (connect, _):
        return _train(Path(out), config, connect, seed, name, progress)


def _train(
    out: Path, config: DaggerConfig, connect: ConnectOptions, seed: int, name, progress: bool
) -> tuple[checkpoint.Policy, dict]:
    start, cpu_start = time.monotonic(), time.process_time()
    rng = np.random.default_rng(seed)
    model = init(config, seed)
    aggregate = Aggregate(input_size(config))
    seeds = training_seeds(config.seed_start, config.rounds * config.episodes_per_round)
    schedule = betas(config)
    rows: list[dict[str, Any]] = []
    best: tuple[float, int, DaggerNet] | None = None
    environment_steps = 0
    losses: list[float] = []
    n = max(1, min(config.num_envs, config.episodes_per_round))
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0",
        num_envs=n,
        connect=connect,
        expert=TEACHERS[config.teacher],
        max_episode_steps=config.max_episode_steps,
    )
    try:
        for r, beta in enumerate(schedule, start=1):
            began = time.monotonic()
            round_seeds = seeds[(r - 1) * config.episodes_per_round : r * config.episodes_per_round]
            played = play_round(
                envs,
                lambda obs, mask, m=model: greedy_actions(m, obs, mask),
                beta,
                round_seeds,
                aggregate,
                r,
                rng,
                MemoryFeatures() if config.memory else None,
            )
            environment_steps += played.states
            model, losses = dagger.fit_round(model, aggregate, config, seed + r)
            view = MemoryFeatures().augment if config.memory else (lambda obs: obs)
            val_scores, _ = evaluate_policy(
                lambda obs, mask, m=model, view=view: greedy_actions(m, view(obs), mask),
                config.validation_episodes,
                seed=VALIDATION_SEED,
                connect=connect,
                num_envs=config.validation_episodes,
                max_steps=config.max_episode_steps,
            )
            val = float(np.mean(val_scores))
            if best is None or val > best[0]:
                best = (val, r, model)
            rows.append(
                {
                    "round": r,
                    "beta": round(beta, 6),
                    "episodes": len(round_seeds),
                    "seeds": f"{round_seeds[0]}..{round_seeds[-1]}",
                    "dataset_steps": aggregate.steps,
                    "teacher_share": round(played.teacher_steps / max(played.states, 1), 4),
                    "rollout_mean_score": round(float(np.mean(played.scores)), 1),
                    "rollout_mean_length": round(float(np.mean(played.lengths)), 1),
                    "validation_mean_score": round(val, 1),
                    "validation_sd": round(float(np.std(val_scores)), 1),
                    "final_loss": round(losses[-1], 5),
                    "round_seconds": round(time.monotonic() - began, 1),
                }
            )
            if progress:
                row = rows[-1]
                print(
                    f"dagger {config.teacher} round {r}/{config.rounds} β={beta:.3g}: "
                    f"mixture {row['rollout_mean_score']:,.0f}, learner on seeds "
                    f"{VALIDATION_SEED}.. {val:,.0f}, {aggregate.steps:,} states, "
                    f"{row['round_seconds']:.0f} s",
                    flush=True,
                )
    finally:
        envs.close()
    assert best is not None
    seconds, cpu_seconds = time.monotonic() - start, time.process_time() - cpu_start
    out = Path(out)
    description = save_run(
        out,
        name=name,
        algorithm="dagger",
        config=config,
        seeds=seeds,
        data={"steps": aggregate.steps, "environment_steps": environment_steps},
        seed=seed,
        best=best,
        seconds=seconds,
        cpu_seconds=cpu_seconds,
        final_loss=losses[-1],
        rows=rows,
        columns=CURVE_COLUMNS,
        title=f"DAgger, teacher {config.teacher}: {out.name}",
    )
    return checkpoint.Policy(best[2], checkpoint.read_description(out)), description


def save_run(
    out: Path,
    *,
    name: str | None,
    algorithm: str,
    config: Any,
    seeds: list[int],
    data: dict[str, Any],
    seed: int,
    best: tuple[float, int, Any],
    seconds: float,
    cpu_seconds: float,
    final_loss: float,
    rows: list[dict[str, Any]],
    columns: tuple[str, ...],
    title: str,
    training: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Saves a DAgger run's best round (``best``: its validation mean score, its round, its
    parameters) as a checkpoint under ``out``, with its description and its curve (one row a
    round, of ``columns``); returns the description. ``data`` and ``training``: the algorithm's
    own entries of the description's "data" and "training" sections."""
    last_validation_seed = VALIDATION_SEED + config.validation_episodes - 1
    description = {
        "name": name or out.name,
        "algorithm": algorithm,
        "package_version": __version__,
        "config": config.to_json(),
        "data": {
            "teacher": config.teacher,
            "episodes": len(seeds),
            "seeds": [seeds[0], seeds[-1]],
            **data,
        },
        "training": {
            "seed": seed,
            "rounds": config.rounds,
            "best_round": best[1],
            "best_validation_mean_score": round(best[0], 1),
            "validation_seeds": f"{VALIDATION_SEED}..{last_validation_seed}",
            "seconds": round(seconds, 3),
            "cpu_seconds": round(cpu_seconds, 3),
            **(training or {}),
            "final_losses": {"cross_entropy": round(final_loss, 6)},
        },
    }

    def curve(tmp: Path) -> None:
        write_curve(
            tmp,
            columns,
            rows,
            lines={
                "validation_mean_score": f"learner, seeds {VALIDATION_SEED}..",
                "rollout_mean_score": "mixture policy π_i",
            },
            xlabel="DAgger round",
            ylabel="mean final score",
            title=title,
            marker="o",
        )

    checkpoint.save(out, best[2], description, extra=curve)
    return description


def iter_rows(directory: str | Path) -> Iterator[dict[str, str]]:
    """The rows of a DAgger checkpoint's ``curve.csv``."""
    yield from read_curve(directory)
