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
(:mod:`dinerdash._membership`): a draining server's environments move off it at once, and a
given-up server that answers again, or a DNS name's new replica, is given environments until the
loads differ by at most one, every move by Snapshot and Restore between two steps: exact, the
trajectories those of an undisturbed run (:mod:`dinerdash._fleet`).

This module is the Gymnasium adapter (arguments, autoreset modes, infos, the ``VectorEnv``
API); the servers and sessions are the :class:`~dinerdash._fleet.Fleet`'s.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import AlreadyPendingCallError, NoAsyncCallError
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ._arguments import (
    RENDER_MODES,
    Config,
    check_options,
    make_arrivals,
    make_config,
)
from ._batch import Batch, decode, join
from ._endpoint import Endpoint
from ._fleet import Fleet
from ._proto import pb
from ._session import (
    SessionCore,
    SessionOwner,
    check_actions,
)
from .connection import ConnectOptions
from .errors import (
    EnvClosed,
    InvalidArgument,
)
from .game import observation_space

__all__ = ["DinerDashVectorEnv"]


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
    _batched = True

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
        self.num_envs = int(num_envs)
        self._take_arguments(address, expert, render_mode, ansi_color, connect, connection)
        config = make_config(config)
        if max_episode_steps is not None:
            cfg = pb.GameConfig()
            if config is not None:
                cfg.CopyFrom(config)
            cfg.time_limit = int(max_episode_steps)
            config = cfg
        self.failover_after = self._options.failover_after
        self._settings = self._settings_for(
            num_envs=self.num_envs,
            autoreset_mode=mode,
            config=config,
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
        """Opens the fleet: connects and creates one session per server (at construction, and
        at a reset after close)."""
        self._fleet = Fleet(self._options, self._settings)
        self.spec_proto: pb.Spec = self._fleet.spec
        #: A step_async() was sent and step_wait() has not collected it yet.
        self._pending = False
        self._seeds = np.zeros(self.num_envs, np.int64)  # each environment's episode seed
        self._everyone = np.ones(self.num_envs, np.bool_)  # copied for each step's `_key` masks
        self._closed = False
        self.closed = False  # Gymnasium's flag: close() calls close_extras only when False

    @property
    def fleet(self) -> Fleet:
        """The servers and sessions this env steps (:class:`~dinerdash._fleet.Fleet`; its
        ``cores`` are the sessions, in environment order, each with its ``transport``). For the
        package's bench and the tests that look inside a step; not a stable API."""
        return self._fleet

    @property
    def _cores(self) -> list[SessionCore]:
        """The fleet's sessions, in environment order."""
        return self._fleet.cores

    @property
    def _endpoint(self) -> Endpoint:
        return self._fleet.endpoint

    @property
    def addresses(self) -> list[str]:
        """The servers serving now, in the order of the first environments they hold (after a
        failover a server may hold several slices; the servers given up are left out)."""
        return list(dict.fromkeys(c.conn.address for c in self._cores))

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
    def moves(self) -> int:
        """Environments moved to another server by Snapshot and Restore (off a draining server,
        onto a server taken in, or to even the loads), each exactly as it was. Not counted: a
        failover's (their episodes restart) and those a server refused to restore (another
        snapshot version: their episodes restart too)."""
        return self._fleet.moves

    @property
    def env_slices(self) -> list[tuple[str, slice]]:
        """Which server holds which environments: one entry per contiguous run of a session's
        environments, in environment order (after a failover a server holds several)."""
        return [(c.conn.address, slice(c.start, c.stop)) for c in self._cores]

    @property
    def session_ids(self) -> list[str | None]:
        return [c.session_id for c in self._cores]

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
        called = self._fleet.reset(given, mask)
        batch = join(self._fleet.batches())
        obs, info = decode(batch, self.expert)
        info["seed"] = batch["seeds"].astype(np.int64)  # as SyncVectorEnv; torch has no uint64
        info["_seed"] = batch["reset"] & called
        self._seeds = np.where(info["_seed"], info["seed"], self._seeds)
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
        if self._fleet.blocking():
            return self.decode_step(self._fleet.step(wire))
        self._start(wire)
        return self.decode_step(self._finish())

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
            if not all(core.step_ready(deadline) for core in self._cores if core.in_flight()):
                raise multiprocessing.TimeoutError(
                    f"step_wait(): no reply within {timeout:g} s; the step is still "
                    "pending, call step_wait() again"
                )
        return self.decode_step(self._finish())

    def _check_idle(self, what: str) -> None:
        if self._pending:
            raise AlreadyPendingCallError(
                f"{what} while a step_async() awaits its step_wait(); call step_wait() first",
                "step",
            )

    def _start(self, wire: np.ndarray) -> None:
        self._fleet.start(wire)
        self._pending = True

    def _finish(self) -> list[Batch]:
        """Every core's Batch of the pending step (:meth:`Fleet.finish
        <dinerdash._fleet.Fleet.finish>`); an interrupted wait (Ctrl-C) leaves the step pending,
        to be collected by ``step_wait()``."""
        self._fleet.wait()
        self._pending = False
        return self._fleet.finish()

    def action_masks(self) -> np.ndarray:
        """``(N, 57) bool``: the actions that have an effect in each environment's current state
        (what sb3-contrib's MaskablePPO asks for; ``info["action_mask"]`` holds the same)."""
        self._check_idle("action_masks()")
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before action_masks()")
        return join(self._fleet.batches())["action_masks"].copy()

    def decode_step(self, batches: list[Batch]):
        """The step's ``(obs, rewards, terminated, truncated, info)`` from the sessions' replies
        (``batches``, in environment order): what :meth:`step` and :meth:`step_wait` end in. It
        advances the env's episode seeds, so only the bench calls it besides them, to time it."""
        n = self.num_envs
        batch = join(batches)
        everyone = self._everyone
        obs, info = decode(batch, self.expert, present=everyone)
        rewards = batch["rewards"].astype(np.float64)
        terminated = batch["terminated"].copy()
        truncated = batch["truncated"].copy()
        reset = batch.get("reset")
        # count_nonzero: a quarter of any()'s time on a (256,) bool.
        resets = reset is not None and np.count_nonzero(reset) > 0
        # Every step's info has reset's keys (TorchRL reads them once): each environment's
        # episode seed, as a SyncVectorEnv of DinerDashEnv reports it.
        ended_seeds = self._seeds
        if resets:
            self._seeds = np.where(reset, batch["seeds"].astype(np.int64), self._seeds)
        info["seed"], info["_seed"] = self._seeds.copy(), everyone.copy()
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
        cut = [c for c in self._cores if c.reconnected]
        if cut:
            lost = np.zeros(n, dtype=np.bool_)
            for core in cut:
                core.take_reconnected()
                lost[core.start : core.stop] = True
            info["reconnected"] = lost
            info["_reconnected"] = lost.copy()
        return obs, rewards, terminated, truncated, info

    def _shown(self) -> tuple[Any, Any, Any]:
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before render()")
        obs, info = decode(join(self._fleet.batches()), self.expert)
        return obs, info["score"], info["lost"]

    def close_extras(self, **kwargs: Any) -> None:
        """Closes the sessions (and the local server, if this env started one). A later full
        ``reset()`` opens new sessions; other calls raise :class:`~dinerdash.EnvClosed`."""
        if not self._closed:
            self._pending = False  # the cores' threads end as the sessions close
            self._fleet.close()
            self._closed = True
