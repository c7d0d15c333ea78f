"""The session core: environments ``start:stop`` of an env, held in one batched session on one
server, and everything both environments do with such a session; and :class:`SessionOwner`, what
the two environments share (their endpoint and the server's Spec).

It creates the session, chooses its transport (:mod:`dinerdash._transport`; a change is an event),
resets and steps it (blocking, or handed to its :mod:`step thread <dinerdash._step_thread>` and
collected later), checks actions, and, with ``reconnect=True``, waits for a lost server and reopens
the session there; or, when the env has other servers and the lost one stays away past
``failover_after``, raises :class:`ServerLost` (a private signal) for the env to move the core's
environments (:mod:`dinerdash._failover`). :class:`~dinerdash.DinerDashEnv` is one core of one
environment; :class:`~dinerdash.DinerDashVectorEnv` is one core per server. Errors are the server's
typed errors; a core of a vector env that is split over several servers reports an environment by
its index in the vector env (from the error's structured ``env_index``).

A core's state (``last``, ``pending``, ``reconnected``, the session's ``session_id``, ``spec``,
``offer``, ``transport``...) is changed only by its own methods, never assigned by another module
(``tests/test_module_graph.py`` reads every module with :mod:`ast` to check it: its
``SESSION_STATE``). A core never changes its range of environments: a move between servers
(:mod:`dinerdash._fleet`) makes new cores of restored sessions (:meth:`SessionCore.restored`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import grpc
import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from . import _shm, _transport
from ._arguments import check_render_mode, config_dict, expert_fields
from ._batch import Batch, interrupt
from ._endpoint import Endpoint
from ._proto import pb
from ._step_thread import Caller
from .connection import Connection, ConnectOptions
from .errors import (
    InvalidArgument,
    NoServerLeft,
    ServiceError,
    ServiceTransportError,
    SessionNotFound,
)
from .game import NUM_ACTIONS

_WIRE_AUTORESET = {
    AutoresetMode.NEXT_STEP: pb.AUTORESET_MODE_NEXT_STEP,
    AutoresetMode.SAME_STEP: pb.AUTORESET_MODE_SAME_STEP,
    AutoresetMode.DISABLED: pb.AUTORESET_MODE_DISABLED,
}
_U64 = 1 << 64
#: The unsigned dtype of each integer width, for :func:`check_actions` (a dtype parsed from its
#: name every step costs three times the view).
_UNSIGNED = {width: np.dtype(f"u{width}") for width in (1, 2, 4, 8)}
#: The errors after which ``reconnect=True`` waits for the server and opens a new session.
LOST = (ServiceTransportError, SessionNotFound)


@dataclass
class Settings:
    """What every core of one env shares; the env changes ``config`` on a reset with a config."""

    num_envs: int
    autoreset_mode: AutoresetMode
    config: pb.GameConfig | None = None
    expert: bool = False
    #: Which expert fills ``expert_action`` (``pb.POLICY_EXPERT`` or ``pb.POLICY_PLANNER``).
    expert_policy: int = pb.POLICY_EXPERT
    reconnect: bool = False
    reconnect_timeout: float = 60.0
    #: Seconds a lost server is waited for before its environments move to the servers left
    #: (``reconnect=True``, several servers); ``None``: it is waited for ``reconnect_timeout``.
    failover_after: float | None = None
    #: Several cores: errors name the environments by their index in the whole env.
    split: bool = field(default=False)


class ServerLost(Exception):
    """Raised by a core whose server stayed unreachable past ``failover_after`` (or was given
    up already) while the env has other servers: the env moves the core's environments to them
    (:func:`dinerdash._failover.move`) and never lets this escape. A private signal, not one of
    the public errors: no ``except ServiceError`` of a caller can mistake it for a failure."""

    def __init__(self, core: SessionCore, error: ServiceError) -> None:
        super().__init__(
            f"gave up {core.conn.address} (environments {core.start}..{core.stop - 1}): {error}"
        )
        self.core = core
        self.error = error


def check_actions(actions: Any, num_envs: int) -> np.ndarray:
    """``actions`` as ``num_envs`` little-endian int32, every one checked against the game's
    actions before any server steps: int32 casting would wrap 2**32 + 1 into action 1, and over
    several servers a step refused by one would have moved the others."""
    acts = np.asarray(actions)
    if acts.shape != (num_envs,):
        raise ValueError(f"actions: expected shape ({num_envs},), got {acts.shape}")
    if acts.dtype.kind in "iu":
        # One pass: viewed as unsigned, a negative action is huge, so one comparison finds both
        # ends (two thirds of min() and max()'s time).
        bad = np.count_nonzero(acts.view(_UNSIGNED[acts.itemsize]) >= NUM_ACTIONS) > 0
    else:
        bad = num_envs > 0 and (acts.min() < 0 or acts.max() >= NUM_ACTIONS)
    if bad:
        i = int(np.flatnonzero((acts < 0) | (acts >= NUM_ACTIONS))[0])
        raise InvalidArgument(
            f"actions[{i}] must be in 0..={NUM_ACTIONS - 1}, got {acts[i]}",
            reason="ACTION_OUT_OF_RANGE",
            field=f"actions[{i}]",
            env_index=i,
        )
    return acts.astype("<i4", copy=False)


def close_session(conn: Connection, session_id: str) -> None:
    """Closes a session, once and briefly: a server that is gone or already forgot the session
    has nothing left to free."""
    try:
        request = pb.CloseSessionRequest(session_id=session_id)
        conn.call("CloseSession", request, timeout=2.0, retries=0)
    except ServiceError:
        pass


class SessionOwner:
    """What :class:`~dinerdash.DinerDashEnv` and :class:`~dinerdash.DinerDashVectorEnv` share:
    the :class:`Endpoint` they opened and the server's ``Spec`` of their session."""

    _endpoint: Endpoint
    spec_proto: pb.Spec

    def _renders(self) -> bool:
        """Whether ``render()`` draws: with no ``render_mode`` it warns (as Gymnasium's envs do)
        and returns ``None``."""
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='ansi' or 'rgb_array'"
            )
            return False
        return True

    def _take_arguments(
        self,
        address: Any,
        expert: bool | str,
        render_mode: str | None,
        ansi_color: bool,
        connect: ConnectOptions | None,
        connection: dict[str, Any],
    ) -> None:
        """Checks and keeps the constructor's arguments both envs take: ``render_mode``,
        ``expert``, ``ansi_color`` and the merged :class:`ConnectOptions` (errors in the name of
        the env's class, as Python's own)."""
        self.render_mode = check_render_mode(render_mode)
        expert_request = expert_fields(expert)
        self.expert = expert_request["expert_actions"]
        self._expert_policy = expert_request["expert_policy"]
        self._options = options = ConnectOptions.merged(
            connect, type(self).__name__, address=address, **connection
        )
        self.reconnect = options.reconnect
        self.reconnect_timeout = options.reconnect_timeout
        self.ansi_color = ansi_color

    def _settings_for(self, **settings: Any) -> Settings:
        """The :class:`Settings` of the env's cores: the arguments :meth:`_take_arguments` kept
        and ``settings`` (``num_envs``, ``autoreset_mode``, ``config``, ``failover_after``)."""
        return Settings(
            expert=self.expert,
            expert_policy=self._expert_policy,
            reconnect=self.reconnect,
            reconnect_timeout=self.reconnect_timeout,
            **settings,
        )

    @property
    def server(self):
        """The :class:`~dinerdash.server.LocalServer` this env started, or ``None``."""
        return self._endpoint.server

    @property
    def game_config(self) -> dict[str, int]:
        """The effective game configuration, every field present."""
        return config_dict(self.spec_proto.config)


class SessionCore:
    """Environments ``start:stop`` of an env, in one session on server ``index`` of its
    :class:`~dinerdash._endpoint.Endpoint`."""

    __slots__ = (
        "__weakref__",
        "caller",
        "drain_ms",
        "endpoint",
        "index",
        "last",
        "offer",
        "pending",
        "reconnected",
        "rung",
        "session_id",
        "settings",
        "spec",
        "start",
        "stop",
        "transport",
        "was",
    )

    def __init__(
        self, endpoint: Endpoint, index: int, start: int, stop: int, settings: Settings
    ) -> None:
        self.endpoint = endpoint
        self.index = index
        self.start = start
        self.stop = stop
        self.settings = settings
        #: The session on the server, ``None`` before :meth:`create` and after :meth:`close`.
        self.session_id: str | None = None
        self.spec: pb.Spec | None = None
        #: The last Batch received, kept for render(), action_masks() and a lost server (over
        #: shared memory, views of the region: valid until the next Step is sent).
        self.last: Batch | None = None
        #: NEXT_STEP after a reconnect: the new session's first Batch, handed out at the next
        #: step as that step's autoreset (Gymnasium's NEXT_STEP semantics).
        self.pending: Batch | None = None
        #: The server was lost and the session reopened during the current step.
        self.reconnected = False
        #: The thread that makes the Step calls of ``start_step``, started at the first one.
        self.caller: Caller | None = None
        #: The actions of a Step :meth:`start_step` rang for over shared memory, until
        #: :meth:`finish_step` collects its reply.
        self.rung: bytes | None = None
        #: The server's ``drain_remaining_ms`` in the last Batch it sent (0: not draining).
        self.drain_ms = 0
        #: What the reply that made the session offered of shared memory, and the transport its
        #: Steps take (``None`` until the first Step of a session forked or restored).
        self.offer: _shm.Offer | None = None
        self.transport: _transport.Transport | None = None
        #: The transport of the session's last Steps (kept across a reopened session): a
        #: change is an event (:meth:`Endpoint.transport_changed`).
        self.was: str | None = None

    @property
    def conn(self) -> Connection:
        return self.endpoint.connections[self.index]

    @property
    def size(self) -> int:
        """The environments this core holds."""
        return self.stop - self.start

    def given_up(self) -> bool:
        return self.index in self.endpoint.given_up

    def note(self, batch: Batch) -> Batch:
        """Records what a Batch from the server says of the server (draining)."""
        self.drain_ms = batch.drain_ms
        return batch

    # -- what the env reports -------------------------------------------------------------------

    def start_with(self, batch: Batch) -> None:
        """``batch`` is what the env reports for the environments of this new session (moved
        here by a failover, :mod:`dinerdash._failover`) at this step."""
        self.last = batch

    def restored(self, reply: pb.CreateSessionResponse, last: Batch) -> None:
        """This new core's session is ``reply``'s (Restore's: the environments moved here by
        Snapshot and Restore, exactly as they were); ``last`` is their report of the step just
        made."""
        self.adopt(reply)
        self.last = last

    def cut_over(self, last: Batch, pending: Batch | None) -> None:
        """This new core's session (created and reset) took over environments whose episodes
        were cut (a Restore refused, :func:`~dinerdash._batch.cut`): ``last`` is their report
        of the step just made, ``pending`` (NEXT_STEP) the next step's; ``info["reconnected"]``
        will say so."""
        self.last, self.pending, self.reconnected = last, pending, True

    def take_reconnected(self) -> bool:
        """Whether the server was lost and the session reopened (or an episode cut) during the
        step just reported; reported once."""
        was, self.reconnected = self.reconnected, False
        return was

    # -- the session ----------------------------------------------------------------------------

    def create(self, timeout: float | None = None) -> pb.Spec:
        """Opens the session (not reset yet) and returns the server's Spec; ``timeout``: the
        call's deadline, else the connection's."""
        s = self.settings
        request = pb.CreateSessionRequest(
            num_envs=self.size,
            config=s.config,
            autoreset_mode=_WIRE_AUTORESET[s.autoreset_mode],
            action_masks=True,
            expert_actions=s.expert,
            expert_policy=s.expert_policy,
        )
        try:
            reply = self.conn.call("CreateSession", request, timeout=timeout)
        except ServiceError as e:
            raise self.fail(e) from None
        self.adopt(reply)
        self.attach()
        return reply.spec

    def adopt(self, reply: pb.CreateSessionResponse) -> None:
        """Makes the session of ``reply`` (CreateSession's, Fork's or Restore's) this core's,
        with what it offers of shared memory."""
        self.detach()
        self.session_id, self.spec = reply.session_id, reply.spec
        self.last = self.pending = None
        self.offer = _shm.Offer.of(reply)

    def attach(self) -> None:
        """Chooses the session's transport (:func:`dinerdash._transport.open_for`): shared
        memory when the ``transport`` option allows it and it opens, else gRPC."""
        self.detach()
        option = self.endpoint.options.transport
        # gRPC if the choice raises (``transport="shm"`` that cannot be had): said, not silent.
        self.transport = _transport.GrpcTransport(self.conn, str(self.session_id))
        self.transport = transport = _transport.open_for(self.offer, self.conn, option)
        why = "the session was reopened on a server that offers it shared memory"
        if transport.name == "grpc":
            why = "the reopened session could not attach shared memory (see the debug log)"
        self.changed(transport.name, why)

    def detach(self) -> None:
        """Closes the session's transport (its session closed or replaced)."""
        transport, self.transport = self.transport, None
        if transport is not None:
            if transport.views and self.last is not None:
                self.last = self.last.copy()  # kept (a failover reads it), not the region's
            transport.close()

    def changed(self, name: str, why: str) -> None:
        """The session's Steps go over ``name`` from now on: an event of the endpoint."""
        if self.was is not None and self.was != name:
            self.endpoint.transport_changed(
                self.conn.address, str(self.session_id), self.was, name, why
            )
        self.was = name

    def reopen(self, error: ServiceError) -> None:
        """Waits for the lost server and opens a new session there (``reconnect=True``).

        With ``failover_after`` and another server left, the server is waited for that long
        only, and then (or at once, when it was given up already) :class:`ServerLost` is raised
        for the env to move these environments. The last server left is waited for
        ``reconnect_timeout``, as without failover; if it does not come back,
        :class:`~dinerdash.errors.NoServerLeft` is raised."""

        def create(conn: Connection) -> None:
            self.create()

        endpoint, s = self.endpoint, self.settings
        if self.index in endpoint.given_up:
            raise ServerLost(self, error)
        lost = (
            f"environments {self.start}..{self.stop - 1} ({error})"
            if s.split or s.num_envs > 1
            else f"the session ({error})"
        )
        failover = s.failover_after is not None and len(endpoint.connections) > 1
        if failover and len(endpoint.live()) > 1:
            try:
                endpoint.reopen(self.index, create, lost, s.failover_after)
            except ServiceTransportError:
                raise ServerLost(self, error) from None
            return
        try:
            endpoint.reopen(self.index, create, lost, s.reconnect_timeout)
        except ServiceTransportError as e:
            if not failover:
                raise
            before = ", ".join(endpoint.addresses[i] for i in endpoint.given_up)
            raise NoServerLeft(
                f"no server left: {e.details}; the env's other servers were given up before "
                f"({before}), each after failover_after={s.failover_after:g} s",
                code=e.code,
                address=e.address,
            ) from None

    def close(self) -> None:
        """Closes the session (its server not called if given up)."""
        self.rung = None
        self.detach()
        if self.caller is not None:
            self.caller.close()
            self.caller = None
        if self.session_id is not None:
            if self.index not in self.endpoint.given_up:  # a server given up is not called
                close_session(self.conn, self.session_id)
            self.session_id = None

    def fail(self, error: ServiceError) -> ServiceError:
        """``error``, saying which environments it concerns when the env is split over several
        servers (its ``env_index`` becomes the index in the whole env), and, for a lost server
        without ``reconnect=True``, what would have ridden it out."""
        lost = isinstance(error, LOST) and not self.settings.reconnect
        if not (self.settings.split or lost):
            return error
        env_index = error.env_index
        where = ""
        if self.settings.split and env_index is not None:
            where = (
                f" [the server's environment {env_index} is environment {env_index + self.start}"
                f" of the vector env, whose environments {self.start}..{self.stop - 1} it holds]"
            )
            env_index += self.start
        elif self.settings.split:
            where = f" [environments {self.start}..{self.stop - 1} of the vector env]"
        if lost:
            where += (
                "; reconnect=True would wait for the server and go on with new episodes "
                "(truncated), and a vector env given several addresses would move its "
                "environments to the others"
            )
        return type(error)(
            error.details + where,
            code=error.code,
            address=error.address,
            reason=error.reason,
            field=error.field,
            env_index=env_index,
            metadata=error.metadata,
        )

    # -- Reset ----------------------------------------------------------------------------------

    def reset_request(
        self,
        *,
        seed: int | None = None,
        seeds: list[int] | None = None,
        arrivals: list[pb.ArrivalList] | None = None,
        config: pb.GameConfig | None = None,
        mask: np.ndarray | None = None,
    ) -> pb.ResetRequest:
        """This core's part of a reset of the whole env: environment ``i`` of the env is seeded
        with ``seed + i`` (or ``seeds[i]``), gets ``arrivals[i]`` when there is one list per
        environment (else the one list), and is reset when ``mask[i]`` (else all are)."""
        r = pb.ResetRequest(session_id=self.session_id, config=config)
        if mask is not None:
            r.reset_mask = mask[self.start : self.stop].astype(np.uint8).tobytes()
        if seeds is not None:
            r.seeds.extend(seeds[self.start : self.stop])
        elif seed is not None:
            r.seed = (int(seed) + self.start) % _U64
        if arrivals:
            if len(arrivals) == 1 or not self.settings.split:
                r.arrivals.extend(arrivals)
            else:
                r.arrivals.extend(arrivals[self.start : self.stop])
        return r

    def reset(self, request: pb.ResetRequest, future: grpc.Future | None = None) -> Batch:
        """The reply to ``request`` (started as ``future``, or called now). After a lost server
        (``reconnect=True``) the new session is reset whole, as a new session must be."""
        try:
            if future is None:
                batch = Batch.from_pb(self.conn.call("Reset", request))
            else:
                batch = Batch.from_pb(self.conn.result("Reset", request, future))
        except ServiceError as e:
            # A call cancelled because its server was given up (silent) is lost too.
            if not self.settings.reconnect or not (isinstance(e, LOST) or self.given_up()):
                raise self.fail(e) from None
            self.reopen(e)
            request.session_id = self.session_id
            request.ClearField("reset_mask")
            batch = Batch.from_pb(self.conn.call("Reset", request))
        self.last, self.pending = self.note(batch), None
        return batch

    # -- Step -----------------------------------------------------------------------------------

    def step(self, actions: bytes, rung: bool = False) -> Batch:
        """One Step of this core's environments (their ``actions`` as packed int32), blocking;
        ``rung``: :meth:`start_step` already sent it over shared memory (the checks below were
        made then), only its reply is awaited."""
        if rung:
            batch = self.step_or_recover(actions, rung)
        elif self.pending is not None:
            batch, self.pending = self.pending, None
        elif self.index in self.endpoint.given_up:
            # Another session on this server found it lost: this one moves too.
            gone = ServiceTransportError("the server was given up", address=self.conn.address)
            batch = self.recover_step(gone)
        else:
            batch = self.step_or_recover(actions)
        self.last = batch
        return batch

    def step_or_recover(self, actions: bytes, rung: bool = False) -> Batch:
        """The Batch of a Step on the session's transport; a lost server (``reconnect=True``)
        recovered from (:meth:`recover_step`), any other error raised."""
        try:
            return self.note(self.step_on(actions, rung))
        except ServiceError as e:
            # A call cancelled because its server was given up (silent) is lost too.
            if not (isinstance(e, LOST) or self.given_up()):
                raise self.fail(e) from None
            return self.recover_step(e)

    def ready_transport(self) -> _transport.Transport:
        """The session's transport, attached if it has none yet (a session forked or restored is
        attached at its first Step); its last Batch copied first when the next Step overwrites
        it and a lost server's episodes may have to end in their last state."""
        if self.transport is None:
            self.attach()
        if self.transport.views and self.last is not None and self.settings.reconnect:
            self.last = self.last.copy()
        return self.transport

    def step_on(self, actions: bytes, rung: bool = False) -> Batch:
        """One Step on the session's transport (``rung``: its reply only, the Step was sent by
        :meth:`start_step`); shared memory lost under it (:class:`Detached
        <dinerdash._transport.Detached>`) changes to gRPC (an event), where the Step is made
        unless it was abandoned (its error raised)."""
        try:
            if rung:
                return self.transport.receive()
            return self.ready_transport().step(actions)
        except _transport.Detached as gone:
            self.detach()
            self.transport = _transport.GrpcTransport(self.conn, self.session_id)
            self.changed("grpc", gone.reason)
            if gone.error is not None:
                raise gone.error from None
            return self.transport.step(actions)

    def start_step(self, actions: bytes) -> None:
        """Starts a Step and returns at once; :meth:`finish_step` returns its Batch (or raises
        its error). Over shared memory the Step is rung for here, with no thread (the server
        steps while the caller works); otherwise it is handed to this core's :class:`Caller`
        thread."""
        if (
            self.pending is None
            and self.transport is not None
            and self.transport.split
            and not self.given_up()
            and self.ready_transport().send(actions)
        ):
            self.rung = actions
            return
        if self.caller is None:
            self.caller = Caller(self.step, f"dinerdash-step-{self.index}")
        self.caller.submit(actions)

    def in_flight(self) -> bool:
        """A Step started by :meth:`start_step` awaits :meth:`finish_step`."""
        return self.rung is not None or self.caller is not None

    def step_ready(self, deadline: float | None = None) -> bool:
        """True when the Step begun by :meth:`start_step` has its outcome by ``deadline``
        (a :func:`time.monotonic` time; ``None``: waits for it)."""
        if self.rung is not None:
            timeout = None if deadline is None else deadline - time.monotonic()
            return self.transport.ready(timeout)
        return self.caller.wait(deadline)

    def finish_step(self) -> Batch:
        """The Batch of the Step begun by :meth:`start_step`, once it has arrived."""
        if self.rung is not None:
            actions, self.rung = self.rung, None
            return self.step(actions, rung=True)
        return self.caller.result()

    def recover_step(self, error: ServiceError) -> Batch:
        """A Batch that reports the interrupted episodes as truncated, after opening a new
        session for them (``reconnect=True``); raises ``error`` otherwise."""
        if not self.settings.reconnect or self.last is None:
            raise self.fail(error) from None
        last = self.last
        self.reopen(error)
        first = Batch.from_pb(self.conn.call("Reset", pb.ResetRequest(session_id=self.session_id)))
        return self.interrupt(last, first)

    def interrupt(self, last: Batch, first: Batch) -> Batch:
        """The Batch of a step that interrupts this core's episodes, whose ``last`` Batch came
        from a lost session, and starts the new session's, whose Reset replied ``first``
        (:func:`~dinerdash._batch.interrupt`); ``info["reconnected"]`` will say so."""
        out, self.pending = interrupt(last, first, self.settings.autoreset_mode)
        self.reconnected = True
        return out

    # -- the rest -------------------------------------------------------------------------------

    def render_text(self, env_index: int, color: bool) -> str:
        request = pb.RenderRequest(session_id=self.session_id, env_index=env_index, color=color)
        try:
            return self.conn.call("Render", request).text
        except ServiceError as e:
            raise self.fail(e) from None
