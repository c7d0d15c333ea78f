"""The vector environment: N Diner Dash games in one batched server session per server.

``gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=N, ...)`` builds this class (the
registered ``vector_entry_point``). Each step is one ``Step`` call per server carrying N actions as
packed little-endian ``int32``; the reply's packed arrays are turned into numpy arrays with
``numpy.frombuffer``, with no Python loop over the environments.

Scale-out: ``address`` may be a list of servers (or a DNS name that resolves to several). The N
environments are then split into contiguous slices, one batched session per server, and the
servers are called concurrently (each server's Step by a thread of the env). Environment ``i`` is
seeded with ``seed + i`` whatever server holds it, so the trajectories are the same as on one
server. A session's calls always go to the server that created it.

Failover (``reconnect=True``): a server unreachable, or silent, for more than ``failover_after``
seconds is given up and its environments move to the servers left (:mod:`dinerdash._failover`);
they keep their indices, and the other servers' sessions are not touched. Membership
(:mod:`dinerdash._membership`): a given-up server that answers again, or a DNS name's new
replica, is taken in, and environments move onto it at their own episode ends until the loads
differ by at most one; a draining server's environments move off it at their episode ends.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from typing import Any

import grpc
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import AlreadyPendingCallError, NoAsyncCallError
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import render as _render
from ._arguments import (
    RENDER_MODES,
    Config,
    check_options,
    check_render_mode,
    expert_fields,
    make_arrivals,
    make_config,
)
from ._batch import FINAL, OUTCOME, Batch, boundary, decode, handover, join
from ._endpoint import Endpoint
from ._failover import fail_over
from ._membership import Membership, await_replies, has_name
from ._placement import SessionView, plan
from ._proto import pb
from ._session import (
    ServerLost,
    SessionCore,
    SessionOwner,
    Settings,
    check_actions,
)
from .connection import ConnectOptions
from .errors import (
    EnvClosed,
    InvalidArgument,
    ServerDraining,
    ServiceError,
    ServiceTimeout,
    ServiceTransportError,
)
from .game import observation_space

__all__ = ["DinerDashVectorEnv"]

#: Seconds a server that refused a session for moving environments (full) is not asked again.
REST = 10.0


class DinerDashVectorEnv(SessionOwner, VectorEnv):
    """``num_envs`` Diner Dash environments stepped together on one or more DinerDash servers.

    The single environment, its spaces and infos are described in
    :class:`dinerdash.env.DinerDashEnv`; here every value gains a leading axis of ``num_envs``:
    observations ``(N, 40) float32``, rewards ``(N,) float64``, ``info["action_mask"]`` ``(N, 57)
    bool``, ``info["score"]``, ``info["lost"]``, ``info["tick"]`` and (``expert=True``)
    ``info["expert_action"]`` of shape ``(N,)``, each with its Gymnasium ``_key`` mask; and
    ``info["seed"]``, each environment's episode seed, at reset and at every step (the keys never
    change, as for a ``SyncVectorEnv`` of :class:`~dinerdash.DinerDashEnv`; ``int64`` as there,
    a seed given above 2**63 - 1 reading modulo 2**64).

    Autoreset: ``AutoresetMode.NEXT_STEP`` (default; the step after an episode ends resets that
    environment, ignores its action and reports reward 0 and ``info["seed"]``) or
    ``AutoresetMode.SAME_STEP`` (the ending step returns the new episode's first observation and
    puts the ended one's last observation in ``info["final_obs"]`` and its infos in
    ``info["final_info"]``) or ``AutoresetMode.DISABLED`` (stepping a finished environment raises
    :class:`~dinerdash.errors.FailedPrecondition`; reset it with ``options={"reset_mask": ...}``).
    ``metadata["autoreset_mode"]`` says which.

    Args:
        num_envs: number of environments N.
        address: a server, a list of servers, or a DNS name resolving to several; with several,
            the environments are split into contiguous slices, one per server (at most N servers).
            Default: ``DINERDASH_ADDRESS``, else a local server is started and stopped on close.
        expert: add ``expert_action`` to the infos: ``True`` the reference heuristic's choices,
            ``"planner"`` the look-ahead planner's.
        reconnect: when a server is lost, wait for it (``reconnect_timeout`` seconds), recreate
            its session and report its environments' episodes as truncated.
        failover_after: with ``reconnect=True`` and several servers: seconds a lost server is
            waited for, or a server that answers nothing (hung, black-holed) is borne with,
            before it is given up and its environments move to the servers left (new sessions,
            spread evenly; their episodes end truncated with ``info["reconnected"]``, as after a
            reconnect). The last server left is waited for ``reconnect_timeout``, then
            :class:`~dinerdash.errors.NoServerLeft` is raised. ``None``: no failover. A given-up
            server that answers again is taken back.
        resolve_every: with failover, seconds between resolutions of a DNS-name ``address``;
            new replicas are taken in. ``None``: never.
        autoreset_mode: ``AutoresetMode.NEXT_STEP``, ``SAME_STEP`` or ``DISABLED``.
        config: game configuration (GameConfig fields), as for the single env.
        max_episode_steps: shorthand for ``config["time_limit"]`` (the server truncates).
        render_mode: ``"ansi"`` or ``"rgb_array"``; ``render()`` returns one frame per env.
        timeout, tls, tls_ca: every call's deadline and TLS, as for the single env.
        token, connect_timeout, reconnect_timeout, server_binary, ansi_color: as for the single env.
        connect: a :class:`~dinerdash.ConnectOptions` holding the connection keywords (address,
            token, timeout, TLS, reconnect, failover_after, ...) as one value; a keyword given
            beside it overrides its field.

    Reset: ``reset(seed=s)`` seeds environment ``i`` with ``s + i``; ``seed`` may also be a list
    of N seeds. Options: ``{"arrivals": one list of (type, size) pairs or N lists,
    "config": {...}, "reset_mask": (N,) bool array}``. With a ``reset_mask`` (any autoreset mode,
    as in Gymnasium) only those environments are reset, environment ``i`` still with ``s + i``;
    the others keep their episode, and the observations and infos returned are their current ones
    (``info["_seed"]`` is the mask of environments reset). A ``config`` needs a full reset.

    Pipelining: :meth:`step_async` sends a step and returns at once, :meth:`step_wait` returns
    its results (Gymnasium's ``AsyncVectorEnv`` names; ``step()`` is the two in a row). A trainer
    that alternates two vector envs keeps one step on the wire while it works on the other.

    :meth:`action_masks` gives the ``(N, 57)`` masks of the current states. Errors that concern
    one environment carry its index in this vector env as ``env_index``. ``close()`` frees the
    sessions; a later full ``reset()`` opens new ones.
    """

    #: Until ``__init__`` has opened the sessions: an env whose arguments were refused has nothing
    #: to close when it is collected (gymnasium's ``__del__`` closes every vector env).
    _closed = True

    def __init__(
        self,
        num_envs: int = 1,
        address: str | Sequence[str] | None = None,
        *,
        expert: bool | str = False,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        config: Config = None,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        ansi_color: bool = False,
        connect: ConnectOptions | None = None,
        **connection: Any,
    ) -> None:
        mode = AutoresetMode(autoreset_mode)
        self.metadata = {
            "render_modes": list(RENDER_MODES),
            "render_fps": 8,
            "autoreset_mode": mode,
        }
        self.autoreset_mode = mode
        self.render_mode = check_render_mode(render_mode)
        self.num_envs = int(num_envs)
        expert_request = expert_fields(expert)
        self.expert = expert_request["expert_actions"]
        self._options = ConnectOptions.merged(
            connect, "DinerDashVectorEnv", address=address, **connection
        )
        self._membership: Membership | None = None
        #: Environments moved to another server at their episode end (before a close()).
        self._moves = 0
        #: Servers that refused a session of moving environments (full): until when they rest.
        self._resting: dict[int, float] = {}
        #: What the last planning saw, and the servers and sessions of the last step after
        #: which nothing was under way (:meth:`_settle`).
        self._planned: tuple = ()
        self._quiet: tuple | None = None
        self.reconnect = self._options.reconnect
        self.reconnect_timeout = self._options.reconnect_timeout
        self.failover_after = self._options.failover_after
        self.ansi_color = ansi_color
        config = make_config(config)
        if max_episode_steps is not None:
            cfg = pb.GameConfig()
            if config is not None:
                cfg.CopyFrom(config)
            cfg.time_limit = int(max_episode_steps)
            config = cfg
        self._settings = Settings(
            num_envs=self.num_envs,
            autoreset_mode=mode,
            config=config,
            expert=self.expert,
            expert_policy=expert_request["expert_policy"],
            reconnect=self.reconnect,
            reconnect_timeout=self.reconnect_timeout,
            failover_after=self.failover_after,
        )
        self._open()
        spec = self.spec_proto
        self.single_observation_space = observation_space(spec)
        self.single_action_space = spaces.Discrete(spec.num_actions)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    # -- sessions -------------------------------------------------------------------------------

    def _open(self) -> None:
        """Connects and creates one session per server (at construction, and at a reset after
        close): the environments split into contiguous slices, one per server."""
        self._endpoint = Endpoint(self._options, max_servers=max(1, self.num_envs))
        self._moves = 0
        self._last_finish = time.monotonic()
        k = len(self._endpoint.connections)
        self._settings.split = k > 1
        sizes = [self.num_envs // k + (j < self.num_envs % k) for j in range(k)]
        self._cores: list[SessionCore] = []
        start = 0
        for j, size in enumerate(sizes):
            self._cores.append(SessionCore(self._endpoint, j, start, start + size, self._settings))
            start += size
        try:
            for core in self._cores:
                self.spec_proto: pb.Spec = core.create()
        except BaseException:
            self._close_sessions()
            self._endpoint.close()
            raise
        # Membership for several servers, or a DNS name that may come to name several.
        if self._failover_on() and self._endpoint.server is None:
            if len(self._endpoint.connections) > 1 or has_name(self._options.address):
                self._membership = Membership(self._endpoint, self._options)
        #: A step_async() was sent and step_wait() has not collected it yet.
        self._pending = False
        self._seeds = np.zeros(self.num_envs, np.int64)  # each environment's episode seed
        self._closed = False
        self.closed = False  # Gymnasium's flag: close() calls close_extras only when False

    @property
    def addresses(self) -> list[str]:
        """The servers serving now, in the order of the first environments they hold (after a
        failover a server may hold several slices; the servers given up are left out)."""
        return list(dict.fromkeys(c.conn.address for _, _, c in self._pieces()))

    @property
    def lost_addresses(self) -> list[str]:
        """The servers given up (``reconnect=True``: unreachable or silent past
        ``failover_after``, or drained), in the order they were lost; one that answers its
        health check again is taken back and leaves this list."""
        return [self._endpoint.addresses[i] for i in self._endpoint.given_up]

    @property
    def failovers(self) -> int:
        """Servers given up for a failure since the env's sessions were opened."""
        return self._endpoint.failovers

    @property
    def rejoins(self) -> int:
        """Servers taken in since the env's sessions were opened: given-up ones that answered
        again, and a DNS name's new replicas."""
        return self._endpoint.rejoins

    @property
    def transports(self) -> dict[str, str]:
        """The transport each server's session steps over now (``{address: "shm" | "grpc"}``,
        in the order of the first environments they hold; ``"shm,grpc"`` for a server whose
        sessions differ). A change is logged as a warning and counted in
        :attr:`transport_changes`: nothing falls back to gRPC silently."""
        out: dict[str, list[str]] = {}
        for _, _, core in self._pieces():
            name = core.transport.name if core.transport is not None else "grpc"
            names = out.setdefault(core.conn.address, [])
            if name not in names:
                names.append(name)
        return {address: ",".join(names) for address, names in out.items()}

    @property
    def transport_changes(self) -> int:
        """Sessions whose Steps changed transport since the env's sessions were opened (shared
        memory lost, or taken up again by a session reopened after a reconnect)."""
        return self._endpoint.transport_changes

    @property
    def moves(self) -> int:
        """Environments moved to another server at their episode end (onto a server taken in,
        or off a draining one), or, a draining server's deadline about to pass, cut."""
        return self._moves

    @property
    def env_slices(self) -> list[tuple[str, slice]]:
        """Which server holds which environments: one entry per contiguous run of a session's
        environments, in environment order (after a failover a server holds several)."""
        return [(c.conn.address, slice(lo, hi)) for lo, hi, c in self._pieces()]

    def _pieces(self) -> list[tuple[int, int, SessionCore]]:
        """``(start, stop, core)``: which core holds which environments, in environment order."""
        out = [(lo, hi, c) for c in self._cores for lo, hi in c.runs()]
        out.sort(key=lambda p: p[0])
        return out

    def _batches(self) -> list[Batch]:
        """The cores' last Batches cut to the environments each holds, in environment order."""
        cores = self._cores
        if all(c.owned is None for c in cores):
            return [c.last for c in cores]
        return [
            c.last if c.owned is None else c.last.slice(lo - c.start, hi - c.start)
            for lo, hi, c in self._pieces()
        ]

    def _refused(self, dest: int, error: ServiceError) -> None:
        """Server ``dest`` could not take environments moving to it: one that drains is marked
        so, one that does not answer is given up (no step of the env would notice: it holds
        none of its environments), one that refuses otherwise (full) is not asked for a while."""
        if isinstance(error, ServerDraining):
            self._endpoint.drain(dest, None)
        elif isinstance(error, (ServiceTransportError, ServiceTimeout)):
            self._endpoint.give_up(dest, f"could not open a session there: {error}")
        else:
            self._resting[dest] = time.monotonic() + REST

    def _targets(self) -> list[int]:
        """The servers environments may move to now: open to new sessions, and not resting
        after refusing one."""
        now = time.monotonic()
        for j in [j for j, until in self._resting.items() if until <= now]:
            del self._resting[j]
        return [j for j in self._endpoint.open_to_new() if j not in self._resting]

    def _quick(self) -> float:
        """The deadline of the calls that move environments between servers: a server that
        does not answer within ``failover_after`` is passed over (the env's watch gives it up
        at the next step), not waited for the whole ``timeout``."""
        return min(self._options.timeout, self.failover_after)

    def _failover_on(self) -> bool:
        return self.reconnect and self.failover_after is not None

    @property
    def session_ids(self) -> list[str | None]:
        return [c.session_id for c in self._cores]

    def watch_url(self, index: int = 0) -> str:
        """The URL of the server's web page that shows environment ``index`` playing (the
        server must serve pages: ``--http-port``); see :mod:`dinerdash.watch`."""
        from .watch import watch_url

        self._check_open("watch_url()")
        if not 0 <= index < self.num_envs:
            raise IndexError(f"index must be in 0..{self.num_envs - 1}, got {index}")
        core = next(c for lo, hi, c in self._pieces() if lo <= index < hi)
        return watch_url(core.conn, core.session_id, index - core.start)

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise EnvClosed(f"{what} after close(); reset() opens new sessions")

    # -- Gymnasium API --------------------------------------------------------------------------

    def reset(
        self,
        *,
        seed: int | Sequence[int] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        seed_list = None
        if seed is None or isinstance(seed, (int, np.integer)):
            super().reset(seed=None if seed is None else int(seed))
        else:
            seed_list = [int(s) for s in seed]
            if len(seed_list) != self.num_envs:
                raise ValueError(
                    f"seed: expected an int or {self.num_envs} seeds, got {len(seed_list)}"
                )
        options = check_options(options, ("arrivals", "config", "reset_mask"))
        self._check_idle("reset()")
        if self._closed:
            if options.get("reset_mask") is not None:
                raise EnvClosed("a reset_mask after close(): the new sessions need a full reset")
            self._open()  # reuse after close: new sessions (and a new local server if needed)
        mask = self._reset_mask(options.get("reset_mask"), options.get("config"))
        arrivals = make_arrivals(options.get("arrivals"), self.num_envs)
        if len(self._cores) > 1 and len(arrivals) not in (0, 1, self.num_envs):
            raise InvalidArgument(
                f"arrivals: expected one list or {self.num_envs} lists (one per environment), "
                f"got {len(arrivals)}"
            )
        config = make_config(options.get("config"))
        if config is not None:
            self._settings.config = config

        # A core with none of its environments in the mask is not called: it keeps its state.
        given = {
            "seed": None if seed is None or seed_list is not None else int(seed),
            "seeds": seed_list,
            "arrivals": arrivals,
            "config": config,
        }
        given_up, endpoint = self._endpoint.given_up, self._endpoint
        self._take_in()

        # The moved environments' new sessions are reset whole, as after a reconnect.
        def start(old: SessionCore, new: SessionCore) -> Batch:
            return Batch.from_pb(new.conn.call("Reset", new.reset_request(**given)))

        for core in self._cores:
            core.entering = set()
        if mask is None:
            self._complete_transfers()
        if mask is None and self._failover_on():
            # A full reset ends every episode: the environments of a draining server move now.
            drained = [c for c in self._cores if c.index in endpoint.draining]
            if drained:
                self._moves += sum(c.load for c in drained)
                self._cores = fail_over(self._cores, drained, start, why=None)
        calls, kept = [], set()
        for core in self._cores:
            if mask is not None and not any(mask[lo:hi].any() for lo, hi in core.runs()):
                kept.add(id(core))
                continue
            req = core.reset_request(**given, mask=mask)
            calls.append(
                (core, req, None if core.index in given_up else core.conn.future("Reset", req))
            )
        if self._failover_on() and len(endpoint.live()) > 1:
            waiting = [(c.index, _ready(f)) for c, _, f in calls if f is not None]
            await_replies(waiting, endpoint, self.failover_after, time.monotonic())
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
            self._cores = fail_over(self._cores, lost, start)
        batch = join(self._batches())
        obs, info = decode(batch, self.expert)
        info["seed"] = batch["seeds"].astype(np.int64)  # as SyncVectorEnv; torch has no uint64
        reset = batch["reset"].copy()
        for lo, hi, c in self._pieces():
            if id(c) in kept:
                reset[lo:hi] = False
        info["_seed"] = reset
        self._seeds = np.where(info["_seed"], info["seed"], self._seeds)
        self._last_finish = time.monotonic()  # the time between steps, for a drain's margin
        return obs, info

    def _reset_mask(self, reset_mask: Any, config: Any) -> np.ndarray | None:
        """The ``reset_mask`` option checked as Gymnasium's vector envs check it, or ``None``."""
        if reset_mask is None:
            return None
        if not isinstance(reset_mask, np.ndarray):
            raise TypeError(
                f"options['reset_mask'] must be a numpy array, got {type(reset_mask).__name__}"
            )
        if reset_mask.shape != (self.num_envs,) or reset_mask.dtype != np.bool_:
            raise ValueError(
                f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), got "
                f"{reset_mask.dtype} {reset_mask.shape}"
            )
        if not reset_mask.any():
            raise ValueError("options['reset_mask'] selects no environment")
        if config is not None:
            raise ValueError(
                "options['config'] applies to every environment: give it with a full reset, "
                "not a reset_mask"
            )
        for core in self._cores:
            if core.last is None and not reset_mask[core.start : core.stop].all():
                kept = core.start + int(np.flatnonzero(~reset_mask[core.start : core.stop])[0])
                raise ValueError(
                    f"environment {kept} has never been reset: include it in reset_mask"
                )
        return reset_mask

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every environment: :meth:`step_async` and :meth:`step_wait` in a row."""
        wire = check_actions(actions, self.num_envs)
        self._check_idle("step()")
        self._check_open("step()")
        cores = self._cores
        if len(cores) == 1 and not (self._failover_on() and len(self._endpoint.live()) > 1):
            # One blocking call: cheaper than a future (no hand-off to gRPC's completion thread).
            try:
                batches = [cores[0].step(wire.tobytes())]
            except ServerLost as e:
                self._cores = fail_over(cores, [e.core], _interrupted)
                batches = self._batches()
            if self._membership is not None:
                self._take_in()
                self._settle()
                batches = self._batches()
            return self._decode_step(batches)
        self._start(wire)
        return self._decode_step(self._finish())

    def step_async(self, actions: Any) -> None:
        """Sends this step's ``actions`` to the server(s) and returns at once; :meth:`step_wait`
        returns the step's results. Meanwhile the caller works (e.g. steps a second vector env),
        so that neither the server waits for the caller nor the caller for the network.

        The actions are checked here, before anything is sent, as :meth:`step` checks them.
        Another ``step_async``, a ``step()``, ``reset()``, ``render()`` or ``action_masks()``
        before the ``step_wait`` raises ``gymnasium.error.AlreadyPendingCallError``;
        ``close()`` drops the pending step (the server may or may not have applied it). Each
        server's calls are made by a thread of this env, started at the first ``step_async``."""
        wire = check_actions(actions, self.num_envs)
        self._check_idle("step_async()")
        self._check_open("step_async()")
        self._start(wire)

    def step_wait(
        self, timeout: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """The results of the step sent by :meth:`step_async`: exactly what :meth:`step` would
        have returned, errors, autoreset and ``reconnect=True`` included.

        Without a pending ``step_async`` it raises ``gymnasium.error.NoAsyncCallError``. With a
        ``timeout`` (seconds) and no reply by then it raises ``multiprocessing.TimeoutError`` and,
        unlike Gymnasium's ``AsyncVectorEnv``, the step stays pending: call ``step_wait`` again
        (its calls are in flight and each has the env's ``timeout=`` deadline)."""
        if not self._pending:
            raise NoAsyncCallError("step_wait() without a step_async() before it", "step")
        if timeout is not None:
            deadline = time.monotonic() + timeout
            if not all(core.step_ready(deadline) for core in self._cores if core.caller):
                raise multiprocessing.TimeoutError(
                    f"step_wait(): no reply within {timeout:g} s; the step is still "
                    "pending, call step_wait() again"
                )
        return self._decode_step(self._finish())

    def _check_idle(self, what: str) -> None:
        if self._pending:
            raise AlreadyPendingCallError(
                f"{what} while a step_async() awaits its step_wait(); call step_wait() first",
                "step",
            )

    def _start(self, wire: np.ndarray) -> None:
        """Every server's Step is sent (by its core's thread) before any reply is awaited: the
        servers work in parallel, and with the caller."""
        for core in self._cores:
            core.start_step(wire[core.start : core.stop].tobytes())
        self._pending = True
        self._sent = time.monotonic()

    def _finish(self) -> list[Batch]:
        """Every core's Batch of the pending step. Every reply is awaited (and every core
        updated) before the first error, if any, is raised: no server's step goes unrecorded. An
        interrupted wait (Ctrl-C) leaves the step pending, to be collected by ``step_wait()``.

        The environments of a core whose server was lost past ``failover_after`` move to the
        servers left first, and report this step as interrupted (:func:`_interrupted`). A server
        that answers nothing (the step nor a health check) for ``failover_after`` is given up
        first (:func:`~dinerdash._membership.await_replies`). Then the servers found are taken
        in and environments at their episode ends move (:meth:`_settle`)."""
        endpoint = self._endpoint
        if self._failover_on() and len(endpoint.live()) > 1:
            waiting = [(c.index, c.step_ready) for c in self._cores]
            await_replies(waiting, endpoint, self.failover_after, self._sent)
        else:
            for core in self._cores:
                core.step_ready()
        self._pending = False
        error, lost = None, []
        for core in self._cores:
            try:
                core.finish_step()  # its Batch is core.last
            except ServerLost as e:
                lost.append(e.core)
            except BaseException as e:
                if error is None:
                    error = e
        if lost:
            self._cores = fail_over(self._cores, lost, _interrupted)
        if error is not None:
            raise error
        if self._failover_on():
            self._take_in()
            self._settle()
        return self._batches()

    def _take_in(self) -> None:
        """The servers the membership thread found: given-up ones that answer again are taken
        back, new replicas added (no more servers than environments)."""
        if self._membership is None:
            return
        endpoint = self._endpoint
        for index, conn in self._membership.found():
            if index is not None and index in endpoint.given_up:
                endpoint.take_back(index, conn)
            elif index is None and conn.address not in endpoint.addresses:
                if len(endpoint.live()) < self.num_envs:
                    endpoint.add(conn)
                else:
                    conn.close()
            else:
                conn.close()

    def _settle(self) -> None:
        """After a step: notes which servers drain, then moves environments between servers at
        their own episode ends (:func:`~dinerdash._membership.boundary`): off draining servers,
        and from the most loaded servers onto the least loaded until the loads differ by at
        most one. A move is a transfer (:meth:`_plan`): a session on the new server for a
        contiguous run of environments, each of which enters it at its episode end
        (:meth:`_enter`). The environments of a server whose drain deadline is about to pass
        move at once, their episodes cut (truncated, ``info["reconnected"]``). Not in DISABLED
        mode, where the caller resets finished environments: they move at a full reset."""
        endpoint = self._endpoint
        now = time.monotonic()
        interval, self._last_finish = now - self._last_finish, now
        if self._shape() == self._quiet and not any(
            c.drain_ms or c.source is not None for c in self._cores
        ):
            return  # nothing changed and nothing under way: the common step
        for core in self._cores:
            if core.drain_ms > 0:
                endpoint.drain(core.index, core.drain_ms / 1000)
        if self.autoreset_mode == AutoresetMode.DISABLED:
            return
        # NEXT_STEP: the environments whose episode ended at the last step autoreset here.
        for new in [c for c in self._cores if c.entering]:
            self._enter(new, sorted(new.entering))
            new.entering = set()
        for new in self._cores:
            if new.source is not None and new.index in endpoint.draining:
                new.source, new.entering = None, set()  # no more environments go to it
        targets = self._targets()
        # Planning is asked again only when the servers or the sessions changed.
        key = (len(self._cores), tuple(targets), tuple(endpoint.draining), tuple(endpoint.given_up))
        if targets and key != self._planned:
            self._plan(targets)
            self._planned = key
        # A drain deadline closer than a few steps (and two seconds): move now, cut.
        margin = max(2.0, 3 * interval)
        late = {i for i, t in endpoint.draining.items() if t - now < margin}
        for new in [c for c in self._cores if c.source is not None]:
            source = new.source
            ended = boundary(source.last, self.autoreset_mode)
            due = [
                i
                for i in range(new.start, new.stop)
                if source.holds(i) and ended[i - source.start] and not new.holds(i)
            ]
            if self.autoreset_mode == AutoresetMode.NEXT_STEP:
                new.entering.update(due)
            elif due:
                self._enter(new, due)
        for core in [c for c in self._cores if c.index in late and c.load]:
            targets = [j for j in self._targets() if j != core.index]
            for lo, hi in core.runs():
                for i in range(lo, hi):
                    if targets and i not in self._entering():
                        dest = min(targets, key=lambda j: (self._load(j), j))
                        self._hand_over(core, i, dest, cut=True)
        self._tidy()
        for i in list(endpoint.draining):
            if not any(c.index == i for c in self._cores):
                endpoint.give_up(i)  # drained: probed, and taken back once it serves again
        settled = not (endpoint.draining or self._resting) and all(
            c.source is None for c in self._cores
        )
        self._quiet = self._shape() if settled else None

    def _shape(self) -> tuple:
        """The sessions and servers as :meth:`_settle` compares them from one step to the next:
        a step whose shape is the last quiet one's has nothing to settle."""
        endpoint = self._endpoint
        return (len(self._cores), len(endpoint.connections), tuple(endpoint.given_up))

    def _entering(self) -> set[int]:
        return {i for c in self._cores for i in c.entering}

    def _load(self, server: int) -> int:
        """Environments server ``server`` holds, or will once its transfers are done."""
        load = 0
        for c in self._cores:
            if c.index == server:
                load += c.load
            if c.source is not None:
                pending = sum(c.source.holds(i) and not c.holds(i) for i in range(c.start, c.stop))
                load += pending if c.index == server else 0
                load -= pending if c.source.index == server else 0
        return load

    def _plan(self, targets: list[int]) -> None:
        """Opens the transfers that, once done, leave no environment on a draining server and
        loads that differ by at most one (:func:`dinerdash._placement.plan`, from a view of the
        sessions): each a session on a server of ``targets`` for a run of another server's
        environments. A destination that refuses stops the balancing (the next planning sees
        why); a draining server's other pieces are still tried."""
        endpoint = self._endpoint
        cores = list(self._cores)
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
        loads = {j: self._load(j) for j in servers}
        draining = set(endpoint.draining)
        for move in plan(views, loads, targets, draining):
            if not self._transfer(cores[move.source], move.start, move.stop, move.dest):
                if move.origin not in draining:
                    return

    def _session_on(self, dest: int, lo: int, hi: int) -> tuple[SessionCore, Batch] | None:
        """A new session on server ``dest`` for environments ``lo:hi``, created and reset
        (unseeded: the new server draws the episodes' seeds, as an autoreset does), with its
        first Batch; None when ``dest`` cannot take it now (it drains, is full or unreachable:
        :meth:`_refused` notes why)."""
        new = SessionCore(self._endpoint, dest, lo, hi, self._settings)
        try:
            new.create(self._quick())
            first = Batch.from_pb(
                new.conn.call(
                    "Reset", pb.ResetRequest(session_id=new.session_id), timeout=self._quick()
                )
            )
        except ServiceError as e:
            new.close()
            self._refused(dest, e)
            return None
        except BaseException:
            new.close()
            raise
        return new, first

    def _transfer(self, source: SessionCore, lo: int, hi: int, dest: int) -> bool:
        """Opens a session on server ``dest`` for environments ``lo:hi`` of ``source``, each to
        enter it at its episode end; until then its slots are stepped, their results unused.
        False when ``dest`` cannot take it now (it drains, is full or unreachable)."""
        opened = self._session_on(dest, lo, hi)
        if opened is None:
            return False
        new, first = opened
        new.last = new.note(first)
        new.owned = np.zeros(new.size, dtype=np.bool_)
        new.source = source
        self._cores.append(new)
        self._cores.sort(key=lambda c: c.start)
        return True

    def _enter(self, new: SessionCore, envs: list[int]) -> None:
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
            reply = new.conn.call("Reset", request, timeout=self._quick())
            first = new.note(Batch.from_pb(reply))
        except ServiceError:
            return  # its server is going: the transfer is dropped at the next failover
        batch = new.last.splice(first, mask)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            old = new.source.last.slice(new.start - new.source.start, new.stop - new.source.start)
            batch = batch.splice(old, mask, OUTCOME + FINAL)
        else:
            batch = batch.splice(Batch(new.size, {}), mask, OUTCOME)
        ones = Batch(new.size, {"reset": np.ones(new.size, np.bool_)})
        batch = batch.splice(ones, mask, ("reset",))
        new.last = batch
        for i in envs:
            new.source.disown(i, i + 1)
        new.own(envs)
        self._moves += len(envs)

    def _tidy(self) -> None:
        """Closes the sessions whose environments have all moved, and ends the transfers that
        are done or whose source is gone (a failover)."""
        for core in list(self._cores):
            if core.source is not None:
                if core.owned is None:
                    core.source = None
                elif core.source not in self._cores or not any(
                    core.source.holds(i) for i in range(core.start, core.stop)
                ):
                    core.source, core.entering = None, set()
            if core.load == 0 and core.source is None:
                core.close()
                self._cores.remove(core)
        self._cores.sort(key=lambda c: c.start)  # what _batches' common case relies on

    def _complete_transfers(self) -> None:
        """A full reset starts every episode: the transfers in progress are done at once."""
        for new in [c for c in self._cores if c.source is not None]:
            envs = [i for i in range(new.start, new.stop) if new.source.holds(i)]
            for i in envs:
                new.source.disown(i, i + 1)
            new.own(envs)
            new.entering = set()
        self._tidy()

    def _hand_over(self, core: SessionCore, i: int, dest: int, cut: bool) -> bool:
        """Environment ``i`` of ``core`` moves to a new session on server ``dest`` (created
        and reset now; unseeded: the new server draws the episode's seed, as an autoreset
        does): its Batch of this step becomes the new core's (:func:`handover`). False when
        ``dest`` cannot take it now (it drains, is full or unreachable): it stays, for now."""
        opened = self._session_on(dest, i, i + 1)
        if opened is None:
            return False
        new, first = opened
        ended = core.last.slice(i - core.start, i - core.start + 1)
        new.last, new.pending = handover(ended, first, self.autoreset_mode, cut)
        new.reconnected = cut
        core.disown(i, i + 1)
        self._cores.append(new)
        self._cores.sort(key=lambda c: c.start)
        self._moves += 1
        return True

    def action_masks(self) -> np.ndarray:
        """``(N, 57) bool``: the actions that have an effect in each environment's current state
        (what sb3-contrib's MaskablePPO asks for; ``info["action_mask"]`` holds the same)."""
        self._check_idle("action_masks()")
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before action_masks()")
        return join(self._batches())["action_masks"].copy()

    def _decode_step(self, batches: list[Batch]):
        n = self.num_envs
        batch = join(batches)
        f = batch.fields
        obs, info = decode(batch, self.expert)
        rewards = f["rewards"].astype(np.float64)
        terminated = f["terminated"].copy()
        truncated = f["truncated"].copy()
        reset = f.get("reset")
        resets = reset is not None and reset.any()
        # Every step's info has reset's keys (TorchRL reads them once): each environment's
        # episode seed, as a SyncVectorEnv of DinerDashEnv reports it.
        ended_seeds = self._seeds
        if resets:
            self._seeds = np.where(reset, batch["seeds"].astype(np.int64), self._seeds)
        info["seed"], info["_seed"] = self._seeds.copy(), np.ones(n, np.bool_)
        if resets:
            reset = reset.copy()
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                final, final_info = decode(batch, self.expert, "final_", reset)
                final_info["seed"] = np.where(reset, ended_seeds, 0)
                final_info["_seed"] = reset.copy()
                final_obs = np.full(n, None, dtype=object)
                for i in np.flatnonzero(reset):  # only the environments that just ended
                    final_obs[i] = final[i]
                info["final_obs"] = final_obs
                info["_final_obs"] = reset.copy()
                info["final_info"] = final_info
                info["_final_info"] = reset.copy()
        if any(c.reconnected for c in self._cores):
            lost = np.zeros(n, dtype=np.bool_)
            for core in self._cores:
                if core.reconnected:
                    for lo, hi in core.runs():
                        lost[lo:hi] = True
                    core.reconnected = False
            info["reconnected"] = lost
            info["_reconnected"] = lost.copy()
        return obs, rewards, terminated, truncated, info

    def render(self) -> tuple[Any, ...] | None:
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='ansi' or 'rgb_array'"
            )
            return None
        self._check_idle("render()")
        if self.render_mode == "ansi":
            self._check_open("render()")
            return tuple(
                core.render_text(i - core.start, self.ansi_color)
                for lo, hi, core in self._pieces()
                for i in range(lo, hi)
            )
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before render()")
        obs, info = decode(join(self._batches()), self.expert)
        lives = self.spec_proto.config.lives
        return tuple(
            _render.draw(
                obs[i], score=int(info["score"][i]), lost=int(info["lost"][i]), lives=lives
            )
            for i in range(self.num_envs)
        )

    def _close_sessions(self) -> None:
        for core in self._cores:
            core.close()

    def close_extras(self, **kwargs: Any) -> None:
        """Closes the sessions (and the local server, if this env started one). A later full
        ``reset()`` opens new sessions; other calls raise :class:`~dinerdash.EnvClosed`."""
        if not self._closed:
            self._pending = False  # the cores' threads end as the sessions close
            if self._membership is not None:
                self._membership.close()
                self._membership = None
            self._close_sessions()
            self._endpoint.close()
            self._closed = True


def _ready(future):
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


def _interrupted(old: SessionCore, new: SessionCore) -> Batch:
    """A moved core's Batch for the step in which its server was given up: its environments'
    episodes end truncated in their last state (``old.last``), and the new session's first
    Batch (an unseeded Reset: the new server draws each episode's seed) is the autoreset, as
    after a reconnect."""
    first = Batch.from_pb(new.conn.call("Reset", pb.ResetRequest(session_id=new.session_id)))
    last = old.last.slice(new.start - old.start, new.stop - old.start)
    return new.interrupt(last, first)
