"""DAgger with a learner that remembers its episode: ``train dagger-recurrent --kind gru|stack``.

The v0 observation shows a group's patience only as ``P div 200``; the planner times its seat
actions on the exact value, so its choices are not a function of one observation
(docs/agents.md, "What limits the planner's pupil"). These learners see the episode's
observations so far:

- ``kind="gru"``: a GRU over the episode's observations. Each step, the observation (divided by
  v0's upper bounds) enters a GRU cell of ``hidden`` units; the action logits come from an MLP
  over the observation and the cell's state (``concat(obs, h) -> FC hidden -> ReLU -> FC 57``).
  Only the cell runs inside ``jax.lax.scan``; the head runs over all steps at once.
- ``kind="stack"``: the frame-stacked feed-forward baseline: the last ``stack`` observations
  concatenated, oldest first (before the episode's ``stack``-th step the first observation
  repeats, as Gymnasium's ``FrameStackObservation(padding_type="reset")``), into an MLP
  ``40·stack -> hidden -> hidden -> 57`` (ReLU). The stacking is done inside the learner, with
  the same episode bookkeeping as the GRU's state, so the two differ in their model only.

**Episode starts.** The state (the GRU's ``h``, the stack's window) is reset on the first
observation of every episode. A policy sees observations only, not resets, so "first" is a
function of the observations: a batch of a new size starts every environment afresh, and an
observation that :func:`~dinerdash_agents.dagger.is_episode_start` (tables free and clean, no
food, empty hands, one group waiting at its starting level) and differs from the environment's
previous one starts its episode afresh, across autoreset too. Training marks the same steps (the
first of each recorded episode, and any later one the rule matches), so ``evaluate`` replays the
training's computation exactly: a test checks that a :class:`RecurrentPolicy` stepping through a
batch gives the actions of one ``scan`` over the same sequences.

**Sequence DAgger.** Round ``i`` plays ``episodes_per_round`` training episodes with the mixture
``β_i·teacher + (1 − β_i)·learner`` (β_1 = 1, then ``p^(i−1)``), the learner stepping its state
on every observation whoever acts; each recorded episode (observations, masks, the teacher's
``info["expert_action"]``, episode-start flags) joins the aggregate. Training is truncated
back-propagation through time: the aggregate's episodes are laid end to end, cut into ``lanes``
and the lanes into chunks of ``chunk`` steps; one forward pass of the current network over the
lanes gives each chunk's starting state (held fixed, no gradient through it), then Adam runs
``epochs`` epochs over shuffled minibatches of chunks with the cross-entropy over the legal
actions, the teacher's seat actions weighted ``seat_weight`` (as :mod:`dagger`). After each round
the learner plays the validation seeds 2000.. greedily; the checkpoint keeps the best round.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from dinerdash.game import FIRST_SEAT, NUM_ACTIONS, OBSERVATION_HIGH, OBSERVATION_SIZE

from . import checkpoint
from .dagger import MEMORY_SIZE, Episode, MemoryFeatures, episode_starts
from .errors import AgentsError
from .supervised import masked_logits

__all__ = [
    "ALGORITHM",
    "GruNet",
    "RecurrentConfig",
    "RecurrentPolicy",
    "StackNet",
    "chunk_starts",
    "config_from_json",
    "fit_round",
    "init",
    "make_policy",
    "sequence_batches",
]

ALGORITHM = "dagger-recurrent"
KINDS = ("gru", "stack")
TEACHERS = {"planner": "planner", "expert": True}


@dataclass(frozen=True)
class RecurrentConfig:
    """Sequence DAgger's settings; :data:`dinerdash_agents.paper.RECURRENT_SETTINGS` holds
    what differs from these defaults in the committed results."""

    teacher: str = "planner"
    kind: str = "gru"
    #: The GRU's state size, or the stacked MLP's hidden layers' width.
    hidden: int = 128
    #: Observations a stacked learner sees (``kind="stack"``).
    stack: int = 8
    rounds: int = 6
    episodes_per_round: int = 64
    p: float = 0.5
    num_envs: int = 64
    max_episode_steps: int = 5000
    #: Truncated BPTT: steps of a chunk, and chunks of a minibatch.
    chunk: int = 64
    batch_chunks: int = 8
    epochs: int = 6
    learning_rate: float = 2e-3
    seat_weight: float = 4.0
    seed_start: int = 0
    validation_episodes: int = 50
    #: The learner also sees :class:`~dinerdash_agents.dagger.MemoryFeatures` (hand-made
    #: memory computed from the same observations) beside each observation.
    memory: bool = False

    def __post_init__(self) -> None:
        if self.teacher not in TEACHERS:
            raise AgentsError(
                f"--teacher must be one of {', '.join(TEACHERS)}, got {self.teacher!r}"
            )
        if self.kind not in KINDS:
            raise AgentsError(f"--kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        for name in (
            "hidden",
            "stack",
            "rounds",
            "episodes_per_round",
            "num_envs",
            "chunk",
            "batch_chunks",
            "epochs",
            "validation_episodes",
        ):
            if getattr(self, name) < 1:
                raise AgentsError(f"{name} must be at least 1 (got {getattr(self, name)})")
        if not 0.0 <= self.p <= 1.0:
            raise AgentsError(f"p must be in [0, 1] (got {self.p})")

    def to_json(self) -> dict:
        return {**asdict(self), "betas": betas(self)}


def config_from_json(values: dict) -> RecurrentConfig:
    return RecurrentConfig(**{k: v for k, v in values.items() if k != "betas"})


def betas(config: RecurrentConfig) -> list[float]:
    """β_1..β_R: 1, then p^(i-1)."""
    return [float(config.p**i) for i in range(config.rounds)]


def input_size(config: RecurrentConfig) -> int:
    """Features per step: the observation, and the memory features with ``memory``."""
    return OBSERVATION_SIZE + (MEMORY_SIZE if config.memory else 0)


def _scaled(obs: jax.Array) -> jax.Array:
    """The observation divided by v0's upper bounds; memory features (already in [0, 1]) kept."""
    return jnp.concatenate(
        [obs[..., :OBSERVATION_SIZE] / OBSERVATION_HIGH, obs[..., OBSERVATION_SIZE:]], axis=-1
    )


def _linear(layer: eqx.nn.Linear, x: jax.Array) -> jax.Array:
    """``layer`` over the last axis of ``x`` of any leading shape."""
    return x @ layer.weight.T + layer.bias


class GruNet(eqx.Module):
    """obs / v0's bounds -> GRU cell (``hidden``); concat(obs, h) -> FC hidden -> ReLU -> FC 57."""

    cell: eqx.nn.GRUCell
    head: eqx.nn.Linear
    out: eqx.nn.Linear

    def __init__(self, config: RecurrentConfig, key: jax.Array) -> None:
        k1, k2, k3 = jax.random.split(key, 3)
        width = input_size(config)
        self.cell = eqx.nn.GRUCell(width, config.hidden, key=k1)
        self.head = eqx.nn.Linear(width + config.hidden, config.hidden, key=k2)
        self.out = eqx.nn.Linear(config.hidden, NUM_ACTIONS, key=k3)

    def initial_state(self, n: int) -> jax.Array:
        return jnp.zeros((n, self.cell.hidden_size), jnp.float32)

    def unroll(
        self, state: jax.Array, obs: jax.Array, first: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Logits (T, B, 57) of time-major ``obs`` (T, B, 40) with start flags ``first`` (T, B)
        from ``state`` (B, hidden); and the state after the last step."""
        x = _scaled(obs)
        cell = jax.vmap(self.cell)

        def step(h, inputs):
            x_t, first_t = inputs
            h = cell(x_t, jnp.where(first_t[:, None], 0.0, h))
            return h, h

        last, hs = jax.lax.scan(step, state, (x, first))
        z = jax.nn.relu(_linear(self.head, jnp.concatenate([x, hs], axis=-1)))
        return _linear(self.out, z), last


class StackNet(eqx.Module):
    """The last ``stack`` observations / v0's bounds, oldest first -> [FC hidden -> ReLU] × 2 ->
    FC 57; the state is the window of the ``stack - 1`` observations before the current one."""

    layers: list[eqx.nn.Linear]
    out: eqx.nn.Linear
    stack: int = eqx.field(static=True)
    width: int = eqx.field(static=True)

    def __init__(self, config: RecurrentConfig, key: jax.Array) -> None:
        k1, k2, k3 = jax.random.split(key, 3)
        self.stack = config.stack
        self.width = input_size(config)
        self.layers = [
            eqx.nn.Linear(self.width * config.stack, config.hidden, key=k1),
            eqx.nn.Linear(config.hidden, config.hidden, key=k2),
        ]
        self.out = eqx.nn.Linear(config.hidden, NUM_ACTIONS, key=k3)

    def initial_state(self, n: int) -> jax.Array:
        return jnp.zeros((n, self.width * (self.stack - 1)), jnp.float32)

    def unroll(
        self, state: jax.Array, obs: jax.Array, first: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """As :meth:`GruNet.unroll`; the state is the window (B, 40·(stack − 1))."""
        x = _scaled(obs)
        repeats = self.stack - 1

        def step(window, inputs):
            x_t, first_t = inputs
            window = jnp.where(first_t[:, None], jnp.tile(x_t, (1, repeats)), window)
            frame = jnp.concatenate([window, x_t], axis=-1)
            return frame[:, self.width :], frame

        last, frames = jax.lax.scan(step, state, (x, first))
        z = frames
        for layer in self.layers:
            z = jax.nn.relu(_linear(layer, z))
        return _linear(self.out, z), last


def init(config: RecurrentConfig, seed: int = 0) -> GruNet | StackNet:
    key = jax.random.PRNGKey(seed)
    return GruNet(config, key) if config.kind == "gru" else StackNet(config, key)


@eqx.filter_jit
def _act(model, state, obs, mask, first, use_mask):
    logits, state = model.unroll(state, obs[None], first[None])
    actions = jnp.argmax(masked_logits(logits[0], mask if use_mask else None), axis=-1)
    return actions, state


@dataclass
class RecurrentState:
    """What a :class:`RecurrentPolicy` carries from one step of a batch to the next: the model's
    state per environment (the GRU's ``h``, the stack's window), each environment's last
    observation (for :func:`episode_starts`) and, with ``memory``, its memory features."""

    model: jax.Array
    last: np.ndarray
    memory: MemoryFeatures | None


class RecurrentPolicy(checkpoint.BasePolicy):
    """A recurrent (or frame-stacked) learner as a policy over batches (the package's shape,
    :class:`~dinerdash_agents.checkpoint.BasePolicy`): its state is a :class:`RecurrentState`,
    one per environment of the batch, reset where :func:`episode_starts` or ``episode_start``
    marks a row and everywhere when the batch's size changes (a new vector env)."""

    def __init__(self, model: Any, description: dict[str, Any]) -> None:
        super().__init__()
        self.model = model
        self.description = description
        self.algorithm: str = description["algorithm"]
        self.name: str = description.get("name", self.algorithm)
        config = description.get("config") or {}
        self._with_memory = bool(config.get("memory", False))

    def predict(
        self,
        obs: Any,
        state: RecurrentState | None = None,
        episode_start: Any = None,
        deterministic: bool = True,
        action_masks: Any = None,
    ) -> tuple[np.ndarray, RecurrentState]:
        obs, mask, use_mask, single = checkpoint.batch_of(obs, action_masks)
        n = len(obs)
        if state is None or state.model.shape[0] != n:
            memory = MemoryFeatures() if self._with_memory else None
            first = np.ones(n, np.bool_)
            carried = self.model.initial_state(n)
        else:
            memory, carried = state.memory, state.model
            first = episode_starts(obs, state.last)
        if episode_start is not None:
            first |= np.asarray(episode_start, np.bool_).reshape(n)
        last = obs.copy()
        if memory is not None:
            obs = memory.augment(obs)
        actions, carried = _act(self.model, carried, obs, mask, first, use_mask)
        actions = np.asarray(actions, dtype=np.int64)
        return (actions[0] if single else actions), RecurrentState(carried, last, memory)


def make_policy(model: Any, description: dict[str, Any]) -> RecurrentPolicy:
    """The checkpoint loader's hook: the stateful policy of a ``dagger-recurrent`` checkpoint."""
    return RecurrentPolicy(model, description)


def sequence_batches(
    episodes: list[Episode], chunk: int, seat_weight: float, lanes: int = 64
) -> dict[str, np.ndarray]:
    """The aggregate laid out for truncated BPTT: the episodes end to end, padded and cut into
    ``L ≤ lanes`` lanes of ``S`` chunks of ``chunk`` steps; arrays (L, S, chunk, ...): ``obs``,
    ``mask``, ``action``, ``first`` and ``weight`` (0 on padding and on states where only one
    action is legal; ``seat_weight`` where the teacher seats a group; 1 elsewhere). A lane begins
    with a start flag, so its first chunk starts from an empty state."""
    obs = np.concatenate([e.obs for e in episodes]).astype(np.float32)
    mask = np.concatenate([e.mask for e in episodes]).astype(np.bool_)
    action = np.concatenate([e.action for e in episodes]).astype(np.int32)
    first = np.concatenate([e.first for e in episodes]).astype(np.bool_)
    weight = np.where(action >= FIRST_SEAT, seat_weight, 1.0).astype(np.float32)
    weight[mask.sum(axis=1) <= 1] = 0.0
    n = len(action)
    chunks = math.ceil(n / chunk)
    lanes = max(1, min(lanes, chunks))
    per_lane = math.ceil(chunks / lanes)
    total = lanes * per_lane * chunk
    pad = total - n

    def padded(a: np.ndarray, value: Any) -> np.ndarray:
        return np.concatenate([a, np.full((pad, *a.shape[1:]), value, a.dtype)])

    out = {
        "obs": padded(obs, 0.0),
        "mask": padded(mask, True),
        "action": padded(action, 0),
        "first": padded(first, True),
        "weight": padded(weight, 0.0),
    }
    out = {k: v.reshape(lanes, per_lane, chunk, *v.shape[1:]) for k, v in out.items()}
    out["first"][:, 0, 0] = True
    return out


@eqx.filter_jit
def chunk_starts(model: Any, obs: jax.Array, first: jax.Array) -> jax.Array:
    """The state at the start of every chunk of :func:`sequence_batches`' lanes (L, S, C, ...),
    from one forward pass of ``model``: (L, S, state...)."""
    lanes = obs.shape[0]

    def run(state, inputs):
        o, f = inputs  # (L, C, 40), (L, C)
        _, after = model.unroll(state, jnp.swapaxes(o, 0, 1), jnp.swapaxes(f, 0, 1))
        return after, state

    _, starts = jax.lax.scan(
        run, model.initial_state(lanes), (jnp.swapaxes(obs, 0, 1), jnp.swapaxes(first, 0, 1))
    )
    return jnp.swapaxes(starts, 0, 1)


def sequence_loss(model: Any, batch: dict[str, jax.Array]) -> jax.Array:
    """The weighted cross-entropy over the legal actions of a minibatch of chunks (B, C, ...)
    unrolled from their starting states ``start`` (B, state...)."""
    logits, _ = model.unroll(
        batch["start"], jnp.swapaxes(batch["obs"], 0, 1), jnp.swapaxes(batch["first"], 0, 1)
    )
    logits = jnp.swapaxes(logits, 0, 1)
    logp = jax.nn.log_softmax(masked_logits(logits, batch["mask"]), axis=-1)
    chosen = jnp.take_along_axis(logp, batch["action"][..., None], axis=-1)[..., 0]
    weight = batch["weight"]
    return -jnp.sum(weight * chosen) / jnp.maximum(jnp.sum(weight > 0), 1.0)


@functools.lru_cache(maxsize=8)
def _optimizer(learning_rate: float) -> optax.GradientTransformation:
    # One object per rate, so the jitted update (which takes it as a static argument) compiles
    # once per run rather than once per round.
    return optax.adam(learning_rate)


@eqx.filter_jit
def _update(params, static, opt_state, batch, optimizer):
    loss, grads = jax.value_and_grad(lambda p: sequence_loss(eqx.combine(p, static), batch))(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return eqx.apply_updates(params, updates), opt_state, loss


def fit_round(
    model: Any, episodes: list[Episode], config: RecurrentConfig, seed: int
) -> tuple[Any, list[float]]:
    """Continues training ``model`` on the aggregate's episodes: each chunk's starting state from
    the current network (:func:`chunk_starts`, fixed for the round), then ``epochs`` epochs of
    Adam (fresh each round, as :mod:`dagger`) over shuffled minibatches of ``batch_chunks``
    chunks; returns the model and each epoch's mean loss. Every minibatch has the same shape, so
    the update compiles once per run."""
    data = sequence_batches(episodes, config.chunk, config.seat_weight)
    starts = chunk_starts(model, jnp.asarray(data["obs"]), jnp.asarray(data["first"]))
    flat = {k: v.reshape(-1, *v.shape[2:]) for k, v in data.items()}
    flat["start"] = np.asarray(starts).reshape(-1, *starts.shape[2:])
    keep = flat["weight"].sum(axis=1) > 0
    flat = {k: v[keep] for k, v in flat.items()}
    n = len(flat["weight"])
    if n == 0:
        return model, [float("nan")]
    size = min(config.batch_chunks, n)
    optimizer = _optimizer(config.learning_rate)
    params, static = eqx.partition(model, eqx.is_array)
    opt_state = optimizer.init(params)
    rng = np.random.default_rng(seed)
    history = []
    for _ in range(config.epochs):
        order = rng.permutation(n)
        losses = []
        for b in range(n // size):
            idx = order[b * size : (b + 1) * size]
            batch = {k: jnp.asarray(v[idx]) for k, v in flat.items()}
            params, opt_state, loss = _update(params, static, opt_state, batch, optimizer)
            losses.append(loss)
        history.append(float(np.mean(jax.device_get(losses))))
    return eqx.combine(params, static), history


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``dagger-recurrent`` checkpoint.
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init, policy=make_policy)
