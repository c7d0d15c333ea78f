"""Checkpoints: a directory with the parameters (``model.eqx``) and a JSON description
(``checkpoint.json``: algorithm, the module that defines it, format version, sizes, data used,
training time); the policies :func:`load` returns (:class:`BasePolicy`, the one shape every
agent of the package answers to); and the table of algorithms.

:data:`ALGORITHMS` is the one list of the algorithms a checkpoint may hold: name -> the module
of this package that defines it. That module holds the algorithm's :class:`Hooks` as its
``CHECKPOINT`` attribute (its model's skeleton, its config, what its policy does beyond the
greedy choice); :func:`load` imports only the module a checkpoint's algorithm needs, and this
module imports none of them. Every checkpoint loads through the table: those written with a
``"module"`` field (which :func:`save` still writes, for a reader of the file) and those
written before the field existed (all those under ``docs/results/checkpoints``).

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
    "ALGORITHMS",
    "FORMAT",
    "FORMAT_VERSION",
    "Algorithm",
    "BasePolicy",
    "Hooks",
    "Policy",
    "load",
    "lookup",
    "read_description",
    "save",
    "tell_actions",
]

FORMAT = "dinerdash-agents checkpoint"
FORMAT_VERSION = 1
DESCRIPTION = "checkpoint.json"
PARAMETERS = "model.eqx"

#: The package whose modules :data:`ALGORITHMS` names.
PACKAGE = __name__.rpartition(".")[0]
#: Every algorithm a checkpoint may hold -> the module of :data:`PACKAGE` that defines it (and
#: holds its :class:`Hooks` as ``CHECKPOINT``). The one source of truth: :func:`save` writes the
#: module into ``checkpoint.json``, :func:`load` imports it.
ALGORITHMS = {
    "bc": "bc",
    "dpgm": "dpgm",
    "ppo": "ppo",
    "ppo-masked": "ppo",
    "gail": "gail",
    "ppo-kickstart": "kickstart",
    "dagger": "dagger",
    "dagger-recurrent": "recurrent",
}


@dataclass(frozen=True)
class Hooks:
    """What :func:`load` needs of an algorithm, held by its module as ``CHECKPOINT``: its model's
    skeleton and config, and what a policy of it does beyond the greedy choice."""

    #: The checkpoint's ``"config"`` (JSON) -> the algorithm's config value.
    config_from_json: Callable[[dict], Any]
    #: ``init(config, seed)``: a model of the config's shape (the skeleton parameters load into).
    init: Callable[[Any, int], Any]
    #: ``check(config)``: why a checkpoint of this config cannot be loaded by this version, or
    #: ``None`` (e.g. DPGM's factor layout).
    check: Callable[[Any], str | None] | None = None
    #: ``view(config)``: a fresh, stateful ``obs -> model input`` for one batch of environments
    #: (a learner with memory sees its episode's history), or ``None``: the observation itself.
    #: A view with an ``acted(actions)`` method is told the actions the policy returned.
    view: Callable[[Any], Callable[[np.ndarray], np.ndarray] | None] | None = None
    #: ``policy(model, description)``: the policy :func:`load` returns instead of a
    #: :class:`Policy`, for a model that is not a batch -> logits function (a recurrent learner
    #: carries a state per environment).
    policy: Callable[[Any, dict[str, Any]], Any] | None = None


@dataclass(frozen=True)
class Algorithm:
    """An entry of :data:`ALGORITHMS` with its module's :class:`Hooks`."""

    name: str
    #: The module that defines it: written into ``checkpoint.json`` as ``"module"``.
    module: str
    hooks: Hooks

    def __getattr__(self, attribute: str) -> Any:  # entry.init, entry.config_from_json, ...
        return getattr(self.hooks, attribute)


def module_of(name: str) -> str:
    """The full name of the module that defines algorithm ``name`` (a key of
    :data:`ALGORITHMS`)."""
    return f"{PACKAGE}.{ALGORITHMS[name]}"


def lookup(name: Any, path: Path | None = None) -> Algorithm:
    """Algorithm ``name`` of :data:`ALGORITHMS`, its module imported; a
    :class:`CheckpointError` (naming ``path``) if the table has no such algorithm."""
    where = f"{path}: " if path is not None else ""
    if not isinstance(name, str) or name not in ALGORITHMS:
        known = ", ".join(sorted(ALGORITHMS))
        raise CheckpointError(f"{where}field 'algorithm' is {name!r}; known: {known}")
    module = importlib.import_module(module_of(name))
    return Algorithm(name, module.__name__, module.CHECKPOINT)


class BasePolicy:
    """The one shape of every agent :func:`load` returns (Stable-Baselines3's):
    ``predict(obs, state, episode_start, action_masks=...) -> (actions, state)``.

    ``obs`` is a batch (B, 40) (or one observation), ``state`` what the policy carries from one
    step of that batch to the next (``None`` to start: a feed-forward policy's stays ``None``; a
    recurrent one's holds each environment's hidden state), ``episode_start`` (B,) the
    environments whose episode begins at ``obs`` (their state is reset), ``action_masks``
    (B, 57) ``info["action_mask"]``: the greedy choice runs over the legal actions (``None``:
    over all 57). Every rollout of the package (DAgger's play, evaluation) calls this, whatever
    the policy.

    ``act(obs, action_mask, episode_start=None)`` is the same with the state kept in the policy
    (:meth:`reset` forgets it): what ``evaluate`` and a notebook call.
    """

    name: str
    algorithm: str
    description: dict[str, Any]

    def __init__(self) -> None:
        self.state: Any = None

    def predict(
        self,
        obs: Any,
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = True,
        action_masks: Any = None,
    ) -> tuple[np.ndarray, Any]:
        raise NotImplementedError

    def reset(self) -> None:
        self.state = None

    def act(
        self, obs: Any, action_mask: Any | None = None, episode_start: Any | None = None
    ) -> np.ndarray:
        actions, self.state = self.predict(obs, self.state, episode_start, action_masks=action_mask)
        return actions

    __call__ = act


def batch_of(obs: Any, action_masks: Any) -> tuple[np.ndarray, np.ndarray, bool, bool]:
    """``obs`` as a (B, 40) float32 batch, its masks (B, 57) (all legal without), whether a mask
    was given and whether ``obs`` was a single observation."""
    obs = np.asarray(obs, dtype=np.float32)
    single = obs.ndim == 1
    if single:
        obs = obs[None]
    if obs.ndim != 2 or obs.shape[1] != OBSERVATION_SIZE:
        raise ValueError(f"obs must have shape (B, {OBSERVATION_SIZE}), got {obs.shape}")
    use_mask = action_masks is not None
    if use_mask:
        mask = np.asarray(action_masks, dtype=np.bool_).reshape(obs.shape[0], NUM_ACTIONS)
    else:
        mask = np.ones((obs.shape[0], NUM_ACTIONS), dtype=np.bool_)
    return obs, mask, use_mask, single


class Policy(BasePolicy):
    """A feed-forward agent: greedy over the legal actions of each state of a batch.

    Its state is ``None``, or, for a learner with memory (a DAgger one with ``memory``), the
    view that computes the memory features of the batch's environments from their observations
    (one memory per environment; a batch of another size starts afresh).
    """

    def __init__(self, model: Any, description: dict[str, Any]) -> None:
        super().__init__()
        self.model = model
        self.description = description
        self.algorithm: str = description["algorithm"]
        self.name: str = description.get("name", self.algorithm)
        self._config = None
        self._make_view = None
        entry = lookup(self.algorithm) if self.algorithm in ALGORITHMS else None
        if entry is not None and entry.view is not None and description.get("config"):
            config = entry.config_from_json(description["config"])
            if entry.view(config) is not None:  # a learner with memory
                self._config, self._make_view = config, entry.view

    def predict(
        self,
        obs: Any,
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = True,
        action_masks: Any = None,
    ) -> tuple[np.ndarray, Any]:
        obs, mask, use_mask, single = batch_of(obs, action_masks)
        if self._make_view is not None:
            if state is None:
                state = self._make_view(self._config)
            obs = state(obs)  # the memory restarts where an observation starts an episode
        actions = np.asarray(_greedy(self.model, obs, mask, use_mask), dtype=np.int64)
        tell_actions(state, actions)
        return (actions[0] if single else actions), state


def tell_actions(view: Any, actions: np.ndarray) -> None:
    """Tells ``view`` (a policy's view of its observations, see :attr:`Hooks.view`) the actions
    played from the observations it last saw, if it has an ``acted`` method (a memory that
    follows the group each seat action took)."""
    acted = getattr(view, "acted", None)
    if acted is not None:
        acted(actions)


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
    algorithm = description.get("algorithm")
    module = {"module": module_of(algorithm)} if algorithm in ALGORITHMS else {}
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
    entry = lookup(found, path)
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
