"""Games played on the server's ``/play`` page, as demonstrations: a recording (JSON, its format
in docs/play.md) is replayed from its seed through a server of its ruleset (:func:`replay`), and
:func:`collect_from_play` writes the replays as ``collect`` writes the expert's episodes. A
recording that is malformed, of another ruleset, or that does not replay to its score is refused
with a :class:`RecordingError` naming the file and the step, before anything is written.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._arguments import CONFIG_FIELDS
from .game import NUM_ACTIONS
from .rollout import Episode

__all__ = ["FORMAT", "RecordingError", "collect_from_play", "load_recording", "replay"]

#: The recording format this client reads.
FORMAT = "dinerdash-play/1"


class RecordingError(ValueError):
    """A recording that cannot become a demonstration: the message names the file and, when the
    replay got that far, the step."""


def load_recording(path: str | os.PathLike) -> dict[str, Any]:
    """The recording at ``path``, checked for shape (format, types, actions in 0..56, steps
    equal to the number of actions); a :class:`RecordingError` naming what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise RecordingError(f"{path}: not a readable JSON recording: {e}") from e

    def bad(what: str) -> RecordingError:
        return RecordingError(f"{path}: malformed recording: {what}")

    if not isinstance(data, dict):
        raise bad("not a JSON object")
    if data.get("format") != FORMAT:
        raise bad(f"format is {data.get('format')!r}, this client reads {FORMAT!r}")
    for key in ("ruleset", "seed", "config", "actions", "score", "steps", "lost", "finished"):
        if key not in data:
            raise bad(f"no {key!r}")
    if not isinstance(data["ruleset"], str):
        raise bad("ruleset is not a string")
    for key in ("seed", "score", "steps", "lost"):
        if not isinstance(data[key], int) or isinstance(data[key], bool):
            raise bad(f"{key} is not a whole number")
    if not 0 <= data["seed"] < 2**64:
        raise bad("seed is outside 0..2^64-1")
    config = data["config"]
    if not isinstance(config, dict):
        raise bad("config is not an object")
    for key, value in config.items():
        if key not in CONFIG_FIELDS:
            raise bad(f"config has an unknown field {key!r}")
        if value is not None and (not isinstance(value, int) or isinstance(value, bool)):
            raise bad(f"config.{key} is not a whole number")
    actions = data["actions"]
    if not isinstance(actions, list):
        raise bad("actions is not a list")
    for i, a in enumerate(actions):
        if not isinstance(a, int) or isinstance(a, bool) or not 0 <= a < NUM_ACTIONS:
            raise RecordingError(
                f"{path}: malformed recording: step {i}: action {a!r} is not in "
                f"0..{NUM_ACTIONS - 1}"
            )
    if data["steps"] != len(actions):
        raise bad(f"steps is {data['steps']} but there are {len(actions)} actions")
    if not actions:
        raise bad("no actions: nothing to learn from")
    return data


def replay(
    recording: dict[str, Any],
    *,
    name: str = "recording",
    address: str | Sequence[str] | None = None,
    **connection: Any,
) -> Episode:
    """Plays ``recording``'s actions from its seed through a server (``address``, else a local
    one) and returns the :class:`~dinerdash.rollout.Episode`, with the masks and the reference
    expert's choices; a :class:`RecordingError` (naming ``name`` and the step) when the server's
    ruleset is another, an action is not legal in the replay, the episode ends before the actions
    do, or the replay's score is not the recording's."""
    from .env import DinerDashEnv

    config = {k: v for k, v in recording["config"].items() if v is not None}
    env = DinerDashEnv(address, expert=True, config=config, **connection)
    try:
        ruleset = env.spec_proto.ruleset
        if recording["ruleset"] != ruleset:
            raise RecordingError(
                f"{name}: the recording is of ruleset {recording['ruleset']!r}, the server plays "
                f"{ruleset!r}: it cannot be replayed here"
            )
        obs, info = env.reset(seed=int(recording["seed"]))
        observations, masks, experts, rewards = [obs], [info["action_mask"]], [], []
        terminated = truncated = False
        actions = recording["actions"]
        for i, a in enumerate(actions):
            if terminated or truncated:
                raise RecordingError(
                    f"{name}: step {i}: the replay's episode ended at step {i}, but the recording "
                    f"has {len(actions)} actions: it does not replay"
                )
            if not info["action_mask"][a]:
                raise RecordingError(
                    f"{name}: step {i}: action {a} is not legal in the replay: it does not replay"
                )
            experts.append(info["expert_action"])
            obs, reward, terminated, truncated, info = env.step(a)
            observations.append(obs)
            masks.append(info["action_mask"])
            rewards.append(reward)
        score, lost = int(info["score"]), int(info.get("lost", 0))
    finally:
        env.close()
    if score != recording["score"]:
        raise RecordingError(
            f"{name}: step {len(actions) - 1} (the last): the replay's score is {score}, the "
            f"recording says {recording['score']}: it does not replay"
        )
    return Episode(
        seed=int(recording["seed"]),
        observations=np.asarray(observations, dtype=np.float32),
        actions=np.asarray(actions, dtype=np.int64),
        rewards=np.asarray(rewards, dtype=np.float64),
        expert_actions=np.asarray(experts, dtype=np.int64),
        action_masks=np.asarray(masks, dtype=np.bool_),
        score=score,
        lost=lost,
        terminated=bool(terminated),
        truncated=bool(truncated),
    )


def collect_from_play(
    recordings: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    address: str | Sequence[str] | None = None,
    progress: Any = None,
    **connection: Any,
):
    """Replays every recording (all are read, checked and replayed first: one refused recording
    writes nothing) and writes them to ``out/dinerdash_play.npz`` as ``collect`` writes the
    expert's; returns the :class:`~dinerdash.evaluation.Collected`."""
    from .evaluation import Collected, write_npz

    if not recordings:
        raise RecordingError("no recordings given")
    loaded = [(str(p), load_recording(p)) for p in recordings]
    played = []
    for name, recording in loaded:
        played.append(replay(recording, name=name, address=address, **connection))
        if progress is not None:
            progress.update()
    path = Path(out) / "dinerdash_play.npz"
    write_npz(path, played)
    return Collected(path, "play", played)
