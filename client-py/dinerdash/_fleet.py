"""The fleet: a vector env's servers (:class:`~dinerdash._endpoint.Endpoint`) and its slices,
session cores each holding a contiguous range of environments, in environment order. After each
step or reset (:meth:`Fleet.settle`) slices move at once by Snapshot and Restore, exactly
(:func:`plan`); a lost server's environments get new sessions on the servers left
(:meth:`Fleet.fail_over`). Its watch gives up silent servers (:meth:`Fleet.await_replies`) and
finds servers to take in (:class:`Membership`). Why: docs/clusters.md#failover, docs/client.md.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

import grpc
import numpy as np

from . import connection
from ._batch import Batch, cut
from ._endpoint import Endpoint
from ._proto import pb
from ._session import ServerLost, SessionCore, Settings
from .connection import Connection, ConnectOptions, is_ip, split_host_port
from .errors import (
    InvalidArgument,
    NoServerLeft,
    ResourceExhausted,
    ServerDraining,
    ServiceError,
    ServiceTimeout,
    ServiceTransportError,
    SessionNotFound,
)

log = logging.getLogger("dinerdash")

#: Seconds a server that refused a Restore (full) is not asked again.
REFUSED_WAIT = 10.0
#: A server that refuses a failover's new session for one of these is passed over, not given up.
PASSED_OVER = (ServiceTransportError, ResourceExhausted, SessionNotFound)
#: Seconds a call may go unanswered before a health check is sent beside it (at most).
PROBE_AFTER = 1.0
#: Seconds between two health checks of the given-up servers.
PROBE_EVERY = 1.0


class Fleet:
    """The servers and slices of one vector env (see the module's doc)."""

    def __init__(self, options: ConnectOptions, settings: Settings) -> None:
        self.options = options
        self.settings = settings
        self.num_envs = n = settings.num_envs
        self.endpoint = endpoint = Endpoint(options, max_servers=max(1, n))
        self.membership: Membership | None = None
        #: Environments moved to another server by Snapshot and Restore (before a close()).
        self.moves = 0
        #: Servers that refused a Restore (full): until when they rest.
        self.refused_until: dict[int, float] = {}
        #: What :meth:`settle` saw last when the slices were where they should be.
        self.settled_key: tuple | None = None
        #: A Restore was refused for its snapshot version: said once.
        self.version_warned = False
        k = len(endpoint.connections)
        settings.split = k > 1
        parts = even_parts(0, n, dict.fromkeys(range(k), 0)) or [(0, 0, 0)]  # N = 0: refused
        self.cores = [SessionCore(endpoint, j, lo, hi, settings) for lo, hi, j in parts]
        try:
            for core in self.cores:
                self.spec: pb.Spec = core.create()
        except BaseException:
            self.close()
            raise
        # Membership for several servers, or a DNS name that may come to name several.
        if self.failover_on() and endpoint.server is None:
            if len(endpoint.connections) > 1 or has_name(options.address):
                self.membership = Membership(endpoint)

    def blocking(self) -> bool:
        """One session and no other server to watch: the step is one blocking call."""
        return len(self.cores) == 1 and not self.watched()

    def watched(self) -> bool:
        """Calls in flight are watched for silent servers (:meth:`await_replies`)."""
        return self.failover_on() and len(self.endpoint.live()) > 1

    def step(self, wire: np.ndarray) -> list[Batch]:
        """The step of a :meth:`blocking` fleet: its Batches, after any failover and move."""
        return self.collect(lambda core: core.step(wire.tobytes()), self.membership is not None)

    def start(self, wire: np.ndarray) -> None:
        """Every server's Step is sent (by its core's thread) before any reply is awaited."""
        for core in self.cores:
            core.start_step(wire[core.start : core.stop].tobytes())
        self.sent = time.monotonic()

    def wait(self) -> None:
        """Waits for every reply of the step :meth:`start` sent."""
        if self.watched():
            waiting = [(c.index, c.step_ready) for c in self.cores]
            self.await_replies(waiting, self.sent)
        else:
            for core in self.cores:
                core.step_ready()

    def finish(self) -> list[Batch]:
        """Every core's Batch of the step :meth:`start` sent, once :meth:`wait` returned."""
        return self.collect(SessionCore.finish_step, self.failover_on())

    def collect(
        self, outcome: Callable[[SessionCore], object], settle: bool, given: dict | None = None
    ) -> list[Batch]:
        """The cores' Batches once ``outcome(core)`` made each core's ``last`` this step's (or
        reset's, ``given``): all updated before the first error is raised, a lost server's
        environments moved (:meth:`fail_over`), then with ``settle`` slices (:meth:`settle`)."""
        error, lost = None, []
        for core in self.cores:
            try:
                outcome(core)
            except ServerLost as e:
                lost.append(e.core)
            except BaseException as e:
                if error is None:
                    error = e
        if lost:
            self.fail_over(lost, given)
        if error is not None:
            raise error
        if settle:
            self.settle()
        return self.batches()

    def reset(self, given: dict, mask: np.ndarray | None) -> np.ndarray:
        """Resets the environments of ``mask`` (all: ``None``) with ``given`` (the keywords of
        :meth:`~dinerdash._session.SessionCore.reset_request`); returns which environments' cores
        were called (a core with none in the mask keeps its state)."""
        called = np.zeros(self.num_envs, np.bool_)
        calls = {}
        for core in self.cores:
            if mask is None or mask[core.start : core.stop].any():
                called[core.start : core.stop] = True
                req = core.reset_request(**given, mask=mask)
                # A server given up at a step: its core's reset raises ServerLost, and it moves.
                calls[core] = (req, None if core.given_up() else core.conn.future("Reset", req))
        if self.watched():
            waiting = [(c.index, _ready(f)) for c, (_, f) in calls.items() if f is not None]
            self.await_replies(waiting, time.monotonic())
        self.collect(lambda c: c in calls and c.reset(*calls[c]), self.failover_on(), given)
        return called

    def await_replies(
        self, waiting: list[tuple[int, Callable[[float | None], bool]]], sent: float
    ) -> None:
        """Waits until every ``ready(deadline)`` of ``waiting`` (server index, ready) is True,
        giving up (its calls cancelled) each server that answers nothing for ``failover_after``
        seconds from ``sent`` or its last health check's answer, while another server answers."""
        endpoint, failover_after = self.endpoint, self.options.failover_after
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
                        f"it answered nothing (no call, no health check) for "
                        f"{now - heard[i]:.1f} s, past failover_after={failover_after:g} s",
                    )
                    probes.pop(i, None)
            pending = [(i, r) for i, r in pending if not r(time.monotonic() + 0.05)]

    def close(self) -> None:
        if self.membership is not None:
            self.membership.close()
        for core in self.cores:
            core.close()
        self.endpoint.close()

    def batches(self) -> list[Batch]:
        """The cores' last Batches, in environment order."""
        return [c.last for c in self.cores]

    def failover_on(self) -> bool:
        return self.options.reconnect and self.options.failover_after is not None

    def fail_over(self, lost: list[SessionCore], given: dict | None) -> None:
        """Gives up the servers of the ``lost`` cores and moves their environments (:meth:`move`,
        ``given``: a reset's keywords); the other cores are not touched."""
        for core in lost:
            after = self.options.failover_after
            self.endpoint.give_up(core.index, f"unreachable past failover_after={after:g} s")
            core.close()
        kept = [c for c in self.cores if all(c is not x for x in lost)]
        made: list[SessionCore] = []
        try:
            for core in lost:
                made += self.move(core, kept + made, given)
        except BaseException:
            for new in made:
                new.close()
            raise
        self.cores = sorted(kept + made, key=lambda c: c.start)

    def move(self, core: SessionCore, others: list[SessionCore], given: dict | None) -> list:
        """New cores, each started (:meth:`~dinerdash._session.SessionCore.start_after`), for the
        environments of ``core`` (its server given up) in :func:`even_parts` of the loads
        ``others`` leave on the servers open to new sessions, passing over those that refuse."""
        endpoint = core.endpoint
        candidates = [i for i in endpoint.open_to_new() if i != core.index]
        while True:
            if not candidates:
                lost = ", ".join(endpoint.addresses[i] for i in endpoint.given_up)
                draining = ", ".join(endpoint.addresses[i] for i in endpoint.draining)
                raise NoServerLeft(
                    f"no server left for environments {core.start}..{core.stop - 1}: every "
                    f"server of the env was given up ({lost or 'none'}), each unreachable for "
                    f"more than failover_after={self.options.failover_after:g} s, or drains "
                    f"({draining or 'none'})",
                    address=core.conn.address,
                )
            made: list[SessionCore] = []
            loads = dict.fromkeys(candidates, 0)
            for other in others:
                if other.index in loads:
                    loads[other.index] += other.stop - other.start
            parts = even_parts(core.start, core.stop, loads)
            try:
                for lo, hi, target in parts:
                    new = SessionCore(endpoint, target, lo, hi, core.settings)
                    new.create()
                    made.append(new)
                    try:
                        new.start_after(core, given)
                    except ServiceError as e:
                        raise new.fail(e) from None
                return made
            except BaseException as e:
                for new in made:
                    new.close()
                if not isinstance(e, PASSED_OVER):
                    raise
                if isinstance(e, ServerDraining):
                    endpoint.drain(target, None)
                candidates.remove(target)

    def settle(self) -> None:
        """After a step or a reset: takes in the servers the membership watch found, notes those
        that drain, and moves slices at once (:meth:`planned`, :meth:`split`) until none is on a
        draining server and the loads differ by at most one (one a failover just cut: next step)."""
        endpoint = self.endpoint
        for index, conn in self.membership.found() if self.membership is not None else ():
            new = index is None and conn.address not in endpoint.addresses
            if index is not None and index in endpoint.given_up:
                endpoint.take_back(index, conn)
            elif new and len(endpoint.live()) < self.num_envs:  # no more servers than envs
                endpoint.add(conn)
            else:
                conn.close()
        for core in self.cores:
            if core.drain_ms > 0:
                endpoint.drain(core.index, core.drain_ms / 1000)
        key, targets = self.key()
        if key == self.settled_key:
            return  # nothing changed since the slices were where they should be: the common step
        cores = list(self.cores)
        # The first refused stops the moves: planned again at the next step, knowing the refusal.
        settled = all(self.split(cores[k], parts) for k, parts in self.planned(targets))
        for i in list(endpoint.draining):
            if not any(c.index == i for c in self.cores):
                endpoint.give_up(i)  # drained: probed, and taken back once it serves again
        key, targets = self.key()
        settled = settled and not self.refused_until and not self.planned(targets, everyone=True)
        self.settled_key = key if settled else None

    def planned(self, targets: list[int], everyone: bool = False) -> list:
        """:func:`plan` for the slices as they are, those that may move now (``everyone``: all;
        then nothing planned says every environment is on ``targets``, their loads within one)."""
        slices = [(c.index, c.start, c.stop, everyone or c.movable()) for c in self.cores]
        return plan(slices, self.num_envs, targets) if targets else []

    def key(self) -> tuple[tuple, list[int]]:
        """What :meth:`settle` compares with :attr:`settled_key`, and the :meth:`targets`."""
        e, targets = self.endpoint, self.targets()
        return (len(self.cores), tuple(e.given_up), tuple(e.draining), tuple(targets)), targets

    def targets(self) -> list[int]:
        """The servers slices may move to now: open to new sessions and not resting (refused)."""
        now = time.monotonic()
        for j in [j for j, until in self.refused_until.items() if until <= now]:
            del self.refused_until[j]
        return [j for j in self.endpoint.open_to_new() if j not in self.refused_until]

    def split(self, core: SessionCore, parts: list[tuple[int, int, int]]) -> bool:
        """Replaces ``core`` by new cores for ``parts`` (``(start, stop, server)``, covering its
        environments): a Snapshot of each range, restored on its server; then ``core``'s session is
        closed. False (nothing changed) when a server cannot take its part or the Snapshot fails."""
        made: list[SessionCore] = []
        moved = 0
        try:
            for lo, hi, dest in parts:
                request = pb.SnapshotRequest(
                    session_id=core.session_id, env_start=lo - core.start, env_count=hi - lo
                )
                snapshot = core.conn.call("Snapshot", request, timeout=self.move_timeout())
                new = SessionCore(self.endpoint, dest, lo, hi, self.settings)
                made.append(new)
                last = core.last.slice(lo - core.start, hi - core.start).copy()
                try:
                    if self.restore(new, snapshot.snapshot, last, core) and dest != core.index:
                        moved += hi - lo
                except ServiceError as e:  # marked draining, given up (no answer), or full
                    if isinstance(e, ServerDraining):
                        self.endpoint.drain(dest, None)
                    elif isinstance(e, (ServiceTransportError, ServiceTimeout)):
                        self.endpoint.give_up(dest, f"could not restore a session there: {e}")
                    else:
                        self.refused_until[dest] = time.monotonic() + REFUSED_WAIT
                    raise
        except BaseException as e:
            for new in made:
                new.close()
            if isinstance(e, ServiceError):
                return False
            raise
        core.close()
        self.cores = sorted(
            [*made, *(c for c in self.cores if c is not core)], key=lambda c: c.start
        )
        self.moves += moved
        return True

    def restore(self, new: SessionCore, snapshot: bytes, last: Batch, old: SessionCore) -> bool:
        """Opens ``new``'s session from ``snapshot`` (``last``: its environments' Batch of the step
        just made). True when restored; False when cut (another snapshot version: new episodes,
        :func:`~dinerdash._batch.cut`, said once as a warning)."""
        timeout = self.move_timeout()
        try:
            reply = new.conn.call("Restore", pb.RestoreRequest(snapshot=snapshot), timeout=timeout)
        except InvalidArgument as e:
            if not self.version_warned:
                self.version_warned = True
                log.warning(
                    "the server at %s refused a snapshot of the server at %s (%s): another "
                    "snapshot version? Environments moved between such servers start new "
                    "episodes, their episodes cut (truncated, info['reconnected'])",
                    new.conn.address,
                    old.conn.address,
                    e.details,
                )
            new.create(timeout)
            new.interrupt(last, cut, timeout)
            return False
        new.adopt(reply, last)
        return True

    def move_timeout(self) -> float:
        """The deadline of a move's calls: a server silent for ``failover_after`` is passed over."""
        return min(self.options.timeout, self.options.failover_after)


def plan(
    slices: list[tuple[int, int, int, bool]], n: int, targets: list[int]
) -> list[tuple[int, list[tuple[int, int, int]]]]:
    """Which of ``slices`` (``(server, start, stop, movable)``, covering environments ``0:n`` in
    order) to split or move, by position, each with its new parts ``(start, stop, server)`` in
    environment order, so that once done no movable environment is on a server outside ``targets``
    and their loads differ by at most one (a pure function: no I/O)."""
    loads = dict.fromkeys(targets, 0)
    for server, lo, hi, _ in slices:
        if server in loads:
            loads[server] += hi - lo
    order = sorted(targets, key=lambda j: (-loads[j], j))
    k = len(targets)
    share = {j: n // k + (r < n % k) for r, j in enumerate(order)}
    free = [
        (pos, lo) for pos, (server, lo, _, ok) in enumerate(slices) if ok and server not in loads
    ]
    for j in targets:
        mine = [pos for pos, s in enumerate(slices) if s[0] == j and s[3]]
        for pos in sorted(mine, key=lambda pos: slices[pos][1] - slices[pos][2]):
            _, lo, hi, _ = slices[pos]
            give = min(loads[j] - share[j], hi - lo)
            if give <= 0:
                break
            free.append((pos, hi - give))
            loads[j] -= give
    out = []
    for pos, first in free:
        server, lo, hi, _ = slices[pos]
        parts = [(lo, first, server)] if first > lo else []
        at = first
        while at < hi:
            short = [(share[j] - loads[j], -j) for j in targets if loads[j] < share[j]]
            if not short:
                break
            dest = -max(short)[1]
            stop = min(hi, at + share[dest] - loads[dest])
            parts.append((at, stop, dest))
            loads[dest] += stop - at
            at = stop
        if at == hi:
            out.append((pos, parts))
    return out


def even_parts(start: int, stop: int, loads: dict[int, int]) -> list[tuple[int, int, int]]:
    """Environments ``start:stop`` cut into one contiguous part ``(start, stop, server)`` per
    server of ``loads`` (server -> environments it holds): sizes differ by at most one, the larger
    to the least loaded (ties: the lower index); empty parts left out."""
    order = sorted(loads, key=lambda i: (loads[i], i))
    m, k = stop - start, len(order)
    out = []
    for j, server in enumerate(order):
        size = m // k + (j < m % k)
        if size:
            out.append((start, start + size, server))
            start += size
    return out


def _ready(future: grpc.Future):
    """``ready(deadline)`` of a grpc future: True once it has its outcome."""

    done = threading.Event()
    future.add_done_callback(lambda _: done.set())

    def ready(deadline: float | None) -> bool:
        return done.wait(None if deadline is None else max(0.0, deadline - time.monotonic()))

    return ready


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
                _, conn, check = self._probes.get(address, (index, None, None))
                if check is not None:
                    continue  # the last one is still out
                try:
                    if conn is None:
                        conn = self._options.connect(address, wait=False)
                    self._probes[address] = (index, conn, conn.health(PROBE_EVERY))
                except (ServiceError, OSError, ValueError):
                    if conn is not None:
                        conn.close()
                    self._probes.pop(address, None)
        return out

    def _resolve(self, every: float) -> None:
        while not self._stop.wait(every):
            try:
                self._replicas = connection.resolve_replicas(self._options.address)
            except (OSError, ValueError):
                pass

    def close(self) -> None:
        self._stop.set()
        for _, conn, _ in self._probes.values():
            conn.close()
        self._probes = {}
