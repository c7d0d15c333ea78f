"""The one DAgger run, whatever the learner (``train dagger --teacher planner|expert`` with a
feed-forward learner, :mod:`~dinerdash_agents.dagger`; ``train dagger-recurrent --kind
gru|stack`` with a sequence learner, :mod:`~dinerdash_agents.recurrent`): a session per round on
the server with the teacher labelling every state, the rounds of play
(:func:`~dinerdash_agents.dagger.play_round`, the one play loop) and retraining, validation of
each round's learner on seeds 2000.., the curve (``curve.csv``, ``curve.png``: one row per round)
and the checkpoint of the best round. What differs between the learners is a row of
:data:`LEARNERS`, not a branch.

Beside the checkpoint, the live curves (:class:`~dinerdash_agents.curves.LiveCurves`), after every
round at its number: ``rollout/score`` and ``rollout/episode_length`` (the mixture's episodes),
``validation/score`` (the learner on seeds 2000..), ``train/loss``, ``dagger/agreement`` (the
learner's action is the teacher's, on the round's states with a choice; from round 2 on, when it
acts), ``dagger/beta``, ``dagger/teacher_share``, ``dagger/dataset_steps`` and
``time/env_steps_per_s`` (the states played over the seconds of play)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

from . import checkpoint, dagger, recurrent
from ._version import __version__
from .connect import ConnectOptions, options, served
from .curves import LiveCurves, read_curve, write_curve
from .dagger import (
    TEACHERS,
    VALIDATION_SEED,
    Aggregate,
    DaggerConfig,
    MemoryFeatures,
    play_round,
    training_seeds,
)
from .evaluate import evaluate_policy
from .recurrent import RecurrentConfig
from .seeds import as_ranges

__all__ = ["CURVE_COLUMNS", "LEARNERS", "Learner", "iter_rows", "save_run", "train_dagger"]

#: The columns of a DAgger run's ``curve.csv``, one row per round.
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
    "play_seconds",
    "fit_seconds",
    "round_seconds",
)


@dataclass(frozen=True)
class Learner:
    """What a DAgger run needs of a kind of learner."""

    #: The checkpoint's algorithm (:data:`~dinerdash_agents.checkpoint.ALGORITHMS`).
    algorithm: str
    init: Callable[[Any, int], Any]
    #: β_1..β_R of a config.
    betas: Callable[[Any], list[float]]
    #: The aggregate's width: the observation and, with ``memory``, its features.
    input_size: Callable[[Any], int]
    #: ``fit(model, aggregate, config, seed) -> (model, losses)``: one round's training.
    fit: Callable[..., tuple[Any, list[float]]]
    #: ``policy(model, description)``: the learner as a policy of the package's shape.
    policy: Callable[[Any, dict[str, Any]], checkpoint.BasePolicy]
    #: What the progress line and the curve's title call it.
    label: Callable[[Any], str]
    #: The memory features a round records beside the observations (None: none).
    memory: Callable[[Any], MemoryFeatures | None]
    #: ``play_round``'s perturbations of the learner's play a config asks for, by keyword.
    perturbations: Callable[[Any], dict[str, Any]] = lambda config: {}


#: The learners, by their config's type.
LEARNERS: dict[type, Learner] = {
    DaggerConfig: Learner(
        "dagger",
        dagger.init,
        dagger.betas,
        dagger.input_size,
        dagger.fit_round,
        checkpoint.Policy,
        lambda config: f"DAgger, teacher {config.teacher}",
        dagger.CHECKPOINT.view,
        lambda config: {
            "learner_memory": config.learner_memory,
            "learner_noise": config.learner_noise,
        },
    ),
    RecurrentConfig: Learner(
        recurrent.ALGORITHM,
        recurrent.init,
        recurrent.betas,
        recurrent.input_size,
        lambda model, aggregate, config, seed: recurrent.fit_round(
            model, aggregate.episodes, config, seed
        ),
        recurrent.RecurrentPolicy,
        lambda config: f"sequence DAgger ({config.kind}), teacher {config.teacher}",
        lambda config: MemoryFeatures() if config.memory else None,
    ),
}


def train_dagger(
    out: str | Path,
    config: DaggerConfig | RecurrentConfig,
    *,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    seed: int = 0,
    name: str | None = None,
    progress: bool = True,
    tensorboard: str | Path | None = None,
    **connection: Any,
) -> tuple[checkpoint.BasePolicy, dict]:
    """Runs ``config.rounds`` DAgger rounds (the learner of :data:`LEARNERS` for the config's
    type) against the server(s) of ``connect`` (with ``address`` and the connection keywords put
    in; none named: ``DINERDASH_ADDRESS``, else a local server started here) and writes the best
    round's learner to ``out``; returns its policy and description. ``tensorboard``: the
    directory of the live curves (``None``: none written)."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    connect = options(connect, "train_dagger", address, **connection)
    # A local server, if any, starts before any JAX work.
    with served(connect) as (connect, _), LiveCurves(tensorboard) as live:
        return _train(Path(out), config, connect, seed, name, progress, live)


def _train(
    out: Path,
    config: Any,
    connect: ConnectOptions,
    seed: int,
    name: str | None,
    progress: bool,
    live: LiveCurves,
) -> tuple[checkpoint.BasePolicy, dict]:
    learner = LEARNERS[type(config)]
    start, cpu_start = time.monotonic(), time.process_time()
    rng = np.random.default_rng(seed)
    model = learner.init(config, seed)
    stub = {"algorithm": learner.algorithm, "name": name or out.name, "config": config.to_json()}
    aggregate = Aggregate(learner.input_size(config))
    seeds = training_seeds(config.seed_start, config.rounds * config.episodes_per_round)
    rows: list[dict[str, Any]] = []
    best: tuple[float, int, Any] | None = None
    losses: list[float] = [float("nan")]
    n = max(1, min(config.num_envs, config.episodes_per_round))
    for r, beta in enumerate(learner.betas(config), start=1):
        began = time.monotonic()
        round_seeds = seeds[(r - 1) * config.episodes_per_round : r * config.episodes_per_round]
        # A session per round: the server expires a session left idle while the learner trains
        # (minutes on a loaded machine).
        envs = gymnasium.make_vec(
            "dinerdash:DinerDash-v0",
            num_envs=n,
            connect=connect,
            expert=TEACHERS[config.teacher],
            max_episode_steps=config.max_episode_steps,
        )
        try:
            played = play_round(
                envs,
                learner.policy(model, stub),
                beta,
                round_seeds,
                rng,
                learner.memory(config),
                **learner.perturbations(config),
            )
        finally:
            envs.close()
        aggregate.extend(played.episodes, r)
        playing = time.monotonic() - began
        model, losses = learner.fit(model, aggregate, config, seed + r)
        fitting = time.monotonic() - began - playing
        val_scores, _ = evaluate_policy(
            learner.policy(model, stub).act,
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
                "play_seconds": round(playing, 1),
                "fit_seconds": round(fitting, 1),
                "round_seconds": round(time.monotonic() - began, 1),
            }
        )
        live.add(
            r,
            {
                "rollout/score": rows[-1]["rollout_mean_score"],
                "rollout/episode_length": rows[-1]["rollout_mean_length"],
                "validation/score": val,
                "train/loss": losses[-1],
                "dagger/agreement": played.agreement,
                "dagger/beta": beta,
                "dagger/teacher_share": rows[-1]["teacher_share"],
                "dagger/dataset_steps": aggregate.steps,
                "time/env_steps_per_s": played.states / max(playing, 1e-9),
            },
        )
        if progress:
            row = rows[-1]
            print(
                f"{learner.label(config)} round {r}/{config.rounds} β={beta:.3g}: "
                f"mixture {row['rollout_mean_score']:,.0f}, learner on seeds "
                f"{VALIDATION_SEED}.. {val:,.0f}, {aggregate.steps:,} states, loss "
                f"{row['final_loss']:.4f}, play {playing:.0f} s, fit {fitting:.0f} s, "
                f"{row['round_seconds']:.0f} s",
                flush=True,
            )
    assert best is not None
    seconds, cpu_seconds = time.monotonic() - start, time.process_time() - cpu_start
    states = aggregate.steps
    description = save_run(
        out,
        name=name,
        algorithm=learner.algorithm,
        config=config,
        seeds=seeds,
        data={"steps": states, "environment_steps": states},
        seed=seed,
        best=best,
        seconds=seconds,
        cpu_seconds=cpu_seconds,
        final_loss=losses[-1],
        rows=rows,
        columns=CURVE_COLUMNS,
        title=f"{learner.label(config)}: {out.name}",
        training={"labelled_states_per_second": round(states / seconds, 1)},
    )
    return learner.policy(best[2], checkpoint.read_description(out)), description


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
            "seed_ranges": as_ranges(seeds),
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
