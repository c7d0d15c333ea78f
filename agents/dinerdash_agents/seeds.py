"""The seeds a checkpoint was trained on, as its ``checkpoint.json`` records them, and the
evaluation seeds that keep clear of them: what ``evaluate`` starts at when not told, and what it
warns about when told to play on seeds the checkpoint has seen.

A checkpoint records them as ``data["seed_ranges"]``, ``[first, last]`` pairs: the
demonstrations' episodes (``bc``, ``dpgm``; ``gail``'s discriminator), DAgger's episodes, the
seeds of an RL run's environments' first resets (both skip :data:`RESERVED_SEEDS`; each later
episode of an environment continues its random stream, which no seeded episode replays) and,
for ``ppo-kickstart``, those of the checkpoint it started from. Checkpoints written before the
field hold ``data["seeds"]``, ``[first, last]`` of their demonstrations or DAgger episodes, which
:func:`trained_on` reads instead (an RL checkpoint of then records none).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from dinerdash.evaluation import EVALUATION_SEEDS

__all__ = [
    "EVALUATION_SEEDS",
    "RESERVED_SEEDS",
    "SELECTION_SEEDS",
    "VALIDATION_SEEDS",
    "as_ranges",
    "evaluation_seed",
    "overlap",
    "overlap_warning",
    "spelled",
    "trained_on",
    "training_seeds",
]

#: DAgger's validation seeds (its learner after each round is judged there).
VALIDATION_SEEDS = range(2000, 2100)
#: Where an experiment is kept or not before the evaluation seeds are looked at
#: (docs/agents.md): DAgger's validation seeds and the 300 after them.
SELECTION_SEEDS = range(2000, 2400)
#: Seeds no training episode of the package's runs takes.
RESERVED_SEEDS = (EVALUATION_SEEDS, SELECTION_SEEDS)
#: The seeds a ``data["seeds"]`` span skipped when it was written (before ``seed_ranges``).
_SKIPPED_BEFORE = (EVALUATION_SEEDS, VALIDATION_SEEDS)
#: Algorithms whose ``data["seeds"]`` span skips :data:`_SKIPPED_BEFORE`.
_SKIPPING = ("dagger", "dagger-recurrent")


def training_seeds(start: int, count: int) -> list[int]:
    """``count`` seeds from ``start`` upwards, skipping :data:`RESERVED_SEEDS`: the seeds of
    DAgger's episodes and of an RL run's environments' first resets."""
    seeds, s = [], start
    while len(seeds) < count:
        if not any(s in r for r in RESERVED_SEEDS):
            seeds.append(s)
        s += 1
    return seeds


def as_ranges(seeds: Iterable[int]) -> list[list[int]]:
    """``seeds`` as sorted ``[first, last]`` runs of consecutive seeds (duplicates merged): what
    ``data["seed_ranges"]`` holds."""
    runs: list[list[int]] = []
    for s in sorted({int(s) for s in seeds}):
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    return runs


def trained_on(description: Mapping[str, Any]) -> list[range]:
    """The seeds a checkpoint's description records it was trained on (see the module's
    docstring), as ranges; ``[]`` when it records none."""
    data = description.get("data") or {}
    if data.get("seed_ranges") is not None:
        return [range(first, last + 1) for first, last in data["seed_ranges"]]
    if data.get("seeds") is None:
        return []
    first, last = data["seeds"]
    span = range(first, last + 1)
    if description.get("algorithm") not in _SKIPPING:
        return [span]
    kept = (s for s in span if not any(s in r for r in _SKIPPED_BEFORE))
    return [range(first, last + 1) for first, last in as_ranges(kept)]


def overlap(trained: Iterable[range], seed: int, episodes: int) -> list[range]:
    """The parts of ``trained`` that the seeds ``seed .. seed + episodes - 1`` fall in."""
    played = range(seed, seed + episodes)
    parts = (range(max(r.start, played.start), min(r.stop, played.stop)) for r in trained)
    return [r for r in parts if len(r)]


def evaluation_seed(trained: Iterable[range], episodes: int) -> int:
    """Where an evaluation of ``episodes`` episodes starts when not told: the first evaluation
    seed (1000), or, if the checkpoint was trained on any of the seeds from there, the first
    seed after them from which ``episodes`` seeds in a row are all unseen."""
    trained = list(trained)
    seed = EVALUATION_SEEDS.start
    while True:
        hit = overlap(trained, seed, episodes)
        if not hit:
            return seed
        seed = max(r.stop for r in hit)


def spelled(ranges: Iterable[range]) -> str:
    """``0..273, 2100..2199``: ranges as the documentation writes them."""
    return ", ".join(f"{r.start}..{r.stop - 1}" for r in ranges)


def overlap_warning(name: str, trained: list[range], seed: int, episodes: int) -> str | None:
    """The warning for an evaluation of checkpoint ``name`` on seeds ``seed ..`` that it was
    trained on in part, naming both ranges; ``None`` when they do not overlap."""
    hit = overlap(trained, seed, episodes)
    if not hit:
        return None
    return (
        f"evaluating on seeds {seed}..{seed + episodes - 1}, of which {spelled(hit)} are seeds "
        f"{name} was trained on ({spelled(trained)}): its score there is not a held-out one "
        f"(the evaluation seeds are {spelled([EVALUATION_SEEDS])})"
    )
