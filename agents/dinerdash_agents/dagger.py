"""DAgger (Ross, Gordon & Bagnell 2011, "A reduction of imitation learning and structured
prediction to no-regret online learning") with the server's teachers, the algorithm: the
learner, its memory, the mixture policy, one round's play and fit. The run (``train dagger
--teacher planner|expert``: the server, rounds, validation, curve, checkpoint) is
:mod:`~dinerdash_agents.train_dagger`.

Round ``i`` (1..R) plays ``E`` training episodes with the mixture policy
``π_i = β_i·teacher + (1 − β_i)·learner``: per step and per environment, with probability
``β_i`` the teacher's action is executed, else the learner's greedy action over the legal ones
(the action the evaluation plays). The sessions run with ``expert="planner"`` (or ``expert=True``,
the reference expert), so ``info["expert_action"]`` labels every visited state with the teacher's
choice, whoever acted. Every visited state (observation, action mask, teacher's action) joins the
aggregate dataset, and the learner is trained on the whole aggregate with the cross-entropy over
the legal actions (:func:`~dinerdash_agents.supervised.cross_entropy`, as BC's masked loss).

- β schedule: ``β_1 = 1`` (round 1 is the teacher's own demonstrations, so its learner is BC on
  them), then ``β_i = p^(i−1)`` (``schedule="exponential"``) or ``β_i = 0`` (``"first"``).
- Training is warm-started: each round continues from the previous round's network for
  ``epochs`` epochs over the whole aggregate (fresh Adam state). States with a single legal
  action ("wait" only) stay in the aggregate but are left out of the fit: their masked loss is
  exactly 0.
- ``seat_weight``: the loss of a state where the teacher seats a group counts this many times
  (1: BC's masked loss). The planner holds small groups until their patience runs low, which the
  observation shows only in levels of 200; unweighted, its pupil almost never seats them in time
  (docs/agents.md, "What limits the planner's pupil").
- Episodes: training seeds only, from ``seed_start`` upwards, skipping the evaluation seeds
  1000..1099 and the validation seeds 2000..2099. After each round the learner plays
  ``validation_episodes`` episodes of seeds 2000.. greedily (no teacher in those sessions); the
  checkpoint keeps the round that scored best there (as Ross et al. pick the best policy of
  the sequence on validation), and ``curve.csv`` lists every round.

The learner is an MLP over the observation scaled by ruleset v0's upper bounds (``layers``
hidden layers of ``hidden`` units, ReLU, dropout after each), 57 action logits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from dinerdash.game import (
    FIRST_SEAT,
    NUM_ACTIONS,
    NUM_TABLES,
    OBSERVATION_HIGH,
    OBSERVATION_SIZE,
    QUEUE_CAPACITY,
)

from . import checkpoint
from .errors import AgentsError
from .seeds import VALIDATION_SEEDS, training_seeds
from .supervised import fit, masked_logits

__all__ = [
    "Aggregate",
    "DaggerConfig",
    "DaggerNet",
    "MemoryFeatures",
    "SeedQueue",
    "betas",
    "config_from_json",
    "fit_round",
    "init",
    "lives_one_hot",
    "mix_actions",
    "play_round",
    "seat_weights",
    "training_seeds",
    "weighted_cross_entropy",
]

#: The teachers: the ``expert=`` keyword of the sessions for each.
TEACHERS = {"planner": "planner", "expert": True}
#: The first validation seed (the learner after each round plays seeds 2000..).
VALIDATION_SEED = VALIDATION_SEEDS.start


@dataclass(frozen=True)
class DaggerConfig:
    """DAgger's settings; :data:`dinerdash_agents.paper.DAGGER_SETTINGS` holds what differs from
    these defaults in the committed results."""

    teacher: str = "planner"
    rounds: int = 8
    episodes_per_round: int = 64
    schedule: str = "exponential"  # "exponential": β_i = p^(i-1); "first": β_1 = 1, then 0
    p: float = 0.5
    num_envs: int = 32
    max_episode_steps: int = 5000
    hidden: int = 512
    layers: int = 2
    dropout: float = 0.1
    epochs: int = 4
    batch_size: int = 512
    learning_rate: float = 1e-3
    #: Weight of the states where the teacher seats a group, against 1 for the others.
    seat_weight: float = 1.0
    seed_start: int = 0
    validation_episodes: int = 50
    #: The learner also sees :class:`MemoryFeatures` of the episode's observations so far.
    memory: bool = False
    #: With ``memory``, the features also hold the tables' timers (``MemoryFeatures(timers=True)``).
    timers: bool = False
    #: With ``memory``, the features end with the groups lost so far, counted from the
    #: observations (``MemoryFeatures(lives=True)``).
    lives: bool = False
    #: With ``memory``, the features end with each group's exact patience and grace buffer,
    #: the memory told the actions played (``MemoryFeatures(patience=True)``).
    patience: bool = False
    #: What the learner's own memory is told while it plays a round: the actions "played", or
    #: its "own" choices. With ``patience``, "own" leaves its patience beliefs wrong wherever the
    #: teacher acted instead, until that group leaves: the learner errs more in its rounds and
    #: the teacher labels the states it errs into (docs/agents.md; a perturbation in DART's spirit).
    learner_memory: str = "played"
    #: Per step where the learner acts, the chance its action is replaced by a legal one drawn
    #: uniformly: DART's injected noise, so the teacher labels states the learner errs into.
    learner_noise: float = 0.0

    def __post_init__(self) -> None:
        if self.teacher not in TEACHERS:
            raise AgentsError(
                f"--teacher must be one of {', '.join(TEACHERS)}, got {self.teacher!r}"
            )
        if self.schedule not in ("exponential", "first"):
            raise AgentsError(f"schedule must be exponential or first, got {self.schedule!r}")
        for name in ("rounds", "episodes_per_round", "num_envs", "layers", "hidden", "epochs"):
            if getattr(self, name) < 1:
                raise AgentsError(f"{name} must be at least 1 (got {getattr(self, name)})")
        if not 0.0 <= self.p <= 1.0:
            raise AgentsError(f"p must be in [0, 1] (got {self.p})")
        if not 0.0 <= self.learner_noise <= 1.0:
            raise AgentsError(f"--learner-noise must be in [0, 1] (got {self.learner_noise})")
        if (self.timers or self.lives or self.patience) and not self.memory:
            raise AgentsError("timers, lives and patience are memory features: they need memory")
        if self.learner_memory not in ("played", "own"):
            raise AgentsError(
                f"--learner-memory must be played or own, got {self.learner_memory!r}"
            )
        if self.learner_memory == "own" and not self.patience:
            raise AgentsError("--learner-memory own: only the patience memory is told actions")

    def to_json(self) -> dict:
        return {**asdict(self), "betas": betas(self)}


def config_from_json(values: dict) -> DaggerConfig:
    values = {k: v for k, v in values.items() if k != "betas"}
    return DaggerConfig(**values)


def betas(config: DaggerConfig) -> list[float]:
    """β_1..β_R: 1, then p^(i-1) ("exponential") or 0 ("first")."""
    if config.schedule == "first":
        return [1.0] + [0.0] * (config.rounds - 1)
    return [float(config.p**i) for i in range(config.rounds)]


#: Steps since a patience level changed are counted up to this many (a type-2 group spends
#: about 29 ticks in a level, plus up to 14 while a refilled grace buffer drains).
MEMORY_CAP = 48
#: Patience slots the memory follows: the six tables, then the seven places of the queue.
MEMORY_SLOTS = NUM_TABLES + QUEUE_CAPACITY
#: Per slot: steps since its level changed / MEMORY_CAP; 1 for a type-2 group (its patience
#: started at level 4); 1 once its level has changed since it arrived.
MEMORY_SIZE = 3 * MEMORY_SLOTS
#: The timers count up to this many steps (reading, eating and cooking last 10, and groups
#: arrive every 9 steps while the queue has room).
TIMER_CAP = 16
#: Per table, the steps since its status changed and since its order reached the kitchen (0:
#: no order there); then the steps since the last group arrived. Each / :data:`TIMER_CAP`.
TIMERS_SIZE = 2 * NUM_TABLES + 1
#: The groups lost so far, one-hot over 0, 1, 2, 3 and 4 or more (the fifth ends the episode).
LIVES_SIZE = 5
#: Per slot (as the memory's): the group's patience P / 800 and grace buffer B / 400 (0 for an
#: empty slot).
PATIENCE_SIZE = 2 * MEMORY_SLOTS
#: Table statuses with a group seated, which a group that runs away leaves as status 0.
_SEATED = (1, 2, 3, 4, 6)


def lives_one_hot(lost: int | np.ndarray) -> np.ndarray:
    """The groups lost (a count, or an array of counts) one-hot over :data:`LIVES_SIZE`
    columns: 0, 1, 2, 3 and 4 or more."""
    return np.eye(LIVES_SIZE, dtype=np.float32)[np.minimum(lost, LIVES_SIZE - 1)]


class _Group:
    """A group the memory follows: what the observations showed of it, and its patience ``p``
    and grace buffer ``b`` as the rules count them (docs/rules.md §1, §5.1)."""

    __slots__ = ("b", "changed", "count", "level", "p", "rate", "size", "type2")

    def __init__(self, level: int, size: int) -> None:
        self.level, self.size = level, size
        self.count, self.type2, self.changed = 0, level >= 4, False
        # Type 1 arrives with P = 600 (level 3), type 2 with P = 800 (level 4), both with B = 100.
        # A group first met at a table (a memory started mid-episode) gets its level's middle.
        self.p = (800 if self.type2 else 600) if size else 200 * level + 100
        self.b = 100 if size else 0
        self.rate = 7 if self.type2 else 12

    def see(self, level: int, bonus: int = 0) -> None:
        """One tick, after which the group shows ``level``; ``bonus``: what the action before it
        added to the group's B (seated, order taken, food served: 100 each)."""
        b = self.b + bonus - self.rate
        if b < 0:  # the overshoot is forgotten (docs/rules.md §5.1)
            self.p, b = self.p - self.rate, 0
        self.b = b
        if level != self.level:
            self.level, self.count, self.changed = level, 0, True
        else:
            self.count = min(self.count + 1, MEMORY_CAP)


def _queue(obs: Sequence[int]) -> list[tuple[int, int]]:
    return [
        (int(obs[24 + 2 * g]), int(obs[25 + 2 * g]))
        for g in range(QUEUE_CAPACITY)
        if obs[25 + 2 * g] > 0
    ]


def is_episode_start(obs: np.ndarray) -> bool:
    """Whether ``obs`` looks like the first observation of an episode (docs/rules.md §3): every
    table free and clean, no food on the counters, empty hands, and one group waiting at its
    starting patience level (3 or 4)."""
    return bool(_look_like_starts(np.asarray(obs)[None])[0])


def _look_like_starts(obs: np.ndarray) -> np.ndarray:
    """:func:`is_episode_start` of each row of a batch (B, 40)."""
    tables_free = (obs[:, 0 : 3 * NUM_TABLES : 3] == 0).all(axis=1)
    empty = (obs[:, 18:24] == 0).all(axis=1) & (obs[:, 38:40] == 0).all(axis=1)
    sizes, levels = obs[:, 25:39:2], obs[:, 24:38:2]
    waiting = sizes > 0
    one = waiting.sum(axis=1) == 1
    first_level = np.where(waiting, levels, -1).max(axis=1)
    return tables_free & empty & one & (first_level >= 3)


class _Timers:
    """One environment's timers (see :class:`MemoryFeatures`): an order reached the kitchen when
    it left the hands while its table still waits for food, and left it when the food is on a
    counter or the table no longer waits."""

    def __init__(self, obs: list[int]) -> None:
        self.since_status = [0] * NUM_TABLES
        self.kitchen = [-1] * NUM_TABLES  # steps since it got the table's order, or -1
        self.orders = _orders_in_hand(obs)
        self.since_arrival = 0

    def step(self, obs: list[int], was: list[int], arrived: bool) -> None:
        """``was``: the tables' statuses before the step."""
        orders = _orders_in_hand(obs)
        for t in range(NUM_TABLES):
            status = obs[3 * t]
            if status == was[t]:
                self.since_status[t] = min(self.since_status[t] + 1, TIMER_CAP)
            else:
                self.since_status[t] = 0
            if status != 3 or obs[18 + t]:
                self.kitchen[t] = -1
            elif self.kitchen[t] >= 0:
                self.kitchen[t] = min(self.kitchen[t] + 1, TIMER_CAP)
            elif t in self.orders and t not in orders:
                self.kitchen[t] = 0
        self.orders = orders
        self.since_arrival = 0 if arrived else min(self.since_arrival + 1, TIMER_CAP)

    def features(self) -> list[float]:
        kitchen = [min(k + 1, TIMER_CAP) if k >= 0 else 0 for k in self.kitchen]
        return [x / TIMER_CAP for x in (*self.since_status, *kitchen, self.since_arrival)]


class _Lives:
    """One environment's count of the groups lost (see :class:`MemoryFeatures`), from what each
    step changed: a table whose group was seated and is now free lost it; the queue lost what
    is missing once the group seated from it and the arrival are counted. Arrivals follow the
    rules' clock (docs/rules.md §5.5: the first at once, then one a step after 8 more ticks while
    there is room). A full queue that stays full either lost none or lost one and took in the
    next: it lost none if every group is still in its place (same size, level the same or one
    lower) or none had level 0, from which alone a group walks out."""

    def __init__(self, queue: list[tuple[int, int]]) -> None:
        self.last_queue = queue
        self.now, self.next_arrival, self.lost = 0, 8, 0

    def step(self, obs: list[int], was: list[int], after: list[tuple[int, int]]) -> None:
        """``was``: the tables' statuses before the step; ``after``: ``_queue(obs)``."""
        pairs = list(zip(was, obs[0 : 3 * NUM_TABLES : 3], strict=True))
        self.lost += sum(1 for w, s in pairs if s == 0 and w in _SEATED)
        before = self.last_queue
        room = len(before) - sum(1 for w, s in pairs if w == 0 and s == 1)
        due = self.now > self.next_arrival
        if due and room < QUEUE_CAPACITY:
            walked, arrived = room + 1 - len(after), True
        elif due and len(after) < QUEUE_CAPACITY:  # full: whoever walked out made room
            walked, arrived = QUEUE_CAPACITY + 1 - len(after), True
        elif due:
            walked = int(not _in_place(before, after))
            arrived = walked > 0
        else:
            walked, arrived = room - len(after), False
        self.lost += walked
        if arrived:
            self.next_arrival = self.now + 8
        self.now += 1
        self.last_queue = after


def _in_place(before: list[tuple[int, int]], after: list[tuple[int, int]]) -> bool:
    """Whether the queue ``after`` a tick holds the groups ``before`` it, each where it was."""
    if all(level > 0 for level, _ in before):
        return True
    return all(
        size == old_size and level in (old_level, old_level - 1)
        for (old_level, old_size), (level, size) in zip(before, after, strict=True)
    )


def _orders_in_hand(obs: Sequence[int]) -> set[int]:
    """The tables (0..5) whose order is in a hand."""
    return {int(h) - 1 for h in obs[38:40] if 1 <= h <= NUM_TABLES}


class _Memory:
    """One environment's patience memory (see :class:`MemoryFeatures`)."""

    def __init__(self, obs: list[int], timers: bool = False, lives: bool = False) -> None:
        self.tables: list[_Group | None] = [None] * NUM_TABLES
        places = _queue(obs)
        self.queue = [_Group(level, size) for level, size in places]
        self.timers = _Timers(obs) if timers else None
        self.lives = _Lives(places) if lives else None
        self.status = obs[0 : 3 * NUM_TABLES : 3]

    def step(self, obs: list[int], action: int | None = None) -> None:
        """``action``: the action played from the last observation, if known."""
        arrived = False
        # The group a seat action took leaves its place in the queue for its table.
        old, seated = self.queue, None
        if action is not None and action >= FIRST_SEAT:
            place, table = divmod(action - FIRST_SEAT, NUM_TABLES)
            if place < len(old):
                old = old[:place] + old[place + 1 :]
                seated = (table, self.queue[place])
        if action is not None:  # P is then exact: who runs out of it this tick walks out
            old = [g for g in old if g.b >= g.rate or g.p > g.rate]
        # The queue: new places matched in order to the old groups whose size is the same and
        # whose level is the same or one lower; unmatched old groups left (seated or walked
        # out), unmatched new ones at the back arrived.
        left, queue, i, places = [], [], 0, _queue(obs)
        for level, size in places:
            while i < len(old) and not (
                old[i].size == size and level in (old[i].level, old[i].level - 1)
            ):
                left.append(old[i])
                i += 1
            if i < len(old):
                old[i].see(level)
                queue.append(old[i])
                i += 1
            else:
                queue.append(_Group(level, size))
                arrived = True
        left.extend(old[i:])
        self.queue = queue
        # The tables: a group newly at a table is the one the seat action took, or else the
        # first group that left the queue and fits. A group's B grew by 100 when it was seated,
        # when its order was taken (status 2 -> 3) and when its food came (3 -> 4).
        was = self.status
        self.status = obs[0 : 3 * NUM_TABLES : 3]
        for t in range(NUM_TABLES):
            level, seats = obs[3 * t + 2], obs[3 * t + 1]
            group = self.tables[t]
            if level < 0:
                self.tables[t] = None
            elif group is not None:
                served = (was[t], self.status[t]) in ((2, 3), (3, 4))
                group.see(level, 100 if served else 0)
            elif seated is not None and seated[0] == t:
                seated[1].see(level, 100)
                self.tables[t] = seated[1]
            else:
                for k, g in enumerate(left):
                    if g.size <= seats and level in (g.level, g.level - 1):
                        g.see(level, 100)
                        self.tables[t] = left.pop(k)
                        break
                else:
                    self.tables[t] = _Group(level, 0)
        if self.timers is not None:
            self.timers.step(obs, was, arrived)
        if self.lives is not None:
            self.lives.step(obs, was, places)

    def features(self) -> list[float]:
        """The memory (and the timers'), the groups lost apart: :class:`MemoryFeatures` one-hots
        them for the whole batch at once."""
        out: list[float] = []
        for g in self.tables + self.queue:
            out += (0.0, 0.0, 0.0) if g is None else (g.count / MEMORY_CAP, g.type2, g.changed)
        out += [0.0] * (3 * MEMORY_SLOTS - len(out))
        if self.timers is not None:
            out += self.timers.features()
        return out

    def patience(self) -> list[float]:
        """P / 800 and B / 400 of each slot's group (see :data:`PATIENCE_SIZE`)."""
        out: list[float] = []
        for g in self.tables + self.queue:
            out += (0.0, 0.0) if g is None else (g.p / 800, g.b / 400)
        return out + [0.0] * (PATIENCE_SIZE - len(out))


class MemoryFeatures:
    """The learner's memory, computed on the client from each environment's own observations:
    for each table and each place in the queue (v0 shows their group's patience only as
    ``P div 200``), the steps since that group's level last changed (one step is one tick,
    capped at :data:`MEMORY_CAP`), whether its patience started at level 4 (type 2: it loses 7 a
    tick instead of 12) and whether its level has changed yet. Groups are followed as the queue
    moves up and as they are seated. An environment's memory starts afresh on an observation
    that :func:`is_episode_start`, so the features are a function of the observations alone
    (whoever acted) and training, validation and ``evaluate`` compute them alike. (An
    unchanged start, the first group still waiting alone, goes on counting.)

    With ``timers`` (issue 49's experiment, docs/agents.md), also :data:`TIMERS_SIZE` timers
    after those: per table the steps since its status changed and since its order reached the
    kitchen, and the steps since the last group arrived. With ``lives``, last, the groups lost
    so far (:data:`LIVES_SIZE`, one-hot), as the observations show them (``info["lost"]`` is not
    read: the features stay a function of the observations).

    With ``patience``, last, each slot's group's patience P and grace buffer B as the rules count
    them (:data:`PATIENCE_SIZE`), the memory told the actions played (:meth:`acted`): a group a
    seat action took is followed from its place in the queue to its table, and a group whose P
    runs out walks out. From the observations alone, of two groups of the same size and level
    side by side, the one seated (or walked out) cannot be told; with the actions, P and B are
    exact (docs/agents.md). These features are a function of the observations and of the
    actions played.

    ``augment(obs)`` (or calling it) takes a batch (B, 40), one step of B environments, and
    returns (B, 40 + :func:`memory_size`); a batch of another size starts every memory afresh."""

    def __init__(self, timers: bool = False, lives: bool = False, patience: bool = False) -> None:
        self.timers, self.lives, self.patience = timers, lives, patience
        self._memories: list[_Memory] = []
        self._last = np.zeros((0, OBSERVATION_SIZE), np.float32)
        self._actions: list[int] | None = None

    def acted(self, actions: np.ndarray) -> None:
        """The actions played from the observations last augmented, one per environment (kept
        with ``patience`` only)."""
        if self.patience:
            self._actions = np.asarray(actions, np.int64).tolist()

    def augment(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.ndim != 2 or obs.shape[1] != OBSERVATION_SIZE:
            raise ValueError(f"obs must have shape (B, {OBSERVATION_SIZE}), got {obs.shape}")
        # Each environment's memory works on its observation as a list of ints: numpy's
        # element access costs more than the arithmetic on 40 numbers.
        rows = obs.astype(np.int64).tolist()
        actions = self._actions
        if actions is None or len(actions) != len(rows):
            actions = [None] * len(rows)
        self._actions = None
        if len(self._memories) != len(obs):
            self._memories = [_Memory(o, self.timers, self.lives) for o in rows]
        else:
            starts = episode_starts(obs, self._last)
            for k, o in enumerate(rows):
                if starts[k]:
                    self._memories[k] = _Memory(o, self.timers, self.lives)
                else:
                    self._memories[k].step(o, actions[k])
        self._last = obs.copy()
        parts = [obs, np.array([m.features() for m in self._memories], np.float32)]
        if self.lives:
            parts.append(lives_one_hot(np.array([m.lives.lost for m in self._memories])))
        if self.patience:
            parts.append(np.array([m.patience() for m in self._memories], np.float32))
        return np.concatenate(parts, axis=1)

    __call__ = augment


def memory_size(
    memory: bool, timers: bool = False, lives: bool = False, patience: bool = False
) -> int:
    """How many memory features follow the observation (:func:`input_blocks` after it)."""
    if not memory:
        return 0
    config = DaggerConfig(memory=True, timers=timers, lives=lives, patience=patience)
    return input_size(config) - OBSERVATION_SIZE


def memory_view(
    memory: bool, timers: bool = False, lives: bool = False, patience: bool = False
) -> MemoryFeatures | None:
    """A policy's view of its observations: with ``memory``, a fresh :class:`MemoryFeatures`
    (called on each step's observations, and told the actions played with :meth:`acted`)."""
    return MemoryFeatures(timers, lives, patience) if memory else None


def input_blocks(config: DaggerConfig) -> list[tuple[str, int]]:
    """The learner's input columns in order, as (name, width) blocks: the observation, then
    the memory features :class:`MemoryFeatures` appends with ``config``'s switches."""
    blocks = [("observation", OBSERVATION_SIZE)]
    if config.memory:
        blocks.append(("memory", MEMORY_SIZE))
        switches = (("timers", TIMERS_SIZE), ("lives", LIVES_SIZE), ("patience", PATIENCE_SIZE))
        blocks += [(name, width) for name, width in switches if getattr(config, name)]
    return blocks


def input_size(config: DaggerConfig) -> int:
    """The learner's input width: the observation, and the memory features with ``memory``."""
    return sum(width for _, width in input_blocks(config))


class DaggerNet(eqx.Module):
    """observation (40) / v0's upper bounds [+ memory features] -> [FC hidden -> ReLU -> dropout]
    × layers -> FC 57."""

    layers: list[eqx.nn.Linear]
    dropout: eqx.nn.Dropout
    out: eqx.nn.Linear

    def __init__(self, config: DaggerConfig, key: jax.Array) -> None:
        keys = jax.random.split(key, config.layers + 1)
        sizes = [input_size(config)] + [config.hidden] * config.layers
        self.layers = [
            eqx.nn.Linear(a, b, key=k)
            for a, b, k in zip(sizes[:-1], sizes[1:], keys[:-1], strict=True)
        ]
        self.dropout = eqx.nn.Dropout(config.dropout)
        self.out = eqx.nn.Linear(config.hidden, NUM_ACTIONS, key=keys[-1])

    def __call__(
        self, obs: jax.Array, mask: jax.Array | None = None, key: jax.Array | None = None
    ) -> jax.Array:
        """Action logits of a batch (B, 40); dropout only when ``key`` is given. The mask only
        restricts the softmax (the caller's), it is not an input."""
        del mask
        h = jnp.concatenate(
            [obs[:, :OBSERVATION_SIZE] / OBSERVATION_HIGH, obs[:, OBSERVATION_SIZE:]], axis=1
        )
        keys = (
            [None] * len(self.layers)
            if key is None
            else list(jax.random.split(key, len(self.layers)))
        )
        for layer, k in zip(self.layers, keys, strict=True):
            h = jax.nn.relu(jax.vmap(layer)(h))
            h = self.dropout(h, key=k, inference=k is None)
        return jax.vmap(self.out)(h)


def init(config: DaggerConfig, seed: int = 0) -> DaggerNet:
    return DaggerNet(config, jax.random.PRNGKey(seed))


@eqx.filter_jit
def _greedy(model: DaggerNet, obs: jax.Array, mask: jax.Array) -> jax.Array:
    return jnp.argmax(masked_logits(model(obs, mask), mask), axis=-1)


def greedy_actions(model: DaggerNet, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The learner's greedy action over the legal ones of each state of a batch."""
    return np.asarray(_greedy(model, jnp.asarray(obs, jnp.float32), jnp.asarray(mask, bool)))


def mix_actions(
    teacher: np.ndarray, learner: np.ndarray, beta: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The mixture policy's actions: per environment the teacher's with probability ``beta``,
    else the learner's; returns them and the mask of environments where the teacher acted."""
    from_teacher = rng.random(len(teacher)) < beta
    return np.where(from_teacher, teacher, learner).astype(np.int64), from_teacher


def add_noise(
    actions: np.ndarray, learner_acted: np.ndarray, mask: np.ndarray, noise: float, rng
) -> np.ndarray:
    """``actions`` with each of the learner's replaced, with probability ``noise``, by a legal
    action drawn uniformly (:attr:`DaggerConfig.learner_noise`)."""
    noised = learner_acted & (rng.random(len(actions)) < noise)
    drawn = np.argmax(np.where(mask, rng.random(mask.shape), -1.0), axis=1)
    return np.where(noised, drawn, actions).astype(np.int64)


class Aggregate:
    """DAgger's dataset: every visited state (observation, action mask) with the teacher's action
    in it, and the round it was visited in."""

    def __init__(self, width: int = OBSERVATION_SIZE) -> None:
        self.width = width
        self._obs: list[np.ndarray] = []
        self._masks: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []
        self._rounds: list[np.ndarray] = []
        #: The episodes added by :meth:`extend`, whole (a sequence learner trains on them).
        self.episodes: list[Episode] = []
        self.steps = 0

    def add(self, obs: np.ndarray, masks: np.ndarray, labels: np.ndarray, round_: int) -> None:
        """Adds a batch of visited states labelled with the teacher's actions ``labels``."""
        obs = np.asarray(obs, np.float32).reshape(-1, self.width)
        masks = np.asarray(masks, np.bool_).reshape(-1, NUM_ACTIONS)
        labels = np.asarray(labels, np.int32).reshape(-1)
        if not len(obs) == len(masks) == len(labels):
            raise ValueError(f"{len(obs)} observations, {len(masks)} masks, {len(labels)} labels")
        if len(labels) and not masks[np.arange(len(labels)), labels].all():
            raise AgentsError("a teacher's action is illegal in its own state")
        self._obs.append(obs.copy())
        self._masks.append(masks.copy())
        self._labels.append(labels.copy())
        self._rounds.append(np.full(len(labels), round_, np.int32))
        self.steps += len(labels)

    def extend(self, episodes: list[Episode], round_: int) -> None:
        """Adds the recorded episodes of round ``round_`` (:attr:`RoundPlay.episodes`)."""
        self.episodes.extend(episodes)
        for e in episodes:
            self.add(e.obs, e.mask, e.action, round_)

    def arrays(self) -> dict[str, np.ndarray]:
        """The whole aggregate: ``obs`` (T, 40), ``mask`` (T, 57), ``action`` (T,), ``round``."""
        if not self._obs:
            return {
                "obs": np.zeros((0, self.width), np.float32),
                "mask": np.zeros((0, NUM_ACTIONS), np.bool_),
                "action": np.zeros(0, np.int32),
                "round": np.zeros(0, np.int32),
            }
        return {
            "obs": np.concatenate(self._obs),
            "mask": np.concatenate(self._masks),
            "action": np.concatenate(self._labels),
            "round": np.concatenate(self._rounds),
        }


def episode_starts(obs: np.ndarray, last: np.ndarray | None) -> np.ndarray:
    """Which rows of a batch ``obs`` (B, 40) start an episode, given each environment's previous
    observation ``last`` (None: all do): the observation looks like an episode's first
    (:func:`is_episode_start`, vectorised) and differs from ``last``."""
    obs = np.asarray(obs)[:, :OBSERVATION_SIZE]
    if last is None:
        return np.ones(len(obs), np.bool_)
    last = np.asarray(last)[:, :OBSERVATION_SIZE]
    return _look_like_starts(obs) & (obs != last).any(axis=1)


def sequence_starts(obs: np.ndarray) -> np.ndarray:
    """The start flags of one recorded episode's observations (T, 40): its first step, and any
    later step that :func:`episode_starts` would mark in play."""
    first = np.zeros(len(obs), np.bool_)
    if len(obs):
        first[0] = True
        first[1:] = episode_starts(obs[1:], obs[:-1])
    return first


@dataclass
class Episode:
    """One recorded episode: observations (T, 40, or wider with memory features), masks
    (T, 57), the teacher's actions (T,), start flags (T,) as :func:`sequence_starts`."""

    obs: np.ndarray
    mask: np.ndarray
    action: np.ndarray
    first: np.ndarray

    def __len__(self) -> int:
        return len(self.action)


@dataclass
class RoundPlay:
    """What one round's episodes gave: the recorded episodes (in the order of the seeds), their
    final scores and lengths, the states recorded, how many of them the teacher acted in; of the
    recorded states with a choice (more than one legal action) in which the learner was asked,
    how many there were and in how many its action was the teacher's (none when β is 1)."""

    episodes: list[Episode]
    scores: np.ndarray
    lengths: np.ndarray
    states: int
    teacher_steps: int
    choices: int = 0
    agreed: int = 0

    @property
    def agreement(self) -> float:
        """The learner's agreement with the teacher on its round's states with a choice (NaN
        when it was not asked)."""
        return self.agreed / self.choices if self.choices else float("nan")


class SeedQueue:
    """One episode per seed of ``seeds`` over the ``n`` environments of a vector env: which
    episode each environment plays (``slot``, -1: none, it plays on unrecorded), which are still
    recorded (``active``) and each episode's final score (``scores``, in the order of
    ``seeds``). Environments beyond the seeds (fewer episodes than environments) start on the
    first seed and are never recorded."""

    def __init__(self, seeds: list[int], n: int) -> None:
        first, self.queue = list(seeds[:n]), list(seeds[n:])
        self.slot = list(range(len(first))) + [-1] * (n - len(first))
        #: The seeds of the first reset, one per environment.
        self.padded = first + [first[0]] * (n - len(first))
        self.scores = np.zeros(len(seeds), np.int64)
        self.next_episode = len(first)
        self.active = np.array([s >= 0 for s in self.slot])

    def end(self, ended: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """Records the final ``score`` of the episodes of the environments ``ended`` and starts
        the next seed on each of them, or retires it when none is left: returns the reset mask
        and the seeds to reset with (``options={"reset_mask": ...}``)."""
        reset = np.zeros(len(self.slot), np.bool_)
        new_seeds = list(self.padded)
        for i in np.flatnonzero(ended):
            self.scores[self.slot[i]] = score[i]
            if self.queue:
                new_seeds[i] = self.queue.pop(0)
                self.slot[i] = self.next_episode
                self.next_episode += 1
                reset[i] = True
            else:
                self.slot[i] = -1
                self.active[i] = False
        return reset, new_seeds


def play_round(
    envs: Any,
    learner: checkpoint.BasePolicy | None,
    beta: float,
    seeds: list[int],
    rng: np.random.Generator,
    memory: MemoryFeatures | None = None,
    learner_memory: str = "played",
    learner_noise: float = 0.0,
) -> RoundPlay:
    """Plays one episode per seed of ``seeds`` with the mixture ``β·teacher + (1 − β)·learner``
    on ``envs`` (a vector env whose infos carry ``expert_action`` and ``action_mask``; an
    environment that ends is reset with the next seed through ``options={"reset_mask": ...}``)
    and records every state visited in those episodes, labelled with ``info["expert_action"]``.

    The one play loop of DAgger, whatever the learner: ``learner`` answers the package's
    policy shape, ``predict(obs, state, episode_start, action_masks=...)``
    (:class:`~dinerdash_agents.checkpoint.BasePolicy`), a feed-forward learner's state staying
    ``None`` and a recurrent one's stepping on every observation of every environment, whoever
    acts; it is not called at all when ``beta`` is 1 (``None`` is then allowed). Per step and
    environment, with probability ``beta`` the teacher's action is executed, else the learner's
    (:func:`mix_actions`, one draw per environment and step). Environments left without a seed
    at the end play on unrecorded. With ``memory``, the recorded observations are extended by
    its :class:`MemoryFeatures` (as a learner with memory computes its own). The recorded memory
    is told the actions played; the learner's own too, unless ``learner_memory`` is "own"
    (:attr:`DaggerConfig.learner_memory`: it keeps what its ``predict`` told it, its choices).
    With ``learner_noise``, the learner's actions are perturbed first (:func:`add_noise`)."""
    n = envs.num_envs
    episodes = SeedQueue(seeds, n)
    slot, active = episodes.slot, episodes.active
    obs, info = envs.reset(seed=episodes.padded)
    record: list[dict[str, list]] = [{"obs": [], "mask": [], "action": []} for _ in seeds]
    lengths = np.zeros(len(seeds), np.int64)
    states = teacher_steps = choices = agreed = 0
    state, restart = None, np.ones(n, np.bool_)
    while active.any():
        teacher = np.asarray(info["expert_action"], np.int64)
        mask = np.asarray(info["action_mask"], np.bool_)
        seen = obs if memory is None else memory.augment(obs)
        for i in np.flatnonzero(active):
            r = record[slot[i]]
            r["obs"].append(np.asarray(seen[i], np.float32))
            r["mask"].append(mask[i])
            r["action"].append(teacher[i])
            lengths[slot[i]] += 1
        states += int(active.sum())
        if beta >= 1.0 or learner is None:
            learned = teacher
        else:
            learned, state = learner.predict(obs, state, restart, action_masks=mask)
            asked = active & (mask.sum(axis=1) > 1)
            choices += int(asked.sum())
            agreed += int((asked & (np.asarray(learned) == teacher)).sum())
        actions, from_teacher = mix_actions(teacher, np.asarray(learned, np.int64), beta, rng)
        if learner_noise > 0.0:
            actions = add_noise(actions, ~from_teacher, mask, learner_noise, rng)
        checkpoint.tell_actions(memory, actions)
        if learner_memory == "played":
            checkpoint.tell_actions(state, actions)
        teacher_steps += int((from_teacher & active).sum())
        restart = np.zeros(n, np.bool_)
        obs, _, terminated, truncated, info = envs.step(actions)
        ended = (np.asarray(terminated) | np.asarray(truncated)) & active
        if not ended.any():
            continue
        reset, new_seeds = episodes.end(ended, info["score"])
        if reset.any():
            obs, info = envs.reset(seed=new_seeds, options={"reset_mask": reset})
            restart = reset
    recorded = []
    for r in record:
        o = np.stack(r["obs"])
        a = np.asarray(r["action"], np.int32)
        recorded.append(Episode(o, np.stack(r["mask"]), a, sequence_starts(o)))
    return RoundPlay(recorded, episodes.scores, lengths, states, teacher_steps, choices, agreed)


def seat_weights(actions: np.ndarray, seat_weight: float) -> np.ndarray:
    """Per-state loss weights: ``seat_weight`` where the teacher seats a group, 1 elsewhere,
    scaled to mean 1 (so weight 1 everywhere is BC's masked loss)."""
    weight = np.where(np.asarray(actions) >= FIRST_SEAT, seat_weight, 1.0).astype(np.float32)
    return weight / weight.mean()


def weighted_cross_entropy(
    logits: jax.Array, actions: jax.Array, mask: jax.Array, weight: jax.Array
) -> jax.Array:
    """The cross-entropy over the legal actions (as
    :func:`~dinerdash_agents.supervised.cross_entropy`), each state's term times ``weight``."""
    logp = jax.nn.log_softmax(masked_logits(logits, mask), axis=-1)
    return -jnp.mean(weight * jnp.take_along_axis(logp, actions[:, None], axis=-1)[:, 0])


def fit_round(model: DaggerNet, aggregate: Aggregate, config: DaggerConfig, seed: int):
    """Continues training ``model`` on the aggregate's states with more than one legal action."""
    data = aggregate.arrays()
    choice = data["mask"].sum(axis=1) > 1
    data = {k: data[k][choice] for k in ("obs", "mask", "action")}
    if len(data["action"]) == 0:
        return model, [float("nan")]
    data["weight"] = seat_weights(data["action"], config.seat_weight)

    def loss_fn(model, batch, key):
        logits = model(batch["obs"], key=key)
        return weighted_cross_entropy(logits, batch["action"], batch["mask"], batch["weight"])

    return fit(
        model,
        loss_fn,
        data,
        epochs=config.epochs,
        batch_size=config.batch_size,
        learning_rate=config.learning_rate,
        seed=seed,
    )


def _view(config: DaggerConfig) -> MemoryFeatures | None:
    return memory_view(config.memory, config.timers, config.lives, config.patience)


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``dagger`` checkpoint.
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init, view=_view)
