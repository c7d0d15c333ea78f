"""Failover: a given-up server's environments (``reconnect=True``, ``failover_after``) move to
the servers left that take new sessions, in contiguous parts of sizes differing by at most one,
the larger to the least loaded; each keeps its index, their episodes end truncated (or start
as the caller's ``start`` says). The other servers' cores are not touched.
"""

from __future__ import annotations

from collections.abc import Callable

from ._batch import Batch
from ._session import SessionCore
from .errors import (
    NoServerLeft,
    ResourceExhausted,
    ServerDraining,
    ServiceError,
    ServiceTransportError,
    SessionNotFound,
)

__all__ = ["even_parts", "fail_over", "move"]

#: A server that refuses a new session for one of these is passed over, not given up: the
#: environments go to the other servers left.
PASSED_OVER = (ServiceTransportError, ResourceExhausted, SessionNotFound)


def even_parts(start: int, stop: int, loads: dict[int, int]) -> list[tuple[int, int, int]]:
    """Environments ``start:stop`` cut into one contiguous piece per server of ``loads``
    (server index -> environments it holds), as ``(start, stop, server)``: the sizes differ by
    at most one, the larger ones go to the servers holding fewest environments (ties: the lower
    index), and empty pieces are left out."""
    order = sorted(loads, key=lambda i: (loads[i], i))
    m, k = stop - start, len(order)
    out = []
    for j, server in enumerate(order):
        size = m // k + (j < m % k)
        if size:
            out.append((start, start + size, server))
            start += size
    return out


#: ``start(lost_core, new_core)``: the new core's session is created; this resets it and returns
#: the Batch that the env reports for the new core's environments.
Start = Callable[[SessionCore, SessionCore], Batch]


def move(core: SessionCore, cores: list[SessionCore], start: Start) -> list[SessionCore]:
    """New cores for the environments of ``core`` (whose server is given up or drains) on the
    servers that take new sessions, given ``cores`` (the env's others, for the servers' loads), each
    started by ``start``; its Batch becomes the new core's ``last``."""
    endpoint = core.endpoint
    first, stop = core.start, core.stop
    candidates = [i for i in endpoint.open_to_new() if i != core.index]
    while True:
        if not candidates:
            lost = ", ".join(endpoint.addresses[i] for i in endpoint.given_up)
            draining = ", ".join(endpoint.addresses[i] for i in endpoint.draining)
            raise NoServerLeft(
                f"no server left for environments {first}..{stop - 1}: every server of the env "
                f"was given up ({lost or 'none'}), each unreachable for more than "
                f"failover_after={core.settings.failover_after:g} s, or drains "
                f"({draining or 'none'})",
                address=core.conn.address,
            )
        loads = dict.fromkeys(candidates, 0)
        for c in cores:
            if c.index in loads:
                loads[c.index] += c.size
        made: list[SessionCore] = []
        target = None
        try:
            for lo, hi, target in even_parts(first, stop, loads):
                new = SessionCore(endpoint, target, lo, hi, core.settings)
                new.create()
                made.append(new)
                try:
                    new.start_with(start(core, new))
                except ServiceError as e:
                    raise new.fail(e) from None
            return made
        except PASSED_OVER as e:
            if isinstance(e, ServerDraining):
                endpoint.drain(target, None)
            candidates.remove(target)
            for new in made:
                new.close()
        except BaseException:
            for new in made:
                new.close()
            raise


def fail_over(
    cores: list[SessionCore], lost: list[SessionCore], start: Start, why: str | None = ""
) -> list[SessionCore]:
    """The env's cores after the servers of the ``lost`` cores are given up and their environments
    moved (:func:`move`), ordered by their first environment."""
    endpoint = lost[0].endpoint
    for core in lost:
        reason = why or f"unreachable past failover_after={core.settings.failover_after:g} s"
        endpoint.give_up(core.index, None if why is None else reason)
    for core in lost:
        core.close()
    out = [c for c in cores if all(c is not x for x in lost)]
    kept = len(out)
    try:
        for core in lost:
            out.extend(move(core, out, start))
    except BaseException:
        for new in out[kept:]:
            new.close()
        raise
    out.sort(key=lambda c: c.start)
    return out
