"""Playing a policy through the client's batched vector env, episode ``i`` seeded ``seed + i``,
and printing the result exactly as ``python -m dinerdash evaluate`` does."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import gymnasium
import numpy as np
from dinerdash.cli import Progress, _stats

__all__ = ["evaluate_policy", "print_evaluation"]

Act = Callable[[np.ndarray, np.ndarray | None], np.ndarray]


def evaluate_policy(
    act: Act,
    episodes: int,
    *,
    seed: int = 0,
    address: str | list[str] | None = None,
    num_envs: int = 64,
    max_steps: int = 100_000,
    use_mask: bool = True,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Final scores and lengths of ``episodes`` episodes of ``act(obs, mask)`` (``mask`` is
    ``info["action_mask"]``, or ``None`` with ``use_mask=False``). Batches of ``num_envs``
    environments are reset with consecutive seeds, as ``dinerdash.cli.evaluate_through_env``
    does, so the same seeds give the same episodes."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    n = max(1, min(num_envs, episodes))
    scores = np.zeros(episodes, dtype=np.int64)
    lengths = np.zeros(episodes, dtype=np.int64)
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=n, address=address)
    try:
        for first in range(0, episodes, n):
            # Seeds past the last episode only pad the batch; their episodes are ignored.
            seeds = [seed + first + i for i in range(n)]
            want = min(n, episodes - first)
            obs, info = envs.reset(seed=seeds)
            done = np.zeros(n, dtype=np.bool_)
            done[want:] = True
            steps = 0
            while not done.all():
                actions = act(obs, info["action_mask"] if use_mask else None)
                obs, _, terminated, truncated, info = envs.step(actions)
                steps += 1
                ended = (terminated | truncated | (steps >= max_steps)) & ~done
                if ended.any():
                    idx = np.flatnonzero(ended)
                    scores[first + idx] = info["score"][idx]
                    lengths[first + idx] = steps
                    done |= ended
                    if progress is not None:
                        progress.update(len(idx))
    finally:
        envs.close()
    return scores, lengths


def print_evaluation(
    policy: str,
    scores: np.ndarray,
    lengths: np.ndarray,
    *,
    seed: int,
    num_envs: int,
    elapsed: float,
    as_json: bool,
) -> None:
    """The lines ``python -m dinerdash evaluate`` prints (``--via env``), JSON line included."""
    episodes = len(scores)
    how = f"the client's vector env ({min(num_envs, episodes)} environments)"
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


def timed(fn: Callable[[], tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, float]:
    start = time.monotonic()
    scores, lengths = fn()
    return scores, lengths, time.monotonic() - start
