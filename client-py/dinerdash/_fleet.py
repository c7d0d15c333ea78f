"""The fleet: the servers a vector env uses and its sessions on them, as they fail, come back,
appear and drain. :class:`Fleet` owns the :class:`~dinerdash._endpoint.Endpoint` (connections,
given-up and draining servers), the :class:`~dinerdash._membership.Membership` watch and the
session cores in environment order; the Gymnasium adapter (:mod:`dinerdash.vector`) only asks it
for the step's Batches and tells it when a step or a reset ended.

After a step (:meth:`Fleet.settle`) it notes which servers drain and moves environments between
servers at their own episode ends: the moves are planned by a pure function of a view of the
sessions (:func:`dinerdash._placement.plan`) and applied here (a transfer: a session on the
destination for a run of environments, each entering it at its episode end, :meth:`Fleet.enter`);
a draining server whose deadline is about to pass has its environments handed over at once, their
episodes cut (:meth:`Fleet.hand_over`). A failed server's environments move with
:func:`dinerdash._failover.fail_over`. The fleet does the calls of a move; each session's phase
(serving, receiving a transfer, draining, lost: :class:`~dinerdash._session.Phase`) and what it
holds are changed by the session core's own methods, never assigned here.
"""

from __future__ import annotations

import time

import grpc
import numpy as np
from gymnasium.vector import AutoresetMode

from ._batch import FINAL, OUTCOME, Batch, boundary, handover
from ._endpoint import Endpoint
from ._failover import fail_over
from ._membership import Membership, await_replies, has_name
from ._placement import SessionView, plan
from ._proto import pb
from ._session import ServerLost, SessionCore, Settings
from .connection import ConnectOptions
from .errors import ServerDraining, ServiceError, ServiceTimeout, ServiceTransportError

__all__ = ["REST", "Fleet", "interrupted"]

#: Seconds a server that refused a session for moving environments (full) is not asked again.
REST = 10.0


class Fleet:
    """The servers and sessions of one vector env (see the module's doc). Created by opening one
    session per server, the environments split into contiguous slices; :meth:`close` closes
    them, the membership watch and the connections (and the local server, if any)."""

    def __init__(self, options: ConnectOptions, settings: Settings) -> None:
        self.options = options
        self.settings = settings
        self.num_envs = n = settings.num_envs
        self.endpoint = endpoint = Endpoint(options, max_servers=max(1, n))
        self.membership: Membership | None = None
        #: Environments moved to another server at their episode end (before a close()).
        self.moves = 0
        #: Servers that refused a session of moving environments (full): until when they rest.
        self.resting: dict[int, float] = {}
        #: What the last planning saw, and the servers and sessions of the last step after
        #: which nothing was under way (:meth:`settle`).
        self.planned: tuple = ()
        self.quiet: tuple | None = None
        #: When the last step or reset ended: the time between steps, for a drain's margin.
        self.last_finish = time.monotonic()
        k = len(endpoint.connections)
        settings.split = k > 1
        sizes = [n // k + (j < n % k) for j in range(k)]
        self.cores: list[SessionCore] = []
        start = 0
        for j, size in enumerate(sizes):
            self.cores.append(SessionCore(endpoint, j, start, start + size, settings))
            start += size
        try:
            for core in self.cores:
                self.spec: pb.Spec = core.create()
        except BaseException:
            for core in self.cores:
                core.close()
            endpoint.close()
            raise
        # Membership for several servers, or a DNS name that may come to name several.
        if self.failover_on() and endpoint.server is None:
            if len(endpoint.connections) > 1 or has_name(options.address):
                self.membership = Membership(endpoint, options)

    # -- a step and a reset --------------------------------------------------------------------

    def blocking(self) -> bool:
        """One session and no other server to watch: the step is one blocking call, cheaper than
        a hand-off to a thread (or to gRPC's completion thread)."""
        return len(self.cores) == 1 and not (self.failover_on() and len(self.endpoint.live()) > 1)

    def step(self, wire: np.ndarray) -> list[Batch]:
        """The step of a :meth:`blocking` fleet: its Batches, after any failover and move."""
        core = self.cores[0]
        try:
            core.step(wire.tobytes())
        except ServerLost as e:
            self.cores = fail_over(self.cores, [e.core], interrupted)
        if self.membership is not None:
            self.take_in()
            self.settle()
        return self.batches()

    def start(self, wire: np.ndarray) -> None:
        """Every server's Step is sent (by its core's thread) before any reply is awaited: the
        servers work in parallel, and with the caller."""
        for core in self.cores:
            core.start_step(wire[core.start : core.stop].tobytes())
        self.sent = time.monotonic()

    def wait(self) -> None:
        """Waits for every reply of the step :meth:`start` sent. A server that answers nothing
        (the step nor a health check) for ``failover_after`` is given up first
        (:func:`~dinerdash._membership.await_replies`)."""
        endpoint = self.endpoint
        if self.failover_on() and len(endpoint.live()) > 1:
            waiting = [(c.index, c.step_ready) for c in self.cores]
            await_replies(waiting, endpoint, self.settings.failover_after, self.sent)
        else:
            for core in self.cores:
                core.step_ready()

    def finish(self) -> list[Batch]:
        """Every core's Batch of the step :meth:`start` sent, once :meth:`wait` returned. Every
        core is updated before the first error, if any, is raised: no server's step goes
        unrecorded. The environments of a core whose server was lost past ``failover_after``
        move to the servers left first, and report this step as interrupted
        (:func:`interrupted`); then the servers found are taken in and environments at their
        episode ends move (:meth:`settle`)."""
        error, lost = None, []
        for core in self.cores:
            try:
                core.finish_step()  # its Batch is core.last
            except ServerLost as e:
                lost.append(e.core)
            except BaseException as e:
                if error is None:
                    error = e
        if lost:
            self.cores = fail_over(self.cores, lost, interrupted)
        if error is not None:
            raise error
        if self.failover_on():
            self.take_in()
            self.settle()
        return self.batches()

    def reset(self, given: dict, mask: np.ndarray | None) -> set[int]:
        """Resets the environments of ``mask`` (all: ``None``) with ``given`` (``seed``,
        ``seeds``, ``arrivals``, ``config`` of :meth:`SessionCore.reset_request
        <dinerdash._session.SessionCore.reset_request>`); returns the ``id`` of the cores not
        called (none of their environments in the mask: they keep their state). A full reset
        ends every episode: the transfers under way are done at once and a draining server's
        environments move now; a server lost during the reset has its environments moved, their
        new sessions reset whole, as after a reconnect."""
        endpoint = self.endpoint
        given_up = endpoint.given_up
        self.take_in()

        def start(old: SessionCore, new: SessionCore) -> Batch:
            return Batch.from_pb(new.conn.call("Reset", new.reset_request(**given)))

        for core in self.cores:
            core.forget_entering()
        if mask is None:
            self.complete_transfers()
        if mask is None and self.failover_on():
            drained = [c for c in self.cores if c.index in endpoint.draining]
            if drained:
                self.moves += sum(c.load for c in drained)
                self.cores = fail_over(self.cores, drained, start, why=None)
        calls, kept = [], set()
        for core in self.cores:
            if mask is not None and not any(mask[lo:hi].any() for lo, hi in core.runs()):
                kept.add(id(core))
                continue
            req = core.reset_request(**given, mask=mask)
            calls.append(
                (core, req, None if core.index in given_up else core.conn.future("Reset", req))
            )
        if self.failover_on() and len(endpoint.live()) > 1:
            waiting = [(c.index, _ready(f)) for c, _, f in calls if f is not None]
            await_replies(waiting, endpoint, self.settings.failover_after, time.monotonic())
        lost = []
        for core, req, future in calls:
            try:
                if future is None:
                    lost.append(core)  # its server was given up at a step: it moves now
                else:
                    core.reset(req, future)
            except ServerLost:
                lost.append(core)
        if lost:
            self.cores = fail_over(self.cores, lost, start)
        self.last_finish = time.monotonic()  # the time between steps, for a drain's margin
        return kept

    def close(self) -> None:
        if self.membership is not None:
            self.membership.close()
            self.membership = None
        for core in self.cores:
            core.close()
        self.endpoint.close()

    def pieces(self) -> list[tuple[int, int, SessionCore]]:
        """``(start, stop, core)``: which core holds which environments, in environment order."""
        out = [(lo, hi, c) for c in self.cores for lo, hi in c.runs()]
        out.sort(key=lambda p: p[0])
        return out

    def batches(self) -> list[Batch]:
        """The cores' last Batches cut to the environments each holds, in environment order."""
        cores = self.cores
        if all(c.owned is None for c in cores):
            return [c.last for c in cores]
        return [
            c.last if c.owned is None else c.last.slice(lo - c.start, hi - c.start)
            for lo, hi, c in self.pieces()
        ]

    def refused(self, dest: int, error: ServiceError) -> None:
        """Server ``dest`` could not take environments moving to it: one that drains is marked
        so, one that does not answer is given up (no step of the env would notice: it holds
        none of its environments), one that refuses otherwise (full) is not asked for a while."""
        if isinstance(error, ServerDraining):
            self.endpoint.drain(dest, None)
        elif isinstance(error, (ServiceTransportError, ServiceTimeout)):
            self.endpoint.give_up(dest, f"could not open a session there: {error}")
        else:
            self.resting[dest] = time.monotonic() + REST

    def targets(self) -> list[int]:
        """The servers environments may move to now: open to new sessions, and not resting
        after refusing one."""
        now = time.monotonic()
        for j in [j for j, until in self.resting.items() if until <= now]:
            del self.resting[j]
        return [j for j in self.endpoint.open_to_new() if j not in self.resting]

    def quick(self) -> float:
        """The deadline of the calls that move environments between servers: a server that
        does not answer within ``failover_after`` is passed over (the env's watch gives it up
        at the next step), not waited for the whole ``timeout``."""
        return min(self.options.timeout, self.settings.failover_after)

    def failover_on(self) -> bool:
        return self.settings.reconnect and self.settings.failover_after is not None

    def take_in(self) -> None:
        """The servers the membership thread found: given-up ones that answer again are taken
        back, new replicas added (no more servers than environments)."""
        if self.membership is None:
            return
        endpoint = self.endpoint
        for index, conn in self.membership.found():
            if index is not None and index in endpoint.given_up:
                endpoint.take_back(index, conn)
            elif index is None and conn.address not in endpoint.addresses:
                if len(endpoint.live()) < self.num_envs:
                    endpoint.add(conn)
                else:
                    conn.close()
            else:
                conn.close()

    def settle(self) -> None:
        """After a step: notes which servers drain, then moves environments between servers at
        their own episode ends (:func:`~dinerdash._membership.boundary`): off draining servers,
        and from the most loaded servers onto the least loaded until the loads differ by at
        most one. A move is a transfer (:meth:`plan_moves`): a session on the new server for a
        contiguous run of environments, each of which enters it at its episode end
        (:meth:`enter`). The environments of a server whose drain deadline is about to pass
        move at once, their episodes cut (truncated, ``info["reconnected"]``). Not in DISABLED
        mode, where the caller resets finished environments: they move at a full reset."""
        endpoint = self.endpoint
        now = time.monotonic()
        interval, self.last_finish = now - self.last_finish, now
        if self.shape() == self.quiet and not any(
            c.drain_ms or c.source is not None for c in self.cores
        ):
            return  # nothing changed and nothing under way: the common step
        for core in self.cores:
            if core.drain_ms > 0:
                endpoint.drain(core.index, core.drain_ms / 1000)
        if self.settings.autoreset_mode == AutoresetMode.DISABLED:
            return
        # NEXT_STEP: the environments whose episode ended at the last step autoreset here.
        for new in [c for c in self.cores if c.entering]:
            self.enter(new, new.take_entering())
        for core in self.cores:
            if core.index in endpoint.draining:
                core.mark_draining()  # no more environments go to it
        targets = self.targets()
        # Planning is asked again only when the servers or the sessions changed.
        key = (len(self.cores), tuple(targets), tuple(endpoint.draining), tuple(endpoint.given_up))
        if targets and key != self.planned:
            self.plan_moves(targets)
            self.planned = key
        # A drain deadline closer than a few steps (and two seconds): move now, cut.
        margin = max(2.0, 3 * interval)
        late = {i for i, t in endpoint.draining.items() if t - now < margin}
        for new in [c for c in self.cores if c.source is not None]:
            source = new.source
            ended = boundary(source.last, self.settings.autoreset_mode)
            due = [
                i
                for i in range(new.start, new.stop)
                if source.holds(i) and ended[i - source.start] and not new.holds(i)
            ]
            if self.settings.autoreset_mode == AutoresetMode.NEXT_STEP:
                new.await_entry(due)
            elif due:
                self.enter(new, due)
        for core in [c for c in self.cores if c.index in late and c.load]:
            targets = [j for j in self.targets() if j != core.index]
            for lo, hi in core.runs():
                for i in range(lo, hi):
                    if targets and i not in self.entering():
                        dest = min(targets, key=lambda j: (self.load(j), j))
                        self.hand_over(core, i, dest, cut=True)
        self.tidy()
        for i in list(endpoint.draining):
            if not any(c.index == i for c in self.cores):
                endpoint.give_up(i)  # drained: probed, and taken back once it serves again
        settled = not (endpoint.draining or self.resting) and all(
            c.source is None for c in self.cores
        )
        self.quiet = self.shape() if settled else None

    def shape(self) -> tuple:
        """The sessions and servers as :meth:`settle` compares them from one step to the next:
        a step whose shape is the last quiet one's has nothing to settle."""
        endpoint = self.endpoint
        return (len(self.cores), len(endpoint.connections), tuple(endpoint.given_up))

    def entering(self) -> set[int]:
        return {i for c in self.cores for i in c.entering}

    def load(self, server: int) -> int:
        """Environments server ``server`` holds, or will once its transfers are done."""
        load = 0
        for c in self.cores:
            if c.index == server:
                load += c.load
            if c.source is not None:
                pending = sum(c.source.holds(i) and not c.holds(i) for i in range(c.start, c.stop))
                load += pending if c.index == server else 0
                load -= pending if c.source.index == server else 0
        return load

    def plan_moves(self, targets: list[int]) -> None:
        """Opens the transfers that, once done, leave no environment on a draining server and
        loads that differ by at most one (:func:`dinerdash._placement.plan`, from a view of the
        sessions): each a session on a server of ``targets`` for a run of another server's
        environments. A destination that refuses stops the balancing (the next planning sees
        why); a draining server's other pieces are still tried."""
        endpoint = self.endpoint
        cores = list(self.cores)
        covered = {
            i
            for c in cores
            if c.source is not None
            for i in range(c.start, c.stop)
            if c.source.holds(i)
        }
        views = [
            SessionView(
                key=k,
                server=c.index,
                runs=tuple((lo, hi) for a, b in c.runs() for lo, hi in _uncovered(a, b, covered)),
                load=c.load,
                busy=c.source is not None,
            )
            for k, c in enumerate(cores)
        ]
        servers = {c.index for c in cores} | set(targets)
        loads = {j: self.load(j) for j in servers}
        draining = set(endpoint.draining)
        for move in plan(views, loads, targets, draining):
            if not self.transfer(cores[move.source], move.start, move.stop, move.dest):
                if move.origin not in draining:
                    return

    def session_on(self, dest: int, lo: int, hi: int) -> tuple[SessionCore, Batch] | None:
        """A new session on server ``dest`` for environments ``lo:hi``, created and reset
        (unseeded: the new server draws the episodes' seeds, as an autoreset does), with its
        first Batch; None when ``dest`` cannot take it now (it drains, is full or unreachable:
        :meth:`refused` notes why)."""
        new = SessionCore(self.endpoint, dest, lo, hi, self.settings)
        try:
            new.create(self.quick())
            first = Batch.from_pb(
                new.conn.call(
                    "Reset", pb.ResetRequest(session_id=new.session_id), timeout=self.quick()
                )
            )
        except ServiceError as e:
            new.close()
            self.refused(dest, e)
            return None
        except BaseException:
            new.close()
            raise
        return new, first

    def transfer(self, source: SessionCore, lo: int, hi: int, dest: int) -> bool:
        """Opens a session on server ``dest`` for environments ``lo:hi`` of ``source``, each to
        enter it at its episode end; until then its slots are stepped, their results unused.
        False when ``dest`` cannot take it now (it drains, is full or unreachable)."""
        opened = self.session_on(dest, lo, hi)
        if opened is None:
            return False
        new, first = opened
        new.begin_receiving(source, first)
        self.cores.append(new)
        self.cores.sort(key=lambda c: c.start)
        return True

    def enter(self, new: SessionCore, envs: list[int]) -> None:
        """Environments ``envs`` of ``new.source`` enter ``new`` at their episode end: their
        slots are reset (unseeded: the new server draws the seeds, as an autoreset does) and
        their report of this step is the new episode's start (NEXT_STEP: this step is their
        autoreset; SAME_STEP: the ended episode's outcome and ``final_*`` from the old server)."""
        envs = [i for i in envs if new.source.holds(i)]
        if not envs:
            return
        mask = np.zeros(new.size, dtype=np.bool_)
        mask[[i - new.start for i in envs]] = True
        request = pb.ResetRequest(session_id=new.session_id, reset_mask=mask.tobytes())
        try:
            reply = new.conn.call("Reset", request, timeout=self.quick())
            first = new.note(Batch.from_pb(reply))
        except ServiceError:
            return  # its server is going: the transfer is dropped at the next failover
        batch = new.last.splice(first, mask)
        if self.settings.autoreset_mode == AutoresetMode.SAME_STEP:
            old = new.source.last.slice(new.start - new.source.start, new.stop - new.source.start)
            batch = batch.splice(old, mask, OUTCOME + FINAL)
        else:
            batch = batch.splice(Batch(new.size, {}), mask, OUTCOME)
        ones = Batch(new.size, {"reset": np.ones(new.size, np.bool_)})
        batch = batch.splice(ones, mask, ("reset",))
        new.enter(envs, batch)
        self.moves += len(envs)

    def tidy(self) -> None:
        """Closes the sessions whose environments have all moved, and ends the transfers that
        are done or whose source is gone (a failover)."""
        for core in list(self.cores):
            if core.source is not None and (
                core.owned is None  # every environment entered
                or core.source not in self.cores
                or not any(core.source.holds(i) for i in range(core.start, core.stop))
            ):
                core.finish_transfer()
            if core.load == 0 and core.source is None:
                core.close()
                self.cores.remove(core)
        self.cores.sort(key=lambda c: c.start)  # what _batches' common case relies on

    def complete_transfers(self) -> None:
        """A full reset starts every episode: the transfers in progress are done at once."""
        for new in [c for c in self.cores if c.source is not None]:
            new.complete_transfer()
        self.tidy()

    def hand_over(self, core: SessionCore, i: int, dest: int, cut: bool) -> bool:
        """Environment ``i`` of ``core`` moves to a new session on server ``dest`` (created
        and reset now; unseeded: the new server draws the episode's seed, as an autoreset
        does): its Batch of this step becomes the new core's (:func:`handover`). False when
        ``dest`` cannot take it now (it drains, is full or unreachable): it stays, for now."""
        opened = self.session_on(dest, i, i + 1)
        if opened is None:
            return False
        new, first = opened
        ended = core.last.slice(i - core.start, i - core.start + 1)
        last, pending = handover(ended, first, self.settings.autoreset_mode, cut)
        new.take_over(last, pending, cut)
        core.disown(i, i + 1)
        self.cores.append(new)
        self.cores.sort(key=lambda c: c.start)
        self.moves += 1
        return True


def _ready(future: grpc.Future):
    """``ready(deadline)`` of a grpc future: True once it has its outcome."""

    def ready(deadline: float | None) -> bool:
        timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        try:
            future.exception(timeout=timeout)
        except grpc.FutureTimeoutError:
            return False
        except grpc.FutureCancelledError:
            pass
        return True

    return ready


def _uncovered(lo: int, hi: int, covered: set[int]) -> list[tuple[int, int]]:
    """The contiguous runs of ``lo:hi`` outside ``covered``."""
    out, start = [], None
    for i in range(lo, hi + 1):
        free = i < hi and i not in covered
        if free and start is None:
            start = i
        elif not free and start is not None:
            out.append((start, i))
            start = None
    return out


def interrupted(old: SessionCore, new: SessionCore) -> Batch:
    """A moved core's Batch for the step in which its server was given up: its environments'
    episodes end truncated in their last state (``old.last``), and the new session's first
    Batch (an unseeded Reset: the new server draws each episode's seed) is the autoreset, as
    after a reconnect."""
    first = Batch.from_pb(new.conn.call("Reset", pb.ResetRequest(session_id=new.session_id)))
    last = old.last.slice(new.start - old.start, new.stop - old.start)
    return new.interrupt(last, first)
