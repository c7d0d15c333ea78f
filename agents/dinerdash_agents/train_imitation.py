"""One imitation-learning run (``train bc|dpgm``): the first K episodes of a demonstrations file
-> a trained agent -> a checkpoint directory with the description of what was done, and the live
curves beside it (:class:`~dinerdash_agents.curves.LiveCurves`): each epoch's mean loss as
``train/loss/<stage>`` (``bc``; DPGM's three stages), at the epoch's number counted over the
stages."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from dinerdash.evaluation import Progress

from . import bc, checkpoint, dpgm
from ._version import __version__
from .curves import LiveCurves
from .demos import load_demos
from .errors import AgentsError
from .seeds import as_ranges

__all__ = ["IMITATION", "default_config", "train_checkpoint"]

#: The imitation algorithms of ``train``: each module's ``train(demos, config, ...)`` and config.
IMITATION = {"bc": (bc, bc.BCConfig), "dpgm": (dpgm, dpgm.DPGMConfig)}


def default_config(algorithm: str, *, epochs: int | None = None, loss: str = "masked") -> Any:
    """The algorithm's default config; ``epochs`` replaces the epochs of every stage."""
    if algorithm not in IMITATION:
        raise AgentsError(f"unknown algorithm {algorithm!r} (known: {', '.join(IMITATION)})")
    if loss not in ("masked", "plain"):
        raise AgentsError(f"--loss must be masked or plain, got {loss!r}")
    if epochs is not None and epochs < 1:
        raise AgentsError(f"--epochs must be at least 1 (got {epochs})")
    config = IMITATION[algorithm][1](loss=loss)
    return config if epochs is None else config.with_epochs(epochs)


def train_checkpoint(
    algorithm: str,
    demos_path: str | Path,
    out: str | Path,
    *,
    episodes: int | None = None,
    seed: int = 0,
    config: Any = None,
    name: str | None = None,
    progress: bool = True,
    tensorboard: str | Path | None = None,
) -> tuple[checkpoint.Policy, dict]:
    """Trains ``algorithm`` on the first ``episodes`` episodes of ``demos_path`` and writes the
    checkpoint to ``out`` (atomically); returns the policy and its description. ``tensorboard``:
    the directory of the live curves (``None``: none written)."""
    if config is None:
        config = default_config(algorithm)
    demos = load_demos(demos_path, episodes)
    module = IMITATION[algorithm][0]
    bar = Progress(config.total_epochs, f"train {name or algorithm}") if progress else None
    losses_seen: list[float] = []
    live = LiveCurves(tensorboard)

    def on_epoch(stage: str, epoch: int, loss: float) -> None:
        losses_seen.append(loss)
        live.add(len(losses_seen), {f"train/loss/{stage.replace(' ', '_')}": loss})
        if bar is not None:
            bar.update()

    start, cpu_start = time.monotonic(), time.process_time()
    with live:
        model, losses = module.train(demos, config, seed=seed, on_epoch=on_epoch)
    # Wall time depends on what else the machine runs; CPU time (all threads) much less so.
    seconds, cpu_seconds = time.monotonic() - start, time.process_time() - cpu_start
    if bar is not None:
        bar.close()

    description = {
        "name": name or Path(out).name,
        "algorithm": algorithm,
        "package_version": __version__,
        "config": config.to_json(),
        "data": {
            "demos": Path(demos_path).name,
            "episodes": demos.episodes,
            "episodes_in_file": demos.available,
            "steps": demos.steps,
            "seeds": None if demos.seeds is None else [int(s) for s in demos.seeds[[0, -1]]],
            "seed_ranges": None if demos.seeds is None else as_ranges(demos.seeds),
        },
        "training": {
            "seed": seed,
            "seconds": round(seconds, 3),
            "cpu_seconds": round(cpu_seconds, 3),
            "final_losses": {stage: round(v[-1], 6) for stage, v in losses.items() if v},
        },
    }
    checkpoint.save(out, model, description)
    return checkpoint.Policy(model, checkpoint.read_description(out)), description
