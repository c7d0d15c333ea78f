"""Membership: :func:`await_replies` gives up a server that answers nothing (no call, no health
check) for ``failover_after``; :class:`Membership` finds given-up servers that answer again and a
DNS name's new replicas, at step boundaries, without blocking (docs/client.md#design-notes).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

import grpc

from . import connection
from ._endpoint import Endpoint
from .connection import Connection, is_ip, split_host_port
from .errors import ServiceError

log = logging.getLogger("dinerdash")

#: Seconds a call may go unanswered before a health check is sent beside it (at most).
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
    up (its calls cancelled) each server that answers nothing for ``failover_after`` seconds from
    ``sent`` or its last health check's answer, while another server is live and answers."""
    probe_after = min(PROBE_AFTER, failover_after / 4)
    pending = [(i, ready) for i, ready in waiting if not ready(sent + probe_after)]
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
        still = {i for i, ready in pending if not ready(now)} - set(endpoint.given_up)
        silent = [i for i, t in heard.items() if i in still and now - t >= failover_after]
        if silent and any(i not in silent for i in endpoint.live()):
            for i in silent:
                endpoint.give_up(
                    i,
                    f"it answered nothing (no call, no health check) for {now - heard[i]:.1f} s, "
                    f"past failover_after={failover_after:g} s",
                )
                probes.pop(i, None)
        pending = [(i, r) for i, r in pending if not r(time.monotonic() + 0.05)]


def has_name(address: str | Sequence[str] | None) -> bool:
    """``address`` names a host by DNS name (which may resolve to other replicas later)."""
    try:
        items = [] if address is None else connection.parse_addresses(address)
    except ValueError:
        return False
    return not all(is_ip(split_host_port(item)[0]) for item in items)


class Membership:
    """Looks for servers to take in at the env's step boundaries (:meth:`found`): every
    :data:`PROBE_EVERY` seconds a health check goes to each given-up server and each new replica
    of a DNS-name address; those answered SERVING by then are handed over with their channel."""

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        self._options = options = endpoint.options
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
        answers SERVING again, ``(None, conn)`` for a new replica."""
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
