"""The session core: environments ``start:stop`` of an env in one batched session on one server
and everything both environments do with it (create, reset, step, the transport, the step thread,
and with ``reconnect=True`` the lost server waited for); and :class:`SessionOwner`, what the two
environments share. A core's state (:data:`tests.test_module_graph.SESSION_STATE`) is changed
only by its own methods; a move between servers makes new cores. Why: docs/clusters.md#failover.
"""

from __future__ import annotations

import queue
import threading
import time
import weakref
from dataclasses import dataclass
from types import MethodType
from typing import Any

import grpc
import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from . import _shm
from . import render as _render
from ._arguments import check_render_mode, expert_fields
from ._batch import Batch, interrupt
from ._endpoint import Endpoint
from ._proto import pb
from .connection import Connection, ConnectOptions
from .errors import (
    EnvClosed,
    InvalidArgument,
    NoServerLeft,
    ServiceError,
    ServiceTransportError,
    SessionNotFound,
)
from .game import NUM_ACTIONS

#: Gymnasium's autoreset modes as the protocol's (``AUTORESET_MODE_NEXT_STEP``, ...).
_WIRE_AUTORESET = {m: pb.AutoresetMode.Value(f"AUTORESET_MODE_{m.name}") for m in AutoresetMode}
_U64 = 1 << 64
#: The unsigned dtype of each integer width, for :func:`check_actions`.
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
    #: Several cores: errors name the environments by their index in the whole env.
    split: bool = False


class ServerLost(Exception):
    """A core's server was lost past ``failover_after`` (or given up) while the env has others:
    its environments move (:meth:`dinerdash._fleet.Fleet.fail_over`)."""

    def __init__(self, core: SessionCore, error: ServiceError) -> None:
        super().__init__(
            f"gave up {core.conn.address} (environments {core.start}..{core.stop - 1}): {error}"
        )
        self.core = core
        self.error = error


def check_actions(actions: Any, num_envs: int) -> np.ndarray:
    """``actions`` as ``num_envs`` little-endian int32, each checked before any server steps."""
    acts = np.asarray(actions)
    if acts.shape != (num_envs,):
        raise ValueError(f"actions: expected shape ({num_envs},), got {acts.shape}")
    if acts.dtype.kind in "iu":  # as unsigned, a negative action is huge: one comparison
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
    """Closes a session, once and briefly (errors ignored: nothing is left to free)."""
    try:
        request = pb.CloseSessionRequest(session_id=session_id)
        conn.call("CloseSession", request, timeout=2.0, retries=0)
    except ServiceError:
        pass


class SessionOwner:
    """What :class:`~dinerdash.DinerDashEnv` and :class:`~dinerdash.DinerDashVectorEnv` share: their
    arguments, :class:`Endpoint`, cores (``_cores``, in environment order), what is read of them."""

    _endpoint: Endpoint
    _cores: list[SessionCore]
    _closed: bool
    spec_proto: pb.Spec
    #: A vector env: ``render()`` returns a tuple of frames, one per environment.
    _batched = False

    def _check_open(self, what: str) -> None:
        if self._closed:
            again = "new sessions" if self._batched else "a new session"
            raise EnvClosed(f"{what} after close(); reset() opens {again}")

    def _check_idle(self, what: str) -> None:
        """Raises while a vector env's ``step_async()`` awaits its ``step_wait()``."""

    def _shown(self) -> tuple[Any, Any, Any]:
        """The observations, scores and lost groups of the current states, for ``render()``."""
        raise NotImplementedError

    def render(self) -> Any:
        """The current state: the server's text board (``"ansi"``) or a picture (``"rgb_array"``); a
        vector env returns a tuple, one per environment. Without a ``render_mode``: ``None``."""
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='ansi' or 'rgb_array'"
            )
            return None
        self._check_idle("render()")
        self._check_open("render()")
        if self.render_mode == "ansi":
            frames = [
                core.render_text(i - core.start, self.ansi_color)
                for core in self._cores
                for i in range(core.start, core.stop)
            ]
        else:
            lives = self.spec_proto.config.lives
            frames = [
                _render.draw(obs, score=int(score), lost=int(lost), lives=lives)
                for obs, score, lost in zip(*self._shown(), strict=True)
            ]
        return tuple(frames) if self._batched else frames[0]

    @property
    def transports(self) -> dict[str, str]:
        """The transport each server's sessions step over now: ``{address: "shm" | "grpc"}``
        (``"shm,grpc"`` where they differ), in the order of their first environments."""
        out: dict[str, dict[str, None]] = {}
        for core in self._cores:
            out.setdefault(core.conn.address, {})[getattr(core.transport, "name", "grpc")] = None
        return {address: ",".join(names) for address, names in out.items()}

    @property
    def transport_changes(self) -> int:
        """Sessions whose Steps changed transport (shared memory lost, or taken up again)."""
        return self._endpoint.transport_changes

    def watch_url(self, index: int = 0) -> str:
        """The URL of the server's web page that shows environment ``index`` playing (the
        server must serve pages: ``--http-port``); see :mod:`dinerdash.watch`."""
        from .watch import watch_url

        self._check_open("watch_url()")
        num_envs = self._cores[-1].stop
        if not 0 <= index < num_envs:
            raise IndexError(f"index must be in 0..{num_envs - 1}, got {index}")
        core = next(c for c in self._cores if c.start <= index < c.stop)
        return watch_url(core.conn, core.session_id, index - core.start)

    def _take_arguments(
        self,
        num_envs: int,
        autoreset_mode: AutoresetMode,
        address: Any,
        expert: bool | str,
        render_mode: str | None,
        ansi_color: bool,
        connect: ConnectOptions | None,
        connection: dict[str, Any],
    ) -> Settings:
        """Checks and keeps the arguments both envs take; returns their cores' :class:`Settings`."""
        self.render_mode = check_render_mode(render_mode)
        self.expert, expert_policy = expert_fields(expert)
        self._options = options = ConnectOptions.merged(
            connect, type(self).__name__, address=address, **connection
        )
        self.reconnect = options.reconnect
        self.reconnect_timeout = options.reconnect_timeout
        self.ansi_color = ansi_color
        return Settings(num_envs, autoreset_mode, expert=self.expert, expert_policy=expert_policy)

    @property
    def server(self):
        """The :class:`~dinerdash.server.LocalServer` this env started, or ``None``."""
        return self._endpoint.server

    @property
    def game_config(self) -> dict[str, int]:
        """The effective game configuration, every field present."""
        config = self.spec_proto.config
        return {
            f.name: getattr(config, f.name)
            for f in config.DESCRIPTOR.fields
            if config.HasField(f.name)
        }


class SessionCore:
    """Environments ``start:stop`` of an env, in one session on server ``index`` of its
    :class:`~dinerdash._endpoint.Endpoint`."""

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
        #: The last Batch received (over shared memory: views valid until the next Step).
        self.last: Batch | None = None
        #: NEXT_STEP after a reconnect: the new session's first Batch, the next step's autoreset.
        self.pending: Batch | None = None
        #: The server was lost and the session reopened (or episodes cut) during this step.
        self.reconnected = False
        #: The thread that makes the Steps of :meth:`start_step` over gRPC, from the first one.
        self.step_thread: StepThread | None = None
        #: The actions of a Step sent over shared memory whose reply :meth:`finish_step` awaits.
        self.shm_sent: bytes | None = None
        #: The server's ``drain_remaining_ms`` in its last Batch (0: not draining).
        self.drain_ms = 0
        #: What the session's reply offered of shared memory, and the transport its Steps take
        #: (``None`` until the first Step of a session forked or restored).
        self.offer: _shm.Offer | None = None
        self.transport: _shm.Transport | None = None
        #: The transport of the session's last Steps, kept across a reopened session.
        self.last_transport: str | None = None

    @property
    def conn(self) -> Connection:
        return self.endpoint.connections[self.index]

    def given_up(self) -> bool:
        return self.index in self.endpoint.given_up

    def movable(self) -> bool:
        """Its environments may move now: reset, and no step cut by a failover still to report."""
        return self.last is not None and self.pending is None and not self.reconnected

    def start_after(self, lost: SessionCore, given: dict | None) -> None:
        """This new core's session (created) takes over environments of ``lost``'s (its server given
        up): reset with ``given`` (a reset's keywords), or at a step cut as by a lost server's."""
        if given is not None:
            self.last = Batch.from_pb(self.conn.call("Reset", self.reset_request(**given)))
        else:
            self.interrupt(lost.last.slice(self.start - lost.start, self.stop - lost.start))

    def take_reconnected(self) -> bool:
        """Whether the session was reopened (or episodes cut) in the step just reported; once."""
        reconnected, self.reconnected = self.reconnected, False
        return reconnected

    def create(self, timeout: float | None = None) -> pb.Spec:
        """Opens the session (not reset yet) and returns the server's Spec."""
        s = self.settings
        request = pb.CreateSessionRequest(
            num_envs=self.stop - self.start,
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

    def adopt(self, reply: pb.CreateSessionResponse, last: Batch | None = None) -> None:
        """Makes the session of ``reply`` (CreateSession's, Fork's or Restore's) this core's;
        ``last``: a Restore's, the moved environments' report of the step just made."""
        self.detach()
        self.session_id = reply.session_id
        self.last, self.pending = last, None
        self.offer = _shm.Offer.of(reply)

    def attach(self) -> None:
        """Chooses the session's transport (:func:`dinerdash._shm.open_for`)."""
        self.detach()
        option = self.endpoint.options.transport
        # gRPC if the choice raises (``transport="shm"`` that cannot be had): said, not silent.
        self.transport = _shm.GrpcTransport(self.conn, str(self.session_id))
        self.transport = transport = _shm.open_for(self.offer, self.conn, option)
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
        """The session's Steps go over ``name`` from now on: a change is an endpoint's event."""
        if self.last_transport is not None and self.last_transport != name:
            self.endpoint.transport_changed(
                self.conn.address, str(self.session_id), self.last_transport, name, why
            )
        self.last_transport = name

    def reopen(self, error: ServiceError) -> None:
        """Waits for the lost server and opens a new session there (``reconnect=True``), for
        ``failover_after`` when another server is left (then :class:`ServerLost`), else for
        ``reconnect_timeout`` (then the error, or ``NoServerLeft`` after a failover)."""
        endpoint, options = self.endpoint, self.endpoint.options
        if self.index in endpoint.given_up:
            raise ServerLost(self, error)
        what = f"environments {self.start}..{self.stop - 1}"
        lost = f"{what if self.settings.num_envs > 1 else 'the session'} ({error})"
        failover = options.failover_after is not None and len(endpoint.connections) > 1
        others = failover and len(endpoint.live()) > 1
        try:
            wait = options.failover_after if others else options.reconnect_timeout
            endpoint.reopen(self.index, self.create, lost, wait)
        except ServiceTransportError as e:
            if others:
                raise ServerLost(self, error) from None
            if not failover:
                raise
            before = ", ".join(endpoint.addresses[i] for i in endpoint.given_up)
            raise NoServerLeft(
                f"no server left: {e.details}; the env's other servers were given up before "
                f"({before}), each after failover_after={options.failover_after:g} s",
                code=e.code,
                address=e.address,
            ) from None

    def close(self) -> None:
        """Closes the session (its server not called if given up)."""
        self.shm_sent = None
        self.detach()
        if self.step_thread is not None:
            self.step_thread.close()
            self.step_thread = None
        if self.session_id is not None and not self.given_up():
            close_session(self.conn, self.session_id)
        self.session_id = None

    def fail(self, error: ServiceError) -> ServiceError:
        """``error`` naming its environments' indices in the whole env when it is split over
        servers, and, for a lost server without ``reconnect=True``, what would ride it out."""
        lost = isinstance(error, LOST) and not self.endpoint.options.reconnect
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

    def reset_request(
        self,
        *,
        seed: int | None = None,
        seeds: list[int] | None = None,
        arrivals: list[pb.ArrivalList] | None = None,
        config: pb.GameConfig | None = None,
        mask: np.ndarray | None = None,
    ) -> pb.ResetRequest:
        """This core's part of a reset of the whole env: environment ``i`` seeded ``seed + i`` (or
        ``seeds[i]``), given ``arrivals[i]`` (or the one list), reset if ``mask[i]`` (or all)."""
        r = pb.ResetRequest(session_id=self.session_id, config=config)
        if mask is not None:
            r.reset_mask = mask[self.start : self.stop].astype(np.uint8).tobytes()
        if seeds is not None:
            r.seeds.extend(seeds[self.start : self.stop])
        elif seed is not None:
            r.seed = (int(seed) + self.start) % _U64
        if arrivals and len(arrivals) > 1 and self.settings.split:
            arrivals = arrivals[self.start : self.stop]  # one list per environment
        r.arrivals.extend(arrivals or ())
        return r

    def reset(self, request: pb.ResetRequest, future: grpc.Future | None = None) -> Batch:
        """The reply to ``request`` (started as ``future``, or called now); after a lost server
        (``reconnect=True``) the new session is reset whole."""
        try:
            if future is None:
                batch = Batch.from_pb(self.conn.call("Reset", request))
            else:
                batch = Batch.from_pb(self.conn.result("Reset", request, future))
        except ServiceError as e:
            # A call cancelled because its server was given up (silent) is lost too.
            if not self.endpoint.options.reconnect or not (isinstance(e, LOST) or self.given_up()):
                raise self.fail(e) from None
            self.reopen(e)
            request.session_id = self.session_id
            request.ClearField("reset_mask")
            batch = Batch.from_pb(self.conn.call("Reset", request))
        self.last, self.pending, self.drain_ms = batch, None, batch.drain_ms
        return batch

    def step(self, actions: bytes, sent: bool = False) -> Batch:
        """One Step of this core's environments (``actions``: packed int32), blocking (``sent``:
        its reply only, :meth:`start_step` sent it). Shared memory lost changes to gRPC; a lost
        server (``reconnect=True``) a new session, its episodes truncated (:meth:`interrupt`)."""
        if self.pending is not None and not sent:
            batch, self.pending = self.pending, None
        else:
            try:
                if not sent and self.given_up():  # another session found the server lost
                    raise ServiceTransportError(
                        "the server was given up", address=self.conn.address
                    )
                try:
                    batch = (
                        self.transport.receive() if sent else self.ready_transport().step(actions)
                    )
                except _shm.Detached as gone:
                    self.detach()
                    self.transport = _shm.GrpcTransport(self.conn, self.session_id)
                    self.changed("grpc", str(gone))
                    if gone.error is not None:
                        raise gone.error from None
                    batch = self.transport.step(actions)
                self.drain_ms = batch.drain_ms
            except ServiceError as e:
                # A call cancelled because its server was given up (silent) is lost too.
                lost = isinstance(e, LOST) or self.given_up()
                if not (lost and self.endpoint.options.reconnect and self.last is not None):
                    raise self.fail(e) from None
                last = self.last
                self.reopen(e)
                batch = self.interrupt(last)
        self.last = batch
        return batch

    def ready_transport(self) -> _shm.Transport:
        """The session's transport, attached at its first Step; the last Batch copied when the
        next Step overwrites it and a lost server's episodes may end in it."""
        if self.transport is None:
            self.attach()
        if self.transport.views and self.last is not None and self.endpoint.options.reconnect:
            self.last = self.last.copy()
        return self.transport

    def start_step(self, actions: bytes) -> None:
        """Starts a Step (over shared memory sent here, else by the step thread);
        :meth:`finish_step` returns its Batch."""
        if (
            self.pending is None
            and self.transport is not None
            and self.transport.views
            and not self.given_up()
            and self.ready_transport().send(actions)
        ):
            self.shm_sent = actions
            return
        if self.step_thread is None:
            self.step_thread = StepThread(self.step, f"dinerdash-step-{self.index}")
        self.step_thread.submit(actions)

    def step_ready(self, deadline: float | None = None) -> bool:
        """Whether the Step :meth:`start_step` began has its outcome by ``deadline``
        (:func:`time.monotonic`; ``None``: waits for it)."""
        if self.shm_sent is not None:
            timeout = None if deadline is None else deadline - time.monotonic()
            return self.transport.ready(timeout)
        return self.step_thread.wait(deadline)

    def finish_step(self) -> Batch:
        """The Batch of the Step begun by :meth:`start_step`, once it has arrived."""
        if self.shm_sent is not None:
            actions, self.shm_sent = self.shm_sent, None
            return self.step(actions, sent=True)
        return self.step_thread.result()

    def interrupt(self, last: Batch, ends=interrupt, timeout: float | None = None) -> Batch:
        """Ends this core's episodes (``last``: their last report) as ``ends`` says (a lost session:
        :func:`~dinerdash._batch.interrupt`; a refused Restore: :func:`~dinerdash._batch.cut`) and
        starts its new session's by an unseeded Reset: their Batch, kept as :attr:`last`."""
        request = pb.ResetRequest(session_id=self.session_id)
        first = Batch.from_pb(self.conn.call("Reset", request, timeout=timeout))
        self.last, self.pending = ends(last, first, self.settings.autoreset_mode)
        self.reconnected = True
        return self.last

    def render_text(self, env_index: int, color: bool) -> str:
        request = pb.RenderRequest(session_id=self.session_id, env_index=env_index, color=color)
        try:
            return self.conn.call("Render", request).text
        except ServiceError as e:
            raise self.fail(e) from None


class StepThread:
    """A thread that makes one session core's blocking gRPC Steps, for ``step_async`` /
    ``step_wait`` (why not a grpcio future: docs/client.md#design-notes). It ends at
    :meth:`close`, or when the core whose method the work is is collected (held weakly)."""

    def __init__(self, work: MethodType, name: str) -> None:
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._replies: queue.SimpleQueue = queue.SimpleQueue()
        self._reply: tuple[bool, Any] | None = None
        threading.Thread(
            target=_serve,
            args=(weakref.WeakMethod(work), self._requests, self._replies),
            name=name,
            daemon=True,
        ).start()
        weakref.finalize(work.__self__, self._requests.put, None)
        self.submit = self._requests.put

    def wait(self, deadline: float | None = None) -> bool:
        """True when the reply is in by ``deadline`` (``None``: waits for it); it is then kept for
        :meth:`result`. An interrupted wait (Ctrl-C) loses nothing: the reply stays queued."""
        if self._reply is None:
            timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                self._reply = self._replies.get(timeout=timeout)
            except queue.Empty:
                return False
        return True

    def result(self) -> Any:
        """The work's return value for the oldest submitted item, or its exception raised."""
        ok, value = self._reply if self._reply is not None else self._replies.get()
        self._reply = None
        if ok:
            return value
        raise value

    def close(self) -> None:
        self._requests.put(None)


def _serve(work: weakref.WeakMethod, requests: queue.SimpleQueue, replies: queue.SimpleQueue):
    while (item := requests.get()) is not None:
        method = work()
        if method is None:
            return
        try:
            replies.put((True, method(item)))
        except BaseException as e:
            replies.put((False, e))
        del method
