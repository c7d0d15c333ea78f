"""Checkpoints: a directory with the parameters (``model.eqx``) and a JSON description
(``checkpoint.json``: algorithm, the module that defines it, format version, sizes, data used,
training time); the :class:`Policy` that :func:`load` returns; and the registry of algorithms.

Each algorithm module adds itself to the registry when it is imported
(``checkpoint.register("bc", module=__name__, config_from_json=..., init=...)``), and
:func:`save` writes that module's name into ``checkpoint.json`` (``"module"``), so :func:`load`
imports only the algorithm a checkpoint needs: this module imports none of them. Checkpoints
written before the field existed name no module; :data:`LEGACY_MODULES` maps their algorithms.

A checkpoint is written into a hidden sibling directory and renamed into place only when complete,
so a failed run leaves no half-written directory (and an older checkpoint of the same name stays
until the new one is whole).
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE

from .errors import CheckpointError
from .supervised import masked_logits

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "Algorithm",
    "Policy",
    "load",
    "lookup",
    "read_description",
    "register",
    "save",
]

FORMAT = "dinerdash-agents checkpoint"
FORMAT_VERSION = 1
DESCRIPTION = "checkpoint.json"
PARAMETERS = "model.eqx"

#: The package whose modules a checkpoint's ``"module"`` may name: loading a checkpoint imports
#: that module, so a file cannot make it import anything else. An algorithm defined elsewhere is
#: loaded once its own module has been imported (and so has registered it).
PACKAGE = __name__.rpartition(".")[0]
#: Checkpoints written before ``"module"`` was recorded: their algorithm -> the module to import.
LEGACY_MODULES = {
    "bc": f"{PACKAGE}.bc",
    "dpgm": f"{PACKAGE}.dpgm",
    "ppo": f"{PACKAGE}.ppo",
    "ppo-masked": f"{PACKAGE}.ppo",
    "gail": f"{PACKAGE}.gail",
    "ppo-kickstart": f"{PACKAGE}.kickstart",
    "dagger": f"{PACKAGE}.dagger",
    "dagger-recurrent": f"{PACKAGE}.recurrent",
}


@dataclass(frozen=True)
class Algorithm:
    """What :func:`load` needs of an algorithm: its model's skeleton and config, and what a
    :class:`Policy` of it does beyond the greedy choice."""

    name: str
    #: The module that registered it: written into ``checkpoint.json`` as ``"module"``.
    module: str
    #: The checkpoint's ``"config"`` (JSON) -> the algorithm's config value.
    config_from_json: Callable[[dict], Any]
    #: ``init(config, seed)``: a model of the config's shape (the skeleton parameters load into).
    init: Callable[[Any, int], Any]
    #: ``check(config)``: why a checkpoint of this config cannot be loaded by this version, or
    #: ``None`` (e.g. DPGM's factor layout).
    check: Callable[[Any], str | None] | None = None
    #: ``view(config)``: a fresh, stateful ``obs -> model input`` for one policy (a learner with
    #: memory sees its episode's history), or ``None``: the observation itself.
    view: Callable[[Any], Callable[[np.ndarray], np.ndarray] | None] | None = None
    #: ``policy(model, description)``: the policy :func:`load` returns instead of a
    #: :class:`Policy`, for a model that is not a batch -> logits function (a recurrent learner
    #: keeps one state per environment).
    policy: Callable[[Any, dict[str, Any]], Any] | None = None


_REGISTRY: dict[str, Algorithm] = {}


def register(
    name: str,
    *,
    module: str,
    config_from_json: Callable[[dict], Any],
    init: Callable[[Any, int], Any],
    check: Callable[[Any], str | None] | None = None,
    view: Callable[[Any], Callable[[np.ndarray], np.ndarray] | None] | None = None,
    policy: Callable[[Any, dict[str, Any]], Any] | None = None,
) -> Algorithm:
    """Adds an algorithm (called by its module when imported, ``module=__name__``)."""
    entry = Algorithm(name, module, config_from_json, init, check, view, policy)
    _REGISTRY[name] = entry
    return entry


def lookup(name: Any, path: Path | None = None, module: str | None = None) -> Algorithm:
    """The registered algorithm ``name``; if it is not registered yet, ``module`` (a checkpoint's
    ``"module"``) and then its :data:`LEGACY_MODULES` entry are imported for it to register. A
    :class:`CheckpointError` (naming ``path``) if none defines it."""
    where = f"{path}: " if path is not None else ""
    legacy = LEGACY_MODULES.get(name) if isinstance(name, str) else None
    for candidate in (module, legacy):
        if name in _REGISTRY or candidate is None:
            continue
        if not isinstance(candidate, str) or candidate.partition(".")[0] != PACKAGE:
            raise CheckpointError(
                f"{where}field 'module' is {candidate!r}, not a module of {PACKAGE}: import it "
                "yourself before loading the checkpoint"
            )
        try:
            importlib.import_module(candidate)
        except ImportError as e:
            raise CheckpointError(f"{where}field 'module' {candidate!r}: {e}") from e
    if name not in _REGISTRY:
        known = ", ".join(sorted(set(_REGISTRY) | set(LEGACY_MODULES)))
        raise CheckpointError(f"{where}field 'algorithm' is {name!r}; known: {known}")
    return _REGISTRY[name]


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
        # A learner with memory (a DAgger one) sees its observations' history: such a policy is
        # stateful, one memory per environment of the batches it is given.
        self._view = None
        entry = _REGISTRY.get(self.algorithm)
        if entry is not None and entry.view is not None and description.get("config"):
            self._view = entry.view(entry.config_from_json(description["config"]))

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
        if self._view is not None:
            obs = self._view(obs)
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
    entry = _REGISTRY.get(description.get("algorithm"))
    module = {"module": entry.module} if entry is not None else {}
    description = {"format": FORMAT, "format_version": FORMAT_VERSION, **module, **description}
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
    entry = lookup(found, path, description.get("module"))
    if algorithm is not None and found != algorithm:
        raise CheckpointError(f"{path}: field 'algorithm' is {found!r}, expected {algorithm!r}")
    try:
        config = entry.config_from_json(description["config"])
    except (KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: field 'config' does not fit {found}: {e}") from e
    problem = entry.check(config) if entry.check is not None else None
    if problem is not None:
        raise CheckpointError(f"{path}: field 'config' {problem}")
    skeleton = entry.init(config, 0)
    params = directory / PARAMETERS
    if not params.is_file():
        raise CheckpointError(f"checkpoint {directory} has no {PARAMETERS}")
    try:
        model = eqx.tree_deserialise_leaves(params, skeleton)
    except Exception as e:  # equinox/numpy raise several types for a truncated or foreign file
        raise CheckpointError(f"{params} does not hold {found} parameters: {e!r}") from e
    jax.block_until_ready(jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array)))
    if entry.policy is not None:
        return entry.policy(model, description)
    return Policy(model, description)
