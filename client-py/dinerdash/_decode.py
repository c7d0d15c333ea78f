"""Reply decoding: the packed fields of the server's ``Batch`` replies turned into the numpy
observations and Gymnasium infos the environments return (:func:`decode` for a vector env,
:func:`decode_one` for the single env), a Batch cut (:func:`slice_batch`) or joined
(:func:`join`) along its environments when an env's environments live on several servers, and
what a Batch says about its server (:func:`drain_remaining_ms`: whether it drains before a
restart)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._proto import pb
from .game import NUM_ACTIONS, OBSERVATION_SIZE

__all__ = ["decode", "decode_one", "drain_remaining_ms", "join", "seeds", "slice_batch"]


def drain_remaining_ms(batch: pb.Batch | None) -> int:
    """Milliseconds left before the server that sent ``batch`` ends its session, when that server
    is draining before a restart (it got SIGTERM: it serves its sessions for up to its
    ``--drain-timeout`` and takes no new ones); 0 when it is not draining, or when there is no
    Batch yet. Each server's Batch says it for that server: a vector env reads it per core
    (``core.last``)."""
    return 0 if batch is None else batch.drain_remaining_ms


def copy_of(batch: Any) -> pb.Batch:
    """A ``pb.Batch`` of ``batch``'s own: a copy of a gRPC reply, or the ``pb.Batch`` that a
    shared-memory reply (:class:`dinerdash._shm.RegionBatch`, which protobuf cannot copy from)
    makes of itself."""
    to_pb = getattr(batch, "to_pb", None)
    if to_pb is not None:
        return to_pb()
    out = pb.Batch()
    out.CopyFrom(batch)
    return out


def slice_batch(batch: pb.Batch, lo: int, hi: int) -> pb.Batch:
    """Environments ``lo:hi`` of ``batch``: every packed field cut at its width per environment
    (the observations' 40 bytes, a score's 4, ...), every repeated field sliced."""
    n = len(batch.observations) // OBSERVATION_SIZE
    out = pb.Batch(num_envs=hi - lo)
    for desc, value in batch.ListFields():
        if desc.name == "num_envs":
            continue
        if isinstance(value, bytes):
            width = len(value) // n
            setattr(out, desc.name, value[lo * width : hi * width])
        elif isinstance(value, int):  # about the whole session: drain_remaining_ms
            setattr(out, desc.name, value)
        else:  # repeated: seeds, stream_episodes
            getattr(out, desc.name).extend(value[lo:hi])
    return out


def join(batches: list[pb.Batch], name: str) -> bytes:
    """Field ``name`` of every core's Batch, in environment order."""
    if len(batches) == 1:
        return getattr(batches[0], name)
    return b"".join([getattr(b, name) for b in batches])


def seeds(batches: list[pb.Batch]) -> np.ndarray:
    if len(batches) == 1:
        return np.array(batches[0].seeds, dtype=np.uint64)
    return np.array([s for b in batches for s in b.seeds], dtype=np.uint64)


def decode(
    batches: list[pb.Batch],
    num_envs: int,
    expert: bool,
    prefix: str = "",
    present: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Observations ``(N, 40)`` and infos of the state the batches return, or with
    ``prefix="final_"`` of the episodes that ended (SAME_STEP); ``present`` is every info key's
    Gymnasium ``_key`` mask."""
    n = num_envs
    if present is None:
        present = np.ones(n, dtype=np.bool_)

    def field(name: str, dtype: str) -> np.ndarray:
        return np.frombuffer(join(batches, prefix + name), dtype=dtype)

    obs = field("observations", "i1").reshape(n, OBSERVATION_SIZE).astype(np.float32)
    info: dict[str, Any] = {
        "action_mask": field("action_masks", "?").reshape(n, NUM_ACTIONS).copy(),
        "score": field("scores", "<i4").astype(np.int64),
        "lost": field("lost", "<u4").astype(np.int64),
        "tick": field("ticks", "<u4").astype(np.int64),
    }
    if expert:
        info["expert_action"] = field("expert_actions", "u1").astype(np.int64)
    for key in list(info):
        info[f"_{key}"] = present.copy()
    return obs, info


def decode_one(batch: pb.Batch, expert: bool) -> tuple[np.ndarray, dict[str, Any]]:
    """The observation ``(40,)`` and info of a one-environment Batch: :func:`decode` without the
    batch axis, with plain ``int`` values (cheaper than numpy for one environment)."""
    obs = np.frombuffer(batch.observations, dtype=np.int8).astype(np.float32)
    info: dict[str, Any] = {
        "action_mask": np.frombuffer(batch.action_masks, dtype=np.bool_).copy(),
        "score": int.from_bytes(batch.scores, "little", signed=True),
        "lost": int.from_bytes(batch.lost, "little"),
        "tick": int.from_bytes(batch.ticks, "little"),
    }
    if expert:
        info["expert_action"] = batch.expert_actions[0]
    return obs, info
