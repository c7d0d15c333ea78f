"""A run of sequence DAgger (:mod:`~dinerdash_agents.recurrent`): ``python -m dinerdash_agents
train dagger-recurrent --kind gru|stack ...``. Plays the rounds against a server (a local one
unless an address is given), labels every visited state with the teacher's action, trains, keeps
the round that scored best on the validation seeds 2000.., and writes the checkpoint with its
``curve.csv`` / ``curve.png``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

from . import checkpoint
from .connect import ConnectOptions, options, served
from .dagger import VALIDATION_SEED, MemoryFeatures, SeedQueue, training_seeds
from .evaluate import evaluate_policy
from .recurrent import (
    ALGORITHM,
    TEACHERS,
    Episode,
    RecurrentConfig,
    RecurrentPolicy,
    betas,
    fit_round,
    init,
    sequence_starts,
)
from .train_dagger import save_run

__all__ = ["CURVE_COLUMNS", "play_round", "train_recurrent"]

#: The columns of a run's ``curve.csv``, one row per round.
CURVE_COLUMNS = (
    "round",
    "beta",
    "episodes",
    "seeds",
    "dataset_steps",
    "rollout_mean_score",
    "rollout_mean_length",
    "validation_mean_score",
    "validation_sd",
    "final_loss",
    "play_seconds",
    "fit_seconds",
    "round_seconds",
)


def play_round(
    envs: Any,
    learner: RecurrentPolicy | None,
    beta: float,
    seeds: list[int],
    rng: np.random.Generator,
    memory: MemoryFeatures | None = None,
) -> tuple[list[Episode], np.ndarray]:
    """Plays one episode per seed of ``seeds`` with the mixture ``β·teacher + (1 − β)·learner``
    on ``envs`` (a vector env whose infos carry ``expert_action`` and ``action_mask``; an
    environment that ends is reset with the next seed through ``options={"reset_mask": ...}``);
    returns the recorded episodes, in the order of ``seeds``, and their final scores. The
    learner steps its state on every observation of every environment, whoever acts (it is not
    called at all when ``beta`` is 1). Environments left without a seed play on unrecorded.
    With ``memory``, the recorded observations are extended by its features (as the learner's
    own, which it computes itself)."""
    n = envs.num_envs
    played = SeedQueue(seeds, n)
    slot, active = played.slot, played.active
    obs, info = envs.reset(seed=played.padded)
    if learner is not None:
        learner.reset()
    record: list[dict[str, list]] = [
        {"obs": [], "mask": [], "action": []} for _ in range(len(seeds))
    ]
    restart = np.ones(n, np.bool_)
    while active.any():
        teacher = np.asarray(info["expert_action"], np.int64)
        mask = np.asarray(info["action_mask"], np.bool_)
        seen = obs if memory is None else memory.augment(obs)
        for i in np.flatnonzero(active):
            r = record[slot[i]]
            r["obs"].append(np.asarray(seen[i], np.float32))
            r["mask"].append(mask[i])
            r["action"].append(teacher[i])
        if learner is None:
            actions = teacher
        else:
            learned = learner.act(obs, mask, episode_start=restart)
            from_teacher = rng.random(n) < beta
            actions = np.where(from_teacher, teacher, learned)
        restart = np.zeros(n, np.bool_)
        obs, _, terminated, truncated, info = envs.step(actions)
        ended = (np.asarray(terminated) | np.asarray(truncated)) & active
        if not ended.any():
            continue
        reset, new_seeds = played.end(ended, info["score"])
        if reset.any():
            obs, info = envs.reset(seed=new_seeds, options={"reset_mask": reset})
            restart = reset
    episodes = []
    for r in record:
        o = np.stack(r["obs"])
        episodes.append(
            Episode(o, np.stack(r["mask"]), np.asarray(r["action"], np.int32), sequence_starts(o))
        )
    return episodes, played.scores


def train_recurrent(
    out: str | Path,
    config: RecurrentConfig,
    *,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    seed: int = 0,
    name: str | None = None,
    progress: bool = True,
    **connection: Any,
) -> tuple[RecurrentPolicy, dict]:
    """Runs ``config.rounds`` rounds of sequence DAgger against the server(s) of ``connect``
    (with ``address`` and the connection keywords put in; none named: ``DINERDASH_ADDRESS``,
    else a local server started here) and writes the best round's learner to ``out``; returns
    its policy and description."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    connect = options(connect, "train_recurrent", address, **connection)
    # A local server, if any, starts before any JAX work.
    with served(connect) as (connect, _):
        return _train(Path(out), config, connect, seed, name, progress)


def _train(out, config, connect, seed, name, progress):
    start, cpu_start = time.monotonic(), time.process_time()
    rng = np.random.default_rng(seed)
    model = init(config, seed)
    description_stub = {
        "algorithm": ALGORITHM,
        "name": name or out.name,
        "config": config.to_json(),
    }
    seeds = training_seeds(config.seed_start, config.rounds * config.episodes_per_round)
    aggregate: list[Episode] = []
    rows: list[dict[str, Any]] = []
    best = None
    losses: list[float] = [float("nan")]
    n = max(1, min(config.num_envs, config.episodes_per_round))

    def make_envs():
        return gymnasium.make_vec(
            "dinerdash:DinerDash-v0",
            num_envs=n,
            connect=connect,
            expert=TEACHERS[config.teacher],
            max_episode_steps=config.max_episode_steps,
        )

    for r, beta in enumerate(betas(config), start=1):
        began = time.monotonic()
        round_seeds = seeds[(r - 1) * config.episodes_per_round : r * config.episodes_per_round]
        learner = None if beta >= 1.0 else RecurrentPolicy(model, description_stub)
        memory = MemoryFeatures() if config.memory else None
        # A session per round: the server expires a session left idle while the learner
        # trains (minutes on a loaded machine).
        envs = make_envs()
        try:
            episodes, scores = play_round(envs, learner, beta, round_seeds, rng, memory)
        finally:
            envs.close()
        aggregate.extend(episodes)
        played = time.monotonic() - began
        model, losses = fit_round(model, aggregate, config, seed + r)
        fitted = time.monotonic() - began - played
        val_scores, _ = evaluate_policy(
            RecurrentPolicy(model, description_stub).act,
            config.validation_episodes,
            seed=VALIDATION_SEED,
            connect=connect,
            num_envs=config.validation_episodes,
            max_steps=config.max_episode_steps,
        )
        val = float(np.mean(val_scores))
        if best is None or val > best[0]:
            best = (val, r, model)
        states = sum(len(e) for e in aggregate)
        rows.append(
            {
                "round": r,
                "beta": round(beta, 6),
                "episodes": len(round_seeds),
                "seeds": f"{round_seeds[0]}..{round_seeds[-1]}",
                "dataset_steps": states,
                "rollout_mean_score": round(float(np.mean(scores)), 1),
                "rollout_mean_length": round(float(np.mean([len(e) for e in episodes])), 1),
                "validation_mean_score": round(val, 1),
                "validation_sd": round(float(np.std(val_scores)), 1),
                "final_loss": round(losses[-1], 5),
                "play_seconds": round(played, 1),
                "fit_seconds": round(fitted, 1),
                "round_seconds": round(time.monotonic() - began, 1),
            }
        )
        if progress:
            row = rows[-1]
            print(
                f"dagger-recurrent {config.kind} round {r}/{config.rounds} β={beta:.3g}: "
                f"mixture {row['rollout_mean_score']:,.0f}, learner on seeds "
                f"{VALIDATION_SEED}.. {val:,.0f}, {states:,} states, loss "
                f"{row['final_loss']:.4f}, play {played:.0f} s, fit {fitted:.0f} s, "
                f"{row['round_seconds']:.0f} s",
                flush=True,
            )
    assert best is not None
    seconds, cpu_seconds = time.monotonic() - start, time.process_time() - cpu_start
    states = sum(len(e) for e in aggregate)
    description = save_run(
        out,
        name=name,
        algorithm=ALGORITHM,
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
        title=f"sequence DAgger ({config.kind}), teacher {config.teacher}: {out.name}",
        training={"labelled_states_per_second": round(states / seconds, 1)},
    )
    return RecurrentPolicy(best[2], checkpoint.read_description(out)), description
