"""Server-side rollouts (the ``Rollout`` RPC): whole episodes played by the server's policies and
streamed back, one message per episode, with no round trip per step.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._arguments import Config, make_config
from ._endpoint import Endpoint
from ._proto import pb
from .connection import ConnectOptions
from .game import NUM_ACTIONS, OBSERVATION_SIZE

__all__ = ["Episode", "rollout"]

_POLICIES = {"expert": pb.POLICY_EXPERT, "random": pb.POLICY_RANDOM, "planner": pb.POLICY_PLANNER}


@dataclass(frozen=True)
class Episode:
    """One episode of ``steps`` steps, as played on the server from ``seed``: ``observations``
    ``(steps + 1, 40) float32`` (the reset's, then one per step), ``actions``, ``rewards`` and
    ``expert_actions`` (the expert's choice before each step) ``(steps,)``, ``action_masks``
    ``(steps + 1, 57) bool`` when asked for, the final ``score`` and ``lost``, and how it ended
    (``truncated``: ``max_steps`` reached)."""

    seed: int
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    expert_actions: np.ndarray
    action_masks: np.ndarray | None
    score: int
    lost: int
    terminated: bool
    truncated: bool

    @property
    def steps(self) -> int:
        return len(self.actions)

    @classmethod
    def from_proto(cls, msg: pb.Episode) -> Episode:
        t = msg.steps
        obs = np.frombuffer(msg.observations, dtype=np.int8).reshape(t + 1, OBSERVATION_SIZE)
        masks = None
        if msg.action_masks:
            masks = (
                np.frombuffer(msg.action_masks, dtype=np.bool_).reshape(t + 1, NUM_ACTIONS).copy()
            )
        return cls(
            seed=msg.seed,
            observations=obs.astype(np.float32),
            actions=np.frombuffer(msg.actions, dtype=np.uint8).astype(np.int64),
            rewards=np.frombuffer(msg.rewards, dtype="<i4").astype(np.float64),
            expert_actions=np.frombuffer(msg.expert_actions, dtype=np.uint8).astype(np.int64),
            action_masks=masks,
            score=msg.score,
            lost=msg.lost,
            terminated=msg.terminated,
            truncated=msg.truncated,
        )


def rollout(
    policy: str = "expert",
    seeds: Iterable[int] | None = None,
    *,
    episodes: int | None = None,
    seed: int = 0,
    address: str | Sequence[str] | None = None,
    config: Config = None,
    max_steps: int | None = None,
    action_masks: bool = False,
    connect: ConnectOptions | None = None,
    **connection: Any,
) -> Iterator[Episode]:
    """Plays ``policy`` (``"expert"``, ``"random"`` or ``"planner"``) on the server, one episode
    per seed (``seeds``, or ``seed .. seed + episodes - 1``), and yields the :class:`Episode`
    objects in seed order as they arrive, in chunks of the server's ``max_rollout_episodes``.
    ``address``, ``connect`` and the connection keywords are the environments' (the stream has no
    overall deadline; keepalive pings notice a dead server)."""
    if policy not in _POLICIES:
        raise ValueError(f"policy must be one of {sorted(_POLICIES)}, got {policy!r}")
    if seeds is None:
        if episodes is None:
            raise ValueError("give seeds or episodes")
        seeds = range(seed, seed + episodes)
    seeds = [int(s) for s in seeds]
    options = ConnectOptions.merged(connect, "rollout", address=address, **connection)
    endpoint = Endpoint(options, pick=0)
    try:
        conn = endpoint.connections[0]
        chunk = max(1, conn.server_info().max_rollout_episodes or len(seeds) or 1)
        for i in range(0, max(len(seeds), 1), chunk):
            request = pb.RolloutRequest(
                policy=_POLICIES[policy],
                seeds=seeds[i : i + chunk],
                config=make_config(config),
                action_masks=action_masks,
            )
            if max_steps is not None:
                request.max_steps = max_steps
            for msg in conn.stream("Rollout", request):
                yield Episode.from_proto(msg)
    finally:
        endpoint.close()
