"""Playing a policy through the client's batched vector env, episode ``i`` seeded ``seed + i``:
the client's own evaluation loop (:func:`dinerdash.evaluation.play_seeded`) with a trained agent
choosing the actions, so agents, the expert and random play are measured the same way."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
from dinerdash import ConnectOptions
from dinerdash.evaluation import Progress, play_seeded

__all__ = ["evaluate_policy"]

Act = Callable[[np.ndarray, np.ndarray | None], np.ndarray]


def evaluate_policy(
    act: Act,
    episodes: int,
    *,
    seed: int = 0,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    num_envs: int = 64,
    max_steps: int = 100_000,
    use_mask: bool = True,
    progress: Progress | None = None,
    **connection: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Final scores and lengths of ``episodes`` episodes of ``act(obs, mask)`` (``mask`` is
    ``info["action_mask"]``, or ``None`` with ``use_mask=False``), in batches of ``num_envs``
    environments, as ``python -m dinerdash evaluate`` plays them. ``connect``: how to reach the
    server (:class:`dinerdash.ConnectOptions`), with ``address`` and the connection keywords
    (``timeout``, ``tls``, ``tls_ca``, ...) put in."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    n = max(1, min(num_envs, episodes))
    envs = gymnasium.make_vec(
        "dinerdash:DinerDash-v0", num_envs=n, address=address, connect=connect, **connection
    )
    try:
        return play_seeded(
            envs,
            lambda obs, info: act(obs, info["action_mask"] if use_mask else None),
            episodes,
            seed=seed,
            max_steps=max_steps,
            progress=progress,
        )
    finally:
        envs.close()
