"""Reading the demonstrations that ``python -m dinerdash collect`` writes, and slicing episodes.

The ``.npz`` holds every step of every episode back to back: ``observations`` (T, 40),
``actions`` (T,), ``action_masks`` (T, 57), and per episode ``episode_lengths`` and
``episode_starts`` (plus seeds and scores). The paper trains on "the first K trajectories", so
:func:`load_demos` keeps the steps of episodes ``0..K-1`` only.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE

from .errors import DemosError

__all__ = ["Demos", "load_demos"]

_FIELDS = ("observations", "actions", "action_masks", "episode_lengths", "episode_starts")


@dataclass(frozen=True)
class Demos:
    """The steps of the first ``episodes`` expert episodes of one file."""

    path: Path
    episodes: int
    #: episodes the file holds in all
    available: int
    observations: np.ndarray  # (T, 40) float32
    actions: np.ndarray  # (T,) int32
    action_masks: np.ndarray  # (T, 57) bool
    episode_lengths: np.ndarray  # (episodes,) int64
    seeds: np.ndarray | None

    @property
    def steps(self) -> int:
        return len(self.actions)


def load_demos(path: str | Path, episodes: int | None = None) -> Demos:
    """The first ``episodes`` episodes (all when ``None``) of a demonstrations file; a
    :class:`DemosError` naming the file and field for a missing, corrupt or too short file."""
    path = Path(path)
    if not path.is_file():
        raise DemosError(f"demonstrations file {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [f for f in _FIELDS if f not in data.files]
            if missing:
                raise DemosError(
                    f"demonstrations file {path} has no field {missing[0]!r} "
                    f"(expected the .npz written by `python -m dinerdash collect`)"
                )
            arrays = {f: data[f] for f in _FIELDS}
            seeds = data["seeds"] if "seeds" in data.files else None
    except DemosError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise DemosError(f"demonstrations file {path} is not a readable .npz: {e}") from e

    lengths = arrays["episode_lengths"].astype(np.int64)
    starts = arrays["episode_starts"].astype(np.int64)
    obs, actions, masks = arrays["observations"], arrays["actions"], arrays["action_masks"]
    total = len(actions)
    _check(path, "observations", obs.ndim == 2 and obs.shape == (total, OBSERVATION_SIZE))
    _check(path, "action_masks", masks.shape == (total, NUM_ACTIONS))
    _check(path, "episode_starts", starts.shape == lengths.shape)
    _check(path, "episode_lengths", lengths.ndim == 1 and int(lengths.sum()) == total)
    _check(path, "actions", bool(np.all((actions >= 0) & (actions < NUM_ACTIONS))))
    expected_starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]) if len(lengths) else starts
    _check(path, "episode_starts", bool(np.array_equal(starts, expected_starts)))

    available = len(lengths)
    k = available if episodes is None else int(episodes)
    if k < 1:
        raise DemosError(f"--episodes must be at least 1 (got {k})")
    if k > available:
        raise DemosError(
            f"--episodes {k} is more than demonstrations file {path} holds ({available} episodes)"
        )
    end = int(lengths[:k].sum())  # episodes are stored back to back from step 0
    return Demos(
        path=path,
        episodes=k,
        available=available,
        observations=obs[:end].astype(np.float32),
        actions=actions[:end].astype(np.int32),
        action_masks=masks[:end].astype(np.bool_),
        episode_lengths=lengths[:k].copy(),
        seeds=None if seeds is None else seeds[:k].copy(),
    )


def _check(path: Path, field: str, ok: bool) -> None:
    if not ok:
        raise DemosError(f"demonstrations file {path}: field {field!r} is inconsistent")
