"""The Batch: one Reset's or Step's reply for the environments of one session (or a whole env) as
numpy arrays, whatever transport carried it; its operations (slice, join, episodes ended early by
a lost server, :func:`interrupt`, or a refused Restore, :func:`cut`); and the observations and
infos made of it (:func:`decode`, copies). The one module that names the reply's fields.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode

from ._proto import pb
from .game import NUM_ACTIONS, OBSERVATION_SIZE

#: The one table of the Batch's per-environment fields (dtype, width): gRPC reads each by name,
#: shared memory in this order (``tests/test_batch_fields.py`` ties it to the proto and server).
FIELDS: dict[str, tuple[str, int]] = {
    "observations": ("i1", OBSERVATION_SIZE),
    "rewards": ("<i4", 1),
    "terminated": ("?", 1),
    "truncated": ("?", 1),
    "scores": ("<i4", 1),
    "lost": ("<u4", 1),
    "ticks": ("<u4", 1),
    "action_masks": ("?", NUM_ACTIONS),
    "expert_actions": ("u1", 1),
    "reset": ("?", 1),
    "seeds": ("<u8", 1),
    "stream_episodes": ("<u4", 1),
    "final_observations": ("i1", OBSERVATION_SIZE),
    "final_scores": ("<i4", 1),
    "final_lost": ("<u4", 1),
    "final_ticks": ("<u4", 1),
    "final_action_masks": ("?", NUM_ACTIONS),
    "final_expert_actions": ("u1", 1),
}
#: The fields a ``pb.Batch`` holds as repeated integers rather than packed bytes.
REPEATED = ("seeds", "stream_episodes")
#: Up to this many items a repeated field is read into numpy through a list (:meth:`Batch.get`).
_LIST_UP_TO = 32
#: An environment's state (what ``final_*`` repeats for an episode that ended in a step).
STATE = ("observations", "scores", "lost", "ticks", "action_masks", "expert_actions")


class Batch:
    """One reply for ``num_envs`` environments: each field it has as an array of ``num_envs`` rows
    (``batch[name]`` reads a field it lacks as zeros); a gRPC reply's decoded when first read."""

    __slots__ = ("_fields", "_msg", "drain_ms", "num_envs")

    def __init__(
        self,
        num_envs: int,
        fields: dict[str, np.ndarray],
        drain_ms: int = 0,
        msg: pb.Batch | None = None,
    ) -> None:
        self.num_envs = num_envs
        self._fields = fields
        self._msg = msg  # the gRPC reply whose other fields are not decoded yet
        self.drain_ms = drain_ms

    @classmethod
    def from_pb(cls, msg: pb.Batch) -> Batch:
        """The Batch of a gRPC reply."""
        return cls(msg.num_envs or len(msg.rewards) // 4, {}, msg.drain_remaining_ms, msg)

    @property
    def fields(self) -> dict[str, np.ndarray]:
        """Each field the reply has, by name (a field it lacks is absent)."""
        if self._msg is not None:
            for desc, _ in self._msg.ListFields():
                self.get(desc.name)
            self._msg = None
        return self._fields

    def get(self, name: str) -> np.ndarray | None:
        """Field ``name``, ``None`` when the reply lacks it."""
        value = self._fields.get(name)
        if value is not None or self._msg is None or name not in FIELDS:
            return value
        raw = getattr(self._msg, name)
        if not raw:
            return None
        dtype, width = FIELDS[name]
        if name in REPEATED:
            # A list is cheaper for a few items (docs/client.md#design-notes).
            value = np.array(raw[:] if len(raw) <= _LIST_UP_TO else raw, dtype=dtype)
        else:
            value = np.frombuffer(raw, dtype=dtype)
            if width > 1:
                value = value.reshape(-1, width)
        self._fields[name] = value
        return value

    def to_pb(self) -> pb.Batch:
        """The ``pb.Batch`` this Batch is the decoding of (for the wire, and the benchmark)."""
        out = pb.Batch(num_envs=self.num_envs, drain_remaining_ms=self.drain_ms)
        for name, value in self.fields.items():
            if name in REPEATED:
                getattr(out, name).extend(value.tolist())
            else:
                setattr(out, name, np.ascontiguousarray(value).tobytes())
        return out

    def __getitem__(self, name: str) -> np.ndarray:
        value = self._fields.get(name)  # most reads: a field decoded already
        if value is None:
            value = self.get(name)
            if value is None:
                dtype, width = FIELDS[name]
                return np.zeros((self.num_envs, width) if width > 1 else self.num_envs, dtype)
        return value

    def copy(self) -> Batch:
        """A Batch of arrays of its own (valid whatever happens to the region it was read from)."""
        return Batch(self.num_envs, {k: v.copy() for k, v in self.fields.items()}, self.drain_ms)

    def replace(self, **changes: np.ndarray | None) -> Batch:
        """This Batch with some fields replaced (``None``: removed)."""
        fields = {k: v for k, v in {**self.fields, **changes}.items() if v is not None}
        return Batch(self.num_envs, fields, self.drain_ms)

    def slice(self, lo: int, hi: int) -> Batch:
        """Environments ``lo:hi`` (views)."""
        return Batch(hi - lo, {k: v[lo:hi] for k, v in self.fields.items()}, self.drain_ms)


def join(batches: list[Batch]) -> Batch:
    """The Batches of consecutive environments as one, in environment order (one Batch: itself,
    no copy). A field some of them lack is zeros there."""
    if len(batches) == 1:
        return batches[0]
    names = dict.fromkeys(k for b in batches for k in b.fields)
    fields = {k: np.concatenate([b[k] for b in batches]) for k in names}
    return Batch(sum(b.num_envs for b in batches), fields, max(b.drain_ms for b in batches))


def cut(ended: Batch, first: Batch, mode: AutoresetMode) -> tuple[Batch, Batch | None]:
    """The Batch environments report for the step just made (``ended``) when they could not be
    restored where they move (another snapshot version) and start new episodes there, whose Reset
    replied ``first``; and the Batch their next step reports (NEXT_STEP; else ``None``)."""
    n = ended.num_envs
    truncated = ~ended["terminated"]
    if mode != AutoresetMode.SAME_STEP:
        pending = first if mode == AutoresetMode.NEXT_STEP else None
        return ended.copy().replace(truncated=truncated.copy()), pending
    reset = ended["reset"]
    finals = {
        "final_" + k: np.where(
            reset.reshape(-1, *([1] * (ended[k].ndim - 1))), ended["final_" + k], ended[k]
        )
        for k in STATE
    }
    out = first.replace(
        rewards=ended["rewards"].copy(),
        terminated=ended["terminated"].copy(),
        truncated=truncated.copy(),
        reset=np.ones(n, np.bool_),
        stream_episodes=None,
        **finals,
    )
    return out, None


def interrupt(last: Batch, first: Batch, mode: AutoresetMode) -> tuple[Batch, Batch | None]:
    """The Batch of a step that ends, truncated (reward 0), episodes whose ``last`` Batch came from
    a lost session and starts the new session's (its Reset replied ``first``); and the Batch the
    next step hands out (NEXT_STEP: ``first``; else ``None``)."""
    n = last.num_envs
    outcome = {
        "rewards": np.zeros(n, "<i4"),
        "terminated": np.zeros(n, np.bool_),
        "truncated": np.ones(n, np.bool_),
        "stream_episodes": None,
    }
    if mode != AutoresetMode.SAME_STEP:
        out = last.copy().replace(
            reset=np.zeros(n, np.bool_), seeds=np.zeros(n, np.uint64), **outcome
        )
        return out, first if mode == AutoresetMode.NEXT_STEP else None
    finals = {"final_" + k: last.fields[k].copy() for k in STATE if k in last.fields}
    return first.replace(**finals, **outcome), None


def decode(
    batch: Batch, expert: bool, prefix: str = "", present: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Observations ``(N, 40) float32`` and infos of ``batch``'s state (``prefix="final_"``: of the
    episodes that ended), ``present`` each key's ``_key`` mask (default: all; copied)."""
    if present is None:
        present = np.ones(batch.num_envs, dtype=np.bool_)
    obs = batch[prefix + "observations"].astype(np.float32)
    info: dict[str, Any] = {
        "action_mask": batch[prefix + "action_masks"].copy(),
        "score": batch[prefix + "scores"].astype(np.int64),
        "lost": batch[prefix + "lost"].astype(np.int64),
        "tick": batch[prefix + "ticks"].astype(np.int64),
    }
    if expert:
        info["expert_action"] = batch[prefix + "expert_actions"].astype(np.int64)
    for key in list(info):
        info[f"_{key}"] = present.copy()
    return obs, info


def decode_one(batch: Batch, expert: bool) -> tuple[np.ndarray, dict[str, Any]]:
    """The observation ``(40,)`` and info of a one-environment Batch, with plain ``int`` values."""
    msg = batch._msg
    observations = msg.observations if msg is not None else None
    if observations:
        info: dict[str, Any] = {
            "action_mask": np.frombuffer(msg.action_masks, dtype=np.bool_).copy(),
            "score": int.from_bytes(msg.scores, "little", signed=True),
            "lost": int.from_bytes(msg.lost, "little"),
            "tick": int.from_bytes(msg.ticks, "little"),
        }
        if expert:
            info["expert_action"] = msg.expert_actions[0] if msg.expert_actions else 0
        return np.frombuffer(observations, dtype=np.int8).astype(np.float32), info
    info = {
        "action_mask": batch["action_masks"][0].copy(),
        "score": int(batch["scores"][0]),
        "lost": int(batch["lost"][0]),
        "tick": int(batch["ticks"][0]),
    }
    if expert:
        info["expert_action"] = int(batch["expert_actions"][0])
    return batch["observations"][0].astype(np.float32), info


def outcome_one(batch: Batch) -> tuple[float, bool, bool]:
    """A one-environment step's reward, ``terminated`` and ``truncated``, as Python values."""
    msg = batch._msg
    if msg is not None:
        reward = int.from_bytes(msg.rewards, "little", signed=True)
        terminated, truncated = msg.terminated, msg.truncated
        return float(reward), bool(terminated and terminated[0]), bool(truncated and truncated[0])
    return float(batch["rewards"][0]), bool(batch["terminated"][0]), bool(batch["truncated"][0])
