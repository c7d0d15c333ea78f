"""Checkpoints: a directory with the parameters (``model.eqx``) and a JSON description
(``checkpoint.json``: algorithm, format version, sizes, data used, training time); and the
:class:`Policy` that :func:`load` returns.

A checkpoint is written into a hidden sibling directory and renamed into place only when complete,
so a failed run leaves no half-written directory (and an older checkpoint of the same name stays
until the new one is whole).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE

from . import bc, dagger, dpgm, kickstart, ppo, recurrent
from .errors import CheckpointError
from .supervised import masked_logits

__all__ = ["ALGORITHMS", "FORMAT", "FORMAT_VERSION", "Policy", "load", "save"]

FORMAT = "dinerdash-agents checkpoint"
FORMAT_VERSION = 1
DESCRIPTION = "checkpoint.json"
PARAMETERS = "model.eqx"

#: algorithm name -> (module with init/train/config_from_json, its config class)
ALGORITHMS: dict[str, Any] = {
    "bc": bc,
    "dpgm": dpgm,
    "ppo": ppo,
    "ppo-masked": ppo,
    "gail": ppo,
    "ppo-kickstart": kickstart,
    "dagger": dagger,
    "dagger-recurrent": recurrent,
}


class Policy:
    """A trained agent: greedy over the legal actions of each state of a batch.

    ``act(obs, action_mask)`` takes ``obs`` (B, 40) and ``action_mask`` (B, 57) as a Gymnasium
    vector env returns them (``info["action_mask"]``) and returns (B,) int64 actions; with
    ``action_mask=None`` the greedy choice runs over all 57 actions.
    """

    def __init__(self, model: Any, description: dict[str, Any]) -> None:
        self.model = model
        self.description = description
        self.algorithm: str = description["algorithm"]
        self.name: str = description.get("name", self.algorithm)
        # A DAgger learner with memory sees its observations' history (dagger.MemoryFeatures):
        # such a policy is stateful, one memory per environment of the batches it is given.
        config = description.get("config") or {}
        self._memory = (
            dagger.MemoryFeatures()
            if self.algorithm == "dagger" and config.get("memory", False)
            else None
        )

    def act(self, obs: Any, action_mask: Any | None = None) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        single = obs.ndim == 1
        if single:
            obs = obs[None]
        if obs.ndim != 2 or obs.shape[1] != OBSERVATION_SIZE:
            raise ValueError(f"obs must have shape (B, {OBSERVATION_SIZE}), got {obs.shape}")
        use_mask = action_mask is not None
        if use_mask:
            mask = np.asarray(action_mask, dtype=np.bool_).reshape(obs.shape[0], NUM_ACTIONS)
        else:
            mask = np.ones((obs.shape[0], NUM_ACTIONS), dtype=np.bool_)
        if self._memory is not None:
            obs = self._memory.augment(obs)
        actions = np.asarray(_greedy(self.model, obs, mask, use_mask), dtype=np.int64)
        return actions[0] if single else actions

    __call__ = act


@eqx.filter_jit
def _greedy(model: Any, obs: jax.Array, mask: jax.Array, use_mask: bool) -> jax.Array:
    # One jitted function for every policy: models of the same shape share its compilation.
    logits = model(obs, mask)
    return jnp.argmax(masked_logits(logits, mask if use_mask else None), axis=-1)


def save(
    directory: str | Path,
    model: Any,
    description: dict[str, Any],
    extra: Callable[[Path], None] | None = None,
) -> Path:
    """Writes ``model`` and ``description`` to ``directory`` atomically; returns the path.
    ``extra(tmp)`` writes further files into the directory before it is renamed into place."""
    directory = Path(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    description = {"format": FORMAT, "format_version": FORMAT_VERSION, **description}
    tmp = Path(tempfile.mkdtemp(prefix=f".{directory.name}.", dir=directory.parent))
    try:
        tmp.chmod(0o755)  # mkdtemp's 0700 would make a committed checkpoint private
        eqx.tree_serialise_leaves(tmp / PARAMETERS, model)
        (tmp / DESCRIPTION).write_text(json.dumps(description, indent=2) + "\n")
        if extra is not None:
            extra(tmp)
        if directory.exists():
            old = directory.with_name(f".{directory.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(directory, old)
            os.replace(tmp, directory)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return directory


def read_description(directory: str | Path) -> dict[str, Any]:
    directory = Path(directory)
    path = directory / DESCRIPTION
    if not directory.is_dir():
        raise CheckpointError(f"checkpoint directory {directory} does not exist")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {directory} has no {DESCRIPTION}")
    try:
        description = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise CheckpointError(f"{path} is not valid JSON: {e}") from e
    if not isinstance(description, dict) or description.get("format") != FORMAT:
        raise CheckpointError(f"{path}: field 'format' is not {FORMAT!r}")
    version = description.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: field 'format_version' is {version!r}; this package reads version "
            f"{FORMAT_VERSION}"
        )
    return description


def load(directory: str | Path, algorithm: str | None = None) -> Policy:
    """The :class:`Policy` of a checkpoint directory; with ``algorithm``, a checkpoint of another
    algorithm is refused. A :class:`CheckpointError` names the file and field that is wrong."""
    directory = Path(directory)
    description = read_description(directory)
    path = directory / DESCRIPTION
    found = description.get("algorithm")
    if found not in ALGORITHMS:
        raise CheckpointError(
            f"{path}: field 'algorithm' is {found!r}; known: {', '.join(ALGORITHMS)}"
        )
    if algorithm is not None and found != algorithm:
        raise CheckpointError(f"{path}: field 'algorithm' is {found!r}, expected {algorithm!r}")
    module = ALGORITHMS[found]
    try:
        config = module.config_from_json(description["config"])
    except (KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: field 'config' does not fit {found}: {e}") from e
    if found == "dpgm" and (config.factors, config.cells) != (
        len(dpgm.FACTORS),
        dpgm.CELLS,
    ):
        raise CheckpointError(
            f"{path}: field 'config' has {config.factors} factors and {config.cells} cells; "
            f"this version's factor layout has {len(dpgm.FACTORS)} and {dpgm.CELLS}"
        )
    skeleton = module.init(config, 0)
    params = directory / PARAMETERS
    if not params.is_file():
        raise CheckpointError(f"checkpoint {directory} has no {PARAMETERS}")
    try:
        model = eqx.tree_deserialise_leaves(params, skeleton)
    except Exception as e:  # equinox/numpy raise several types for a truncated or foreign file
        raise CheckpointError(f"{params} does not hold {found} parameters: {e!r}") from e
    jax.block_until_ready(jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array)))
    # A module whose policy keeps state (one memory per environment) builds its own.
    make_policy = getattr(module, "make_policy", None)
    return make_policy(model, description) if make_policy else Policy(model, description)
