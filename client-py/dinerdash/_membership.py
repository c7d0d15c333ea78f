"""Membership: which servers a vector env over several servers uses, as they hang, come back,
appear and drain (``reconnect=True`` with ``failover_after``).

- :func:`await_replies` waits for the replies of calls in flight and watches their servers: a
  server that has answered nothing (neither the call nor a health check sent beside it) for
  ``failover_after`` seconds is given up, which cancels its calls, and its environments move
  as a killed server's do (:mod:`dinerdash._failover`). A server that answers late is kept.
- :class:`Membership` checks the given-up servers' health and a DNS-name address's new
  replicas (resolved again every ``resolve_every`` seconds) at the env's step boundaries,
  without blocking; the env takes the servers it found (:meth:`Membership.found`).
- :func:`handover` builds the Batch of environments that move to another server at their
  episode end (rebalancing onto a server taken in, or leaving a draining server), so that no
  episode is cut; or, when a draining server's deadline is about to pass, cut as a failover's.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import time
from collections.abc import Callable, Sequence

import grpc
import numpy as np
from gymnasium.vector import AutoresetMode

from . import connection
from ._decode import copy_of
from ._endpoint import Endpoint
from ._proto import pb
from .connection import Connection, ConnectOptions, _split_host_port
from .errors import ServiceError

__all__ = ["Membership", "await_replies", "boundary", "handover", "has_name", "splice"]

log = logging.getLogger("dinerdash")

#: Seconds a call may go unanswered before a health check is sent beside it (at most): a quick
#: call never costs a check.
PROBE_AFTER = 1.0
#: Seconds between two health checks of the given-up servers.
PROBE_EVERY = 1.0


def await_replies(
    waiting: Sequence[tuple[int, Callable[[float | None], bool]]],
    endpoint: Endpoint,
    failover_after: float,
    sent: float,
) -> None:
    """Waits until every ``ready(deadline)`` of ``waiting`` (server index, ready) is True, giving
    up each server that answers nothing for ``failover_after`` seconds from ``sent`` (when the
    calls left) or from its last answer to a health check, as long as another server is live and
    not silent. Giving a server up closes its channel: its calls end at once (cancelled)."""
    probe_after = min(PROBE_AFTER, failover_after / 4)
    pending = list(waiting)
    first = sent + probe_after
    pending = [(i, ready) for i, ready in pending if not ready(first)]
    if not pending:
        return
    heard: dict[int, float] = {}  # server -> last answer (or ``sent``)
    probes: dict[int, grpc.Future] = {}
    while pending:
        now = time.monotonic()
        for i in {i for i, _ in pending}:
            if i in endpoint.given_up:
                continue
            heard.setdefault(i, sent)
            probe = probes.get(i)
            if probe is not None and probe.done():
                del probes[i]
                if not probe.cancelled() and probe.exception() is None:
                    heard[i] = now
            if i not in probes and now - heard[i] >= probe_after:
                try:
                    probes[i] = endpoint.connections[i].health(
                        max(0.05, failover_after - (now - heard[i]))
                    )
                except ServiceError:
                    pass
        still = {i for i, ready in pending if not ready(now)}
        silent = [
            i
            for i, t in heard.items()
            if i in still and i not in endpoint.given_up and now - t >= failover_after
        ]
        if silent:
            answering = [i for i in endpoint.live() if i not in silent]
            if answering:
                for i in silent:
                    endpoint.give_up(
                        i,
                        f"it answered nothing (no call, no health check) for "
                        f"{now - heard[i]:.1f} s, past failover_after={failover_after:g} s",
                    )
                    probes.pop(i, None)
        pending = [(i, r) for i, r in pending if not r(time.monotonic() + 0.05)]


def has_name(address: str | Sequence[str] | None) -> bool:
    """``address`` names a host by DNS name (which may resolve to other replicas later)."""
    if address is None:
        return False
    try:
        items = connection.parse_addresses(address)
    except ValueError:
        return False
    for item in items:
        try:
            ipaddress.ip_address(_split_host_port(item)[0])
        except ValueError:
            return True
    return False


class Membership:
    """Looks for servers to take in, at the env's step boundaries (:meth:`found`), without
    blocking: every :data:`PROBE_EVERY` seconds a ``grpc.health.v1`` check goes to each given-up
    server (on a channel kept for it) and to each new replica of a DNS-name address, and the
    checks answered SERVING by the next boundary are handed over with their connection. The
    address is resolved again every ``resolve_every`` seconds by a thread that only resolves
    names: no gRPC call is made off the env's own calls, so that a process that forks (a
    subprocess, a multiprocessing worker) never does so in the middle of one."""

    def __init__(self, endpoint: Endpoint, options: ConnectOptions) -> None:
        self._endpoint = endpoint
        self._options = endpoint.options
        self._address = options.address
        #: address -> (index or None for a new replica, connection, health check in flight).
        self._probes: dict[str, tuple[int | None, Connection, grpc.Future | None]] = {}
        self._next = time.monotonic() + PROBE_EVERY
        #: The replicas the address resolved to last (the resolver thread's answer).
        self._replicas: list[str] = []
        self._stop = threading.Event()
        every = options.resolve_every if has_name(options.address) else None
        if every is not None:
            threading.Thread(
                target=self._resolve, args=(every,), name="dinerdash-resolve", daemon=True
            ).start()

    def found(self) -> list[tuple[int | None, Connection]]:
        """The servers found since the last call: ``(index, conn)`` for a given-up server that
        answers SERVING again, ``(None, conn)`` for a new replica. The caller takes or closes
        each. Sends the next round of checks when it is time."""
        out = []
        for address, (index, conn, check) in list(self._probes.items()):
            if check is None or not check.done():
                continue
            serving = not check.cancelled() and check.exception() is None and check.result()
            if serving:
                del self._probes[address]
                out.append((index, conn))
            else:
                self._probes[address] = (index, conn, None)
        now = time.monotonic()
        if now >= self._next:
            self._next = now + PROBE_EVERY
            endpoint = self._endpoint
            wanted = {endpoint.addresses[i]: i for i in endpoint.given_up}
            known = set(endpoint.addresses)
            wanted.update({a: None for a in self._replicas if a not in known})
            for address in [a for a in self._probes if a not in wanted]:
                self._probes.pop(address)[1].close()
            for address, index in wanted.items():
                self._check(address, index)
        return out

    def _check(self, address: str, index: int | None) -> None:
        _, conn, check = self._probes.get(address, (index, None, None))
        if check is not None:
            return  # the last one is still out
        try:
            if conn is None:
                conn = self._options.connect(address, wait=False)
            self._probes[address] = (index, conn, conn.health(PROBE_EVERY))
        except (ServiceError, OSError, ValueError):
            if conn is not None:
                conn.close()
            self._probes.pop(address, None)

    def _resolve(self, every: float) -> None:
        while not self._stop.wait(every):
            try:
                self._replicas = connection.resolve_replicas(self._address)
            except (OSError, ValueError):
                pass

    def close(self) -> None:
        self._stop.set()
        for _, conn, _ in self._probes.values():
            conn.close()
        self._probes = {}


def boundary(batch: pb.Batch, mode: AutoresetMode) -> np.ndarray:
    """Which environments of ``batch`` (a step's) are at an episode end, where one may move
    without cutting its episode: NEXT_STEP, the episode ended in this step (its next step is
    the autoreset); SAME_STEP, the next episode began in this step and has not been played."""
    if mode == AutoresetMode.SAME_STEP:
        return np.frombuffer(batch.reset, np.bool_) if batch.reset else np.zeros(0, np.bool_)
    done = np.frombuffer(batch.terminated, np.bool_) | np.frombuffer(batch.truncated, np.bool_)
    return done


def handover(ended: pb.Batch, first: pb.Batch, mode: AutoresetMode, cut: bool) -> tuple:
    """The Batch that environments moving to a new session report for the step just made,
    and the Batch their next step reports (NEXT_STEP's autoreset; else ``None``).

    ``ended`` is their part of the step's Batch on the old server, ``first`` the new session's
    Reset reply. Not ``cut`` (they are at an episode end, :func:`boundary`): NEXT_STEP reports
    ``ended`` as it is and the next step hands out ``first`` as the autoreset; SAME_STEP reports
    ``first`` as the new episode, with the ended one's last state and infos as ``final_*``, so
    that the new episode is the new server's. ``cut`` (a drain deadline about to pass): their
    episodes end truncated in this step, as a failover's do, keeping this step's rewards."""
    n = ended.num_envs or len(ended.rewards) // 4
    if mode != AutoresetMode.SAME_STEP:
        out = copy_of(ended)
        if cut:
            terminated = np.frombuffer(ended.terminated, np.bool_)
            out.truncated = (~terminated).astype(np.uint8).tobytes()
        return out, first
    out = copy_of(first)
    out.rewards = ended.rewards
    out.terminated = ended.terminated
    if cut:
        out.final_observations = ended.observations
        out.final_scores = ended.scores
        out.final_lost = ended.lost
        out.final_ticks = ended.ticks
        out.final_action_masks = ended.action_masks
        out.final_expert_actions = ended.expert_actions
        terminated = np.frombuffer(ended.terminated, np.bool_)
        out.truncated = (~terminated).astype(np.uint8).tobytes()
    else:
        out.truncated = ended.truncated
        out.final_observations = ended.final_observations
        out.final_scores = ended.final_scores
        out.final_lost = ended.final_lost
        out.final_ticks = ended.final_ticks
        out.final_action_masks = ended.final_action_masks
        out.final_expert_actions = ended.final_expert_actions
    out.reset = b"\x01" * n
    out.ClearField("stream_episodes")
    return out, None


#: What a step reports of an episode's outcome (the rest is the environment's state).
OUTCOME = ("rewards", "terminated", "truncated")
FINAL = (
    "final_observations",
    "final_scores",
    "final_lost",
    "final_ticks",
    "final_action_masks",
    "final_expert_actions",
)


def splice(base: pb.Batch, other: pb.Batch, mask: np.ndarray, fields=None) -> pb.Batch:
    """``base`` with the environments of ``mask`` taken from ``other`` (a Batch of the same
    environments) for ``fields`` (default: every field ``other`` has but the episode outcome
    and ``final_*``); a field missing on one side counts as zeros."""
    n = len(mask)
    out = copy_of(base)
    if fields is None:
        fields = [
            d.name
            for d, _ in other.ListFields()
            if d.name not in OUTCOME + FINAL and d.name not in ("num_envs", "stream_episodes")
        ]
    for name in fields:
        if name == "seeds":
            mine = list(base.seeds) or [0] * n
            theirs = list(other.seeds) or [0] * n
            del out.seeds[:]
            out.seeds.extend(t if m else b for b, t, m in zip(mine, theirs, mask, strict=True))
            continue
        a, b = getattr(base, name), getattr(other, name)
        if not a and not b:
            continue
        width = max(len(a), len(b)) // n
        joined = _rows(a, n, width).copy()
        joined[mask] = _rows(b, n, width)[mask]
        setattr(out, name, joined.tobytes())
    return out


def _rows(data: bytes, n: int, width: int) -> np.ndarray:
    """A packed field as one row of bytes per environment (zeros when absent)."""
    if not data:
        return np.zeros((n, width), np.uint8)
    return np.frombuffer(data, np.uint8).reshape(n, width)
