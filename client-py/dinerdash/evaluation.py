"""Seeded evaluation and demonstration collection: the library under ``python -m dinerdash
evaluate`` and ``collect`` and the agents' commands. Every evaluation plays through
:func:`play_seeded` (episode ``i`` reset with ``seed + i``), so the same seeds give the same
episodes; ``**connection`` is any connection keyword of the environments.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from ._arguments import EXPERTS
from .game import NUM_ACTIONS, observation_space

if TYPE_CHECKING:
    from .rollout import Episode

__all__ = [
    "EVALUATION_SEEDS",
    "Collected",
    "Progress",
    "collect",
    "evaluate_by_rollout",
    "evaluate_through_env",
    "play_seeded",
    "print_evaluation",
    "write_minari",
]

#: The project's evaluation seeds (docs/agents.md): every result is measured on them and no agent
#: is trained on them. ``evaluate`` starts at the first of them unless told otherwise.
EVALUATION_SEEDS = range(1000, 1100)


class Progress:
    """A dependency-free progress bar on stderr: redrawn in place on a terminal, a line every
    10 % otherwise (CI logs)."""

    def __init__(
        self, total: int, desc: str, stream: TextIO | None = None, width: int = 30
    ) -> None:
        self.total = max(int(total), 1)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.done = 0
        self.start = time.monotonic()
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_draw = 0.0
        self._last_decile = -1

    def update(self, n: int = 1) -> None:
        self.done = min(self.done + n, self.total)
        now = time.monotonic()
        if self._tty:
            if now - self._last_draw >= 0.1 or self.done == self.total:
                self._last_draw = now
                self._draw(now, end="\r")
        else:
            decile = self.done * 10 // self.total
            if decile != self._last_decile:
                self._last_decile = decile
                self._draw(now, end="\n")

    def _draw(self, now: float, end: str) -> None:
        filled = self.width * self.done // self.total
        rate = self.done / max(now - self.start, 1e-9)
        bar = "#" * filled + "." * (self.width - filled)
        self.stream.write(f"{self.desc} [{bar}] {self.done}/{self.total} {rate:,.1f}/s{end}")
        self.stream.flush()

    def close(self) -> None:
        if self._tty:
            self.stream.write("\n")
            self.stream.flush()


def _stats(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean, population sd (the simulator's ``±``) and sample sd."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return math.nan, math.nan, math.nan
    sample = float(a.std(ddof=1)) if a.size > 1 else 0.0
    return float(a.mean()), float(a.std()), sample


def play_seeded(
    envs: Any,
    act: Callable[[np.ndarray, dict[str, Any]], np.ndarray],
    episodes: int,
    *,
    seed: int,
    max_steps: int,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Plays ``act(obs, info)`` on the vector env ``envs`` for ``episodes`` episodes, episode
    ``i`` reset with ``seed + i`` (batches of ``envs.num_envs``), each cut at ``max_steps``;
    returns the final scores and the lengths."""
    n = envs.num_envs
    scores = np.zeros(episodes, dtype=np.int64)
    lengths = np.zeros(episodes, dtype=np.int64)
    for first in range(0, episodes, n):
        # Seeds past the last episode only pad the batch; their episodes are ignored.
        seeds = [seed + first + i for i in range(n)]
        want = min(n, episodes - first)
        obs, info = envs.reset(seed=seeds)
        done = np.zeros(n, dtype=np.bool_)
        done[want:] = True
        steps = 0
        while not done.all():
            obs, _, terminated, truncated, info = envs.step(act(obs, info))
            steps += 1
            ended = (terminated | truncated | (steps >= max_steps)) & ~done
            if ended.any():
                idx = np.flatnonzero(ended)
                scores[first + idx] = info["score"][idx]
                lengths[first + idx] = steps
                done |= ended
                if progress is not None:
                    progress.update(len(idx))
    return scores, lengths


def evaluate_through_env(
    policy: str,
    episodes: int,
    *,
    seed: int = 0,
    address: str | Sequence[str] | None = None,
    num_envs: int = 64,
    max_steps: int = 100_000,
    progress: Progress | None = None,
    **connection: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Plays ``policy`` (``"expert"``, ``"planner"``: ``info["expert_action"]``; ``"random"``:
    uniform over every action) through a vector env of up to ``num_envs`` environments, episode
    ``i`` reset with ``seed + i``; returns the final scores and the lengths."""
    from .vector import DinerDashVectorEnv

    if policy not in (*EXPERTS, "random"):
        raise ValueError(f"policy must be one of {[*sorted(EXPERTS), 'random']}, got {policy!r}")
    n = max(1, min(num_envs, episodes))
    rng = np.random.default_rng(seed)
    expert = policy in EXPERTS
    envs = DinerDashVectorEnv(n, address, expert=policy if expert else False, **connection)
    actions = int(envs.single_action_space.n)

    def act(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return info["expert_action"] if expert else rng.integers(0, actions, size=n)

    try:
        return play_seeded(envs, act, episodes, seed=seed, max_steps=max_steps, progress=progress)
    finally:
        envs.close()


def evaluate_by_rollout(
    policy: str,
    episodes: int,
    *,
    seed: int = 0,
    address: str | Sequence[str] | None = None,
    max_steps: int = 100_000,
    progress: Progress | None = None,
    **connection: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Lets the server play ``policy`` for ``episodes`` whole episodes (seeds ``seed ..``) with
    :func:`~dinerdash.rollout`; returns the final scores and the lengths, as
    :func:`evaluate_through_env` does."""
    scores, lengths = [], []
    for ep in _played(
        policy,
        progress,
        episodes=episodes,
        seed=seed,
        address=address,
        max_steps=max_steps,
        **connection,
    ):
        scores.append(ep.score)
        lengths.append(ep.steps)
    return np.array(scores, dtype=np.int64), np.array(lengths, dtype=np.int64)


def _played(policy: str, progress: Progress | None, **rollout_args: Any) -> Iterator[Episode]:
    """:func:`~dinerdash.rollout`'s episodes, each counted on ``progress``."""
    from .rollout import rollout

    for ep in rollout(policy, **rollout_args):
        yield ep
        if progress is not None:
            progress.update()


def print_evaluation(
    policy: str,
    scores: Sequence[int],
    lengths: Sequence[int],
    *,
    seed: int,
    how: str,
    elapsed: float,
    as_json: bool,
) -> None:
    """What ``evaluate`` prints: the episodes, score and length mean ± sd, the speed, and with
    ``as_json`` a last line of JSON (policy, seed, scores, lengths, mean, sd)."""
    episodes = len(scores)
    mean, sd, sample = _stats(scores)
    lmean, lsd, _ = _stats(lengths)
    total = int(np.sum(lengths))
    print(
        f"policy {policy}: {episodes} episodes (seeds {seed}..={seed + episodes - 1}) through {how}"
    )
    print(f"score  {mean:.1f} ± {sd:.1f} (sample sd {sample:.1f})")
    print(f"length {lmean:.1f} ± {lsd:.1f} steps")
    print(f"{total} steps in {elapsed:.3f} s: {total / max(elapsed, 1e-9):.0f} steps/s")
    if as_json:
        print(
            json.dumps(
                {
                    "policy": policy,
                    "seed": seed,
                    "scores": [int(s) for s in scores],
                    "lengths": [int(x) for x in lengths],
                    "mean": mean,
                    "sd": sd,
                }
            )
        )


@dataclass(frozen=True)
class Collected:
    """What :func:`collect` wrote: the ``.npz`` at ``path``, and the episodes it holds."""

    path: Path
    policy: str
    #: In seed order.
    episodes: list[Episode]

    @property
    def steps(self) -> int:
        return sum(ep.steps for ep in self.episodes)

    @property
    def scores(self) -> np.ndarray:
        return np.array([ep.score for ep in self.episodes], dtype=np.int64)


def collect(
    out: str | os.PathLike,
    *,
    policy: str = "expert",
    episodes: int = 274,
    seed: int = 0,
    address: str | Sequence[str] | None = None,
    max_steps: int | None = None,
    progress: Progress | None = None,
    **connection: Any,
) -> Collected:
    """Lets the server's ``policy`` (``"expert"``, the reference heuristic, or ``"planner"``)
    play ``episodes`` episodes (seeds ``seed ..``) and writes them to
    ``out/dinerdash_<policy>.npz``: every step back to back (``observations``,
    ``next_observations``, ``actions``, ``rewards``, ``terminations``, ``truncations``,
    ``action_masks``) and per episode ``episode_lengths``, ``episode_starts``, ``seeds`` and
    ``scores``."""
    if policy not in EXPERTS:
        raise ValueError(f"policy must be one of {sorted(EXPERTS)}, got {policy!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    played = list(
        _played(
            policy,
            progress,
            episodes=episodes,
            seed=seed,
            address=address,
            max_steps=max_steps,
            action_masks=True,
            **connection,
        )
    )
    path = out / f"dinerdash_{policy}.npz"
    write_npz(path, played)
    return Collected(path, policy, played)


def write_npz(path: Path, played: Sequence[Episode]) -> None:
    """Writes ``played`` to ``path`` in the layout :func:`collect` documents (the demonstrations
    of ``python -m dinerdash_agents``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lengths = np.array([ep.steps for ep in played], dtype=np.int64)
    np.savez_compressed(
        path,
        observations=np.concatenate([ep.observations[:-1] for ep in played]),
        next_observations=np.concatenate([ep.observations[1:] for ep in played]),
        actions=np.concatenate([ep.actions for ep in played]),
        rewards=np.concatenate([ep.rewards for ep in played]),
        terminations=np.concatenate([_last_flag(ep.steps, ep.terminated) for ep in played]),
        truncations=np.concatenate([_last_flag(ep.steps, ep.truncated) for ep in played]),
        action_masks=np.concatenate([ep.action_masks[:-1] for ep in played]),
        episode_lengths=lengths,
        episode_starts=np.concatenate([[0], np.cumsum(lengths)[:-1]]),
        seeds=np.array([ep.seed for ep in played], dtype=np.uint64),
        scores=np.array([ep.score for ep in played], dtype=np.int64),
    )


#: How a Minari dataset names who played its episodes.
_ALGORITHMS = {
    "expert": "reference expert (docs/rules.md section 8), server-side rollout",
    "planner": "look-ahead planner, server-side rollout",
    "play": "a person on the server's /play page, replayed from its recordings",
}


def write_minari(collected: Collected, dataset_id: str | None = None) -> Path | None:
    """Writes the collected episodes as the Minari dataset ``dataset_id`` (default
    ``dinerdash/<policy>-v0``) under ``minari/`` beside the ``.npz`` (or ``MINARI_DATASETS_PATH``)
    and returns that root; ``None`` when ``minari`` is not installed."""
    try:
        import minari  # noqa: F401
    except ImportError:
        return None
    out = collected.path.parent
    root = Path(os.environ.setdefault("MINARI_DATASETS_PATH", str((out / "minari").resolve())))
    import gymnasium
    from gymnasium import spaces
    from minari import create_dataset_from_buffers
    from minari.data_collector import EpisodeBuffer

    from .env import DinerDashEnv

    episodes, policy = collected.episodes, collected.policy
    buffers = [
        EpisodeBuffer(
            id=i,
            seed=int(ep.seed),
            observations=ep.observations,
            actions=ep.actions,
            rewards=list(ep.rewards),
            terminations=list(_last_flag(ep.steps, ep.terminated)),
            truncations=list(_last_flag(ep.steps, ep.truncated)),
            infos={"action_mask": ep.action_masks},
        )
        for i, ep in enumerate(episodes)
    ]
    with warnings.catch_warnings():
        # Minari's advice to a dataset's author (a code permalink, an e-mail), not to our user.
        warnings.filterwarnings("ignore", message="`(code_permalink|author_email)` is set to None")
        create_dataset_from_buffers(
            dataset_id=dataset_id or f"dinerdash/{policy}-v0",
            buffer=buffers,
            env=gymnasium.spec("DinerDash-v0"),  # registered by importing dinerdash
            eval_env=gymnasium.spec("DinerDash-v0"),
            # A rollout carries no Spec: the spaces of ruleset v0, as its servers report them.
            observation_space=observation_space(),
            action_space=spaces.Discrete(NUM_ACTIONS),
            algorithm_name=_ALGORITHMS.get(policy, policy),
            author="dinerdash",
            description=f"{len(episodes)} {policy} episodes of {DinerDashEnv.__name__}, ruleset v0",
        )
    return root


def _last_flag(steps: int, value: bool) -> np.ndarray:
    flags = np.zeros(steps, dtype=np.bool_)
    if steps:
        flags[-1] = value
    return flags
